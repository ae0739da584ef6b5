#!/usr/bin/env python3
"""Throughput of the Python client: samples/s delivered into Python as numpy arrays, optionally
next to `mpiflow pull` (the Rust client) on the same server with the same request.

    python clients/python/bench_client.py --addr 127.0.0.1:50051 --count 60 --pull target/release/mpiflow
    python clients/python/bench_client.py --spawn target/release/mpiflow --count 60 --pull target/release/mpiflow

`--spawn BIN` starts `BIN serve` on a free loopback port for the run. Modes: `stream`
(FlowStream: decode in the consuming thread), `prefetch` (the same behind the Prefetcher's
background thread, what MPIFlowDataset does), `dataset` (MPIFlowDataset dicts: float32 CHW,
i.e. RAFT-ready). After one warm-up of `--warmup` samples, `--rounds` rounds each run every
client once on `--count` new indices (interleaved, so a drift in load hits all alike). Prints the
mean samples/s per client and the ratio python / pull (goal: >= 0.9).
"""
from __future__ import annotations

import argparse
import json
import re
import subprocess
import sys
import time
from pathlib import Path

HERE = Path(__file__).resolve().parent
sys.path.insert(0, str(HERE))  # the package in the tree (also when not installed)
import mpiflow  # noqa: E402
from mpiflow.stream import Prefetcher  # noqa: E402


def parse_crop(s):
    if not s:
        return None
    w, h = s.lower().split("x")
    return int(w), int(h)


def run_python(a, mode: str, start: int, warmup: int = 0) -> dict:
    crop = parse_crop(a.crop)
    kw = dict(seed=a.seed, crop=crop, lz4=a.lz4, flow_dtype="f16" if a.f16 else "f32",
              batch_size=a.batch_size, server_prefetch=a.prefetch)
    nbytes = 0
    n = 0
    with mpiflow.Client(a.addr, timeout=180) as client:
        if mode == "dataset":
            ds = mpiflow.MPIFlowDataset(a.addr, start_index=start, count=a.count + warmup, rank=0,
                                        world_size=1, prefetch=8, crop=crop, lz4=a.lz4,
                                        flow_dtype="f16" if a.f16 else "f32", batch_size=a.batch_size,
                                        server_prefetch=a.prefetch, seed=a.seed)
            it = iter(ds)
        else:
            st = client.stream(start_index=start, count=a.count + warmup, **kw)
            it = Prefetcher(st, 8, on_close=st.close) if mode == "prefetch" else iter(st)
        for _ in range(warmup):
            next(it)
        t0 = time.perf_counter()
        first = None
        for item in it:
            if first is None:
                first = time.perf_counter() - t0
            arrays = item.values() if isinstance(item, dict) else item.tensors.values()
            nbytes += sum(v.nbytes for v in arrays if hasattr(v, "nbytes"))
            n += 1
        dt = time.perf_counter() - t0
    return {"client": f"python-{mode}", "samples": n, "seconds": round(dt, 3),
            "samples_per_s": round(n / dt, 3), "MB_per_s_decoded": round(nbytes / dt / 1e6, 2)}


def run_pull(a, start: int) -> dict:
    argv = [a.pull, "pull", "--addr", a.addr, "--count", str(a.count), "--seed", str(a.seed),
            "--start-index", str(start), "--batch-size", str(a.batch_size), "--prefetch", str(a.prefetch)]
    if a.crop:
        argv += ["--crop", a.crop]
    if a.lz4:
        argv.append("--lz4")
    if a.f16:
        argv.append("--f16")
    t0 = time.perf_counter()
    r = subprocess.run(argv, capture_output=True, text=True, timeout=1800)
    dt = time.perf_counter() - t0
    if r.returncode != 0:
        raise SystemExit(f"mpiflow pull failed ({r.returncode}): {r.stderr.strip()[-500:]}")
    m = re.search(r"([\d.]+) samples/s", r.stdout)
    if not m:
        raise SystemExit(f"cannot read samples/s from: {r.stdout.strip()}")
    return {"client": "mpiflow-pull", "samples": a.count, "samples_per_s": float(m.group(1)),
            "wall_seconds": round(dt, 3), "summary": r.stdout.strip().splitlines()[0]}


def main() -> int:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--addr", default="127.0.0.1:50051")
    ap.add_argument("--spawn", metavar="BIN", help="start `BIN serve` on a free port for the run")
    ap.add_argument("--pull", metavar="BIN", help="also run `BIN pull` with the same request")
    ap.add_argument("--count", type=int, default=60)
    ap.add_argument("--warmup", type=int, default=16, help="samples pulled once before measuring")
    ap.add_argument("--rounds", type=int, default=2, help="measured runs of each client, interleaved")
    ap.add_argument("--modes", default="stream,prefetch,dataset")
    ap.add_argument("--crop", default=None, help="WxH")
    ap.add_argument("--lz4", action="store_true")
    ap.add_argument("--f16", action="store_true")
    ap.add_argument("--batch-size", type=int, default=1)
    ap.add_argument("--prefetch", type=int, default=0, help="server-side prefetch per stream")
    ap.add_argument("--seed", type=int, default=0)
    ap.add_argument("--json", action="store_true", help="one JSON object per line")
    a = ap.parse_args()

    proc = None
    if a.spawn:
        proc = subprocess.Popen([a.spawn, "serve", "--addr", "127.0.0.1:0"], stdout=subprocess.PIPE,
                                stderr=subprocess.DEVNULL, text=True)
        line = proc.stdout.readline()
        if not line.startswith("mpiflow serving on "):
            raise SystemExit(f"unexpected first line from serve: {line!r}")
        a.addr = line.strip().rsplit(" ", 1)[1]
    try:
        results = []
        start = 1_000_000  # away from the indices other runs may have warmed
        # One warm-up for everything (the server's scene cache fills on first use of a source).
        if a.warmup:
            saved, a.count = a.count, a.warmup
            run_python(a, "stream", start)
            a.count = saved
            start += 2 * a.warmup
        modes = [m for m in a.modes.split(",") if m]
        for _ in range(a.rounds):
            if a.pull:
                results.append(run_pull(a, start))
                start += a.count
            for mode in modes:
                results.append(run_python(a, mode, start, warmup=0))
                start += a.count
        by = {}
        for r in results:
            by.setdefault(r["client"], []).append(r["samples_per_s"])
        pull = sum(by["mpiflow-pull"]) / len(by["mpiflow-pull"]) if "mpiflow-pull" in by else None
        for name, rates in by.items():
            mean = sum(rates) / len(rates)
            r = {"client": name, "samples_per_s": round(mean, 3), "runs": [round(x, 3) for x in rates],
                 "count": a.count}
            if pull and name != "mpiflow-pull":
                r["vs_pull"] = round(mean / pull, 3)
            if a.json:
                print(json.dumps(r))
            else:
                extra = f"  ({r['vs_pull']:.0%} of pull)" if "vs_pull" in r else ""
                print(f"{name:>16}: {mean:8.2f} samples/s over {len(rates)} run(s) of {a.count}{extra}")
    finally:
        if proc is not None:
            proc.terminate()
            proc.wait(30)
    return 0


if __name__ == "__main__":
    sys.exit(main())
