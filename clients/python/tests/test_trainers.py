"""The trainers people run: examples/train_torchvision_raft.py (torchvision's raft_small, a model
nobody here wrote) trained for a few steps against the real server, from the stream, from the
map-style dataset with shuffle=True, under two ranks with DistributedSampler, and with a server
it spawns itself. Skipped where torch or torchvision is absent (CI)."""
from __future__ import annotations

import math
import os
import re
import socket
import subprocess
import sys
from pathlib import Path
from typing import Dict, List, Optional

import pytest

pytest.importorskip("torch")
pytest.importorskip("torchvision")

from conftest import REPO, real_binary  # noqa: E402

EXAMPLE = REPO / "examples" / "train_torchvision_raft.py"
# Small and quick: the smallest crop RAFT's correlation pyramid takes, two refinements.
FAST = ["--crop", "160x128", "--iters", "2"]
RUN_TIMEOUT = 900

STEP = re.compile(
    r"^step (\d+): loss (\S+), epe (\S+) px, data wait (\S+) s, step (\S+) s, indices \[([0-9, ]*)\]$"
)
SUMMARY = re.compile(
    r"^rank (\d+): data-wait fraction (\S+) \((\S+) s of (\S+) s, steps 1\.\.(\d+)\); "
    r"(\S+) samples/s; loss (\S+) -> (\S+); wall (\S+) s incl\. start-up$"
)


def run(args: List[str], env: Optional[Dict[str, str]] = None) -> subprocess.Popen:
    e = dict(os.environ, PYTHONUNBUFFERED="1", **(env or {}))
    return subprocess.Popen([sys.executable, str(EXAMPLE), *args], cwd=str(REPO), env=e,
                            stdout=subprocess.PIPE, stderr=subprocess.STDOUT, text=True)


def finish(proc: subprocess.Popen) -> str:
    try:
        out, _ = proc.communicate(timeout=RUN_TIMEOUT)
    except subprocess.TimeoutExpired:
        proc.kill()
        out, _ = proc.communicate()
        pytest.fail(f"the example ran past {RUN_TIMEOUT} s:\n{out[-4000:]}")
    assert proc.returncode == 0, out[-4000:]
    return out


def parse(out: str, steps: int, batch: int) -> dict:
    """Every step line and the summary, checked for what any run must show."""
    lines = out.splitlines()
    got = [m for m in map(STEP.match, lines) if m]
    assert [int(m[1]) for m in got] == list(range(steps)), out[-4000:]
    losses = [float(m[2]) for m in got]
    assert all(math.isfinite(v) and v >= 0 for v in losses), losses
    indices = [[int(i) for i in m[6].split(",")] for m in got]
    assert all(len(ix) == batch for ix in indices)
    summaries = [m for m in map(SUMMARY.match, lines) if m]
    assert len(summaries) == 1, out[-4000:]
    s = summaries[0]
    frac, wait, total = float(s[2]), float(s[3]), float(s[4])
    rate = float(s[6])
    assert 0.0 <= frac <= 1.0 and 0.0 <= wait <= total and total > 0
    # The fraction is the printed wait over the printed total (both rounded to 0.01 s).
    assert abs(frac - wait / total) <= 0.01 / total + 1e-4
    assert int(s[5]) == steps - 1 and rate > 0 and math.isfinite(rate)
    # The summary's first and last losses are those of the first and last step.
    assert float(s[7]) == pytest.approx(losses[0], abs=1e-4)
    assert float(s[8]) == pytest.approx(losses[-1], abs=1e-4)
    return {"rank": int(s[1]), "losses": losses, "indices": indices, "fraction": frac}


@pytest.fixture
def real(server):
    if server.kind != "real":
        pytest.skip("the example trains on the real server's frames")
    return server


def test_raft_small_trains_from_the_stream(real):
    steps, batch = 3, 2
    out = finish(run(["--addr", real.address, "--steps", str(steps), "--batch-size", str(batch),
                      "--workers", "2", *FAST]))
    r = parse(out, steps, batch)
    flat = sum(r["indices"], [])
    # Two DataLoader workers share the stream: no index twice, all from the first batches.
    assert len(set(flat)) == len(flat)
    assert max(flat) < 2 * steps * batch


def test_raft_small_from_the_map_dataset_with_shuffle(real):
    length, batch = 4, 2
    steps = 2 * length // batch  # two epochs
    out = finish(run(["--addr", real.address, "--dataset", "map", "--length", str(length),
                      "--steps", str(steps), "--batch-size", str(batch), "--workers", "1", *FAST]))
    r = parse(out, steps, batch)
    per_epoch = length // batch
    for e in range(2):  # DataLoader(shuffle=True): every epoch a permutation of the dataset
        epoch = sum(r["indices"][e * per_epoch:(e + 1) * per_epoch], [])
        assert sorted(epoch) == list(range(length))


def free_port() -> int:
    with socket.socket() as s:
        s.bind(("127.0.0.1", 0))
        return s.getsockname()[1]


def test_two_ranks_with_distributed_sampler_split_the_epoch(real):
    length, world = 4, 2
    steps = length // world  # batch 1: one epoch per rank
    env = {"WORLD_SIZE": str(world), "MASTER_ADDR": "127.0.0.1", "MASTER_PORT": str(free_port())}
    args = ["--addr", real.address, "--dataset", "map", "--length", str(length), "--steps",
            str(steps), "--batch-size", "1", "--workers", "1", "--threads", "1", *FAST]
    procs = [run(args, dict(env, RANK=str(r), LOCAL_RANK=str(r))) for r in range(world)]
    results = [parse(finish(p), steps, 1) for p in procs]
    assert sorted(r["rank"] for r in results) == list(range(world))
    seen = [sum(r["indices"], []) for r in results]
    # DistributedSampler: the ranks' shards are disjoint and together the whole epoch.
    assert not set(seen[0]) & set(seen[1])
    assert sorted(seen[0] + seen[1]) == list(range(length))


def test_spawned_server(real):
    exe = real_binary()
    assert exe is not None
    out = finish(run(["--spawn", "--size 320x240 --workers 1", "--steps", "2", "--batch-size", "1",
                      "--workers", "0", *FAST], {"MPIFLOW_BIN": str(exe)}))
    assert re.search(r"^spawned mpiflow serve --size 320x240 --workers 1 on 127\.0\.0\.1:\d+ ", out, re.M)
    parse(out, 2, 1)
