"""Hostile-client load for the buffered budget: N stalled streams (read one batch, then stop
reading; prefetch 64, all fields) while one fast client pulls; prints server RSS over time,
the fast rate, then RSS after the stalled clients leave (the figures of docs/robustness.md,
"Stalled and hostile clients").

Usage (the project's Python env, `eval "$(bash tools/setup_python.sh)"`):
    mpiflow serve --addr 127.0.0.1:50300 --metrics-addr 127.0.0.1:50301 --size 320x240 \
        --workers 2 --max-buffered-mb 512 &
    $MPIFLOW_PYTHON tools/stall_clients.py 127.0.0.1:50300 $! 127.0.0.1:50301 [STALLED=30] [SECONDS=60]
"""
import sys, time, threading, re, urllib.request
import grpc
from mpiflow._proto import mpiflow_pb2 as pb, mpiflow_pb2_grpc as pbg

addr, pid, metrics = sys.argv[1], int(sys.argv[2]), sys.argv[3]
n_stalled = int(sys.argv[4]) if len(sys.argv) > 4 else 30
secs = float(sys.argv[5]) if len(sys.argv) > 5 else 60
ALL = list(range(1, 10))

def rss():
    for l in open(f"/proc/{pid}/status"):
        if l.startswith("VmRSS:"):
            return int(l.split()[1]) // 1024

def buffered():
    try:
        t = urllib.request.urlopen(f"http://{metrics}/metrics", timeout=2).read().decode()
        m = re.search(r"^mpiflow_buffered_bytes (\d+)", t, re.M)
        return int(m.group(1)) >> 20 if m else -1
    except Exception:
        return -1

def fast(seconds, out):
    ch = grpc.insecure_channel(addr, options=[("grpc.max_receive_message_length", 1 << 30)])
    stub = pbg.MpiFlowStub(ch)
    n = 0; t0 = time.time()
    it = stub.StreamSamples(pb.StreamRequest(spec=pb.SampleSpec(seed=999, fields=[1, 2, 3, 4]), prefetch=4))
    for b in it:
        n += len(b.samples)
        if time.time() - t0 > seconds:
            break
    it.cancel()
    out.append(n / (time.time() - t0))
    ch.close()

solo = []
fast(15, solo)
print(f"idle RSS {rss()} MiB, solo fast rate {solo[0]:.2f} samples/s", flush=True)
chans, its = [], []
for i in range(n_stalled):
    ch = grpc.insecure_channel(addr, options=[("grpc.max_receive_message_length", 1 << 30)])
    it = pbg.MpiFlowStub(ch).StreamSamples(pb.StreamRequest(spec=pb.SampleSpec(seed=i, fields=ALL), prefetch=64))
    next(it)
    chans.append(ch); its.append(it)
print(f"{n_stalled} stalled streams open", flush=True)
res = []
th = threading.Thread(target=fast, args=(secs, res)); th.start()
t0 = time.time(); peak = 0
while th.is_alive():
    r = rss(); peak = max(peak, r)
    print(f"t={time.time()-t0:5.0f}s RSS {r} MiB buffered {buffered()} MiB", flush=True)
    th.join(5)
print(f"with stalled: fast rate {res[0]:.2f} samples/s ({res[0]/solo[0]*100:.0f}% of solo), peak RSS {peak} MiB", flush=True)
for it in its: it.cancel()
for ch in chans: ch.close()
for _ in range(6):
    time.sleep(5)  # measurement interval, not synchronisation
    print(f"after leaving: RSS {rss()} MiB buffered {buffered()} MiB", flush=True)
