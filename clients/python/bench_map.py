#!/usr/bin/env python3
"""Random access against streaming: samples/s of MPIFlowMapDataset fetched in shuffled batches
(`__getitems__`, one GetSamples call per batch, as torch's DataLoader does) against
MPIFlowDataset streaming, on the same server with the same options.

    python clients/python/bench_map.py --spawn target/release/mpiflow --count 96 --batch 8
    python clients/python/bench_map.py --addr 127.0.0.1:50051 --count 96 --batch 8 --workers 2

`--spawn BIN` starts `BIN serve` on a free loopback port for the run (`--serve-args` adds
flags). `--workers W` fetches the map dataset's batches from W threads, each with its own copy
of the dataset (own channel), batch k going to thread k % W as DataLoader workers do; 0 fetches
them one after the other in this thread. Each round runs both on `--count` new indices
(interleaved, so a drift in load hits both alike); prints samples/s of each and the ratio
map / stream (goal: >= 0.9).
"""
from __future__ import annotations

import argparse
import pickle
import random
import re
import subprocess
import sys
import threading
import time
from pathlib import Path

HERE = Path(__file__).resolve().parent
sys.path.insert(0, str(HERE))  # the package in the tree (also when not installed)
import mpiflow  # noqa: E402


def parse_crop(s):
    if not s:
        return None
    w, h = s.lower().split("x")
    return int(w), int(h)


def run_stream(a, start: int) -> float:
    ds = mpiflow.MPIFlowDataset(a.addr, start_index=start, count=a.count, rank=0, world_size=1,
                                prefetch=8, crop=parse_crop(a.crop), seed=a.seed, timeout=180)
    t0 = time.perf_counter()
    n = sum(1 for _ in ds)
    assert n == a.count, n
    return n / (time.perf_counter() - t0)


def run_map(a, start: int, rng: random.Random) -> float:
    ds = mpiflow.MPIFlowMapDataset(a.addr, a.count, start_index=start, crop=parse_crop(a.crop),
                                   seed=a.seed, timeout=180)
    order = list(range(a.count))
    rng.shuffle(order)
    batches = [order[i:i + a.batch] for i in range(0, len(order), a.batch)]
    workers = max(1, a.workers)
    copies = [pickle.loads(pickle.dumps(ds)) for _ in range(workers)]
    for c in copies:
        c.client()  # channels open before the clock starts, as in a DataLoader worker's first batch
    got = [0] * workers

    def work(w: int) -> None:
        for k, b in enumerate(batches):
            if k % workers == w:
                items = copies[w].__getitems__(b)
                assert [d["index"] - start for d in items] == b
                got[w] += len(items)

    t0 = time.perf_counter()
    if a.workers == 0:
        work(0)
    else:
        threads = [threading.Thread(target=work, args=(w,)) for w in range(workers)]
        for t in threads:
            t.start()
        for t in threads:
            t.join()
    dt = time.perf_counter() - t0
    for c in copies:
        c.close()
    assert sum(got) == a.count, got
    return a.count / dt


def main() -> int:
    p = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    p.add_argument("--addr", help="HOST:PORT of a running server")
    p.add_argument("--spawn", help="start BIN serve on a free port for the run")
    p.add_argument("--serve-args", default="", help="extra flags for the spawned server")
    p.add_argument("--count", type=int, default=96, help="samples per run")
    p.add_argument("--batch", type=int, default=8, help="indices per __getitems__ call")
    p.add_argument("--workers", type=int, default=0, help="threads fetching map batches (0: this one)")
    p.add_argument("--rounds", type=int, default=3)
    p.add_argument("--crop", default="", help="WxH")
    p.add_argument("--seed", type=int, default=0)
    a = p.parse_args()
    proc = None
    if a.spawn:
        proc = subprocess.Popen([a.spawn, "serve", "--addr", "127.0.0.1:0", *a.serve_args.split()],
                                stdout=subprocess.PIPE, stderr=subprocess.DEVNULL, text=True)
        for line in proc.stdout:
            m = re.match(r"mpiflow serving on (\S+)", line)
            if m:
                a.addr = m.group(1)
                break
    if not a.addr:
        p.error("give --addr or --spawn")
    try:
        mpiflow.Client(a.addr, timeout=180).close()  # SERVING
        # warm-up: the scene cache and the connections
        run_stream(argparse.Namespace(**{**vars(a), "count": a.batch}), 1_000_000)
        rng = random.Random(a.seed)
        rates = {"stream": [], "map": []}
        for r in range(a.rounds):
            base = 2 * r * a.count
            rates["stream"].append(run_stream(a, base))
            rates["map"].append(run_map(a, base + a.count, rng))
        mean = {k: sum(v) / len(v) for k, v in rates.items()}
        for k, v in rates.items():
            print(f"{k:6s} {mean[k]:7.2f} samples/s  (rounds: {', '.join(f'{x:.2f}' for x in v)})")
        print(f"map / stream = {mean['map'] / mean['stream']:.3f} "
              f"(batch {a.batch}, {a.workers} workers, {a.count} samples per run, crop {a.crop or 'none'})")
    finally:
        if proc is not None:
            proc.terminate()
            proc.wait(30)
    return 0


if __name__ == "__main__":
    sys.exit(main())
