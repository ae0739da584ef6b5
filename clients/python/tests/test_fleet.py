"""A local fleet: three `mpiflow serve` replicas on loopback, two trainer ranks (rank 0 and 1 of
world_size 2, one thread each, MPIFlowDataset over all three addresses), replicas SIGKILLed
mid-stream and one restarted on its port.

What happens (a rank's stream starts on replica rank % 3: rank 0 on A, rank 1 on B; C is spare):
1. both ranks stream; once each has KILL_AT samples, B is SIGKILLed -> rank 1 resumes on
   another replica (C, the next in the list);
2. once it has, B is restarted on the same port while both ranks keep streaming;
3. once every rank has FOLLOW samples after the first kill, A and C are SIGKILLed together:
   the streams must resume on B, the restarted replica (the test checks where they resumed,
   from the client's "resuming rank R at index I on ADDR" log). A rank reaching HOLD_AT
   before this waits there (like a trainer in a checkpoint), so that its share is not used up;
4. each rank has received exactly its indices rank, rank + 2, ... < 2 * N (in order, no gap,
   no repeat), and some of them (the first, the first after each failover, the last) equal
   GetSample of the same index asked of B, tensor for tensor.

The stall is measured where the trainer sees it: for each sample, how long the training loop
waited for it after it had the one before (the loop does no work, so this is the gap between
consecutive samples; time spent held at HOLD_AT is not counted). Reported per rank: the longest
gap among the first FOLLOW samples after each kill, against the median, mean and maximum of the
other gaps (the feed is bursty: the server makes a stream's samples a few at a time, so the
median is small and the mean is the inverse of the rate). Also: how long each restart took and
from each kill to the first stream resumed elsewhere. The figures are printed (`pytest -s`) and
written to `fleet_stall.json` in the test's tmp dir (and appended as one JSON line to
$MPIFLOW_FLEET_REPORT when set, to collect several runs).
"""
from __future__ import annotations

import json
import logging
import os
import re
import statistics
import threading
import time
from typing import Dict, List, Optional

import numpy as np

import mpiflow
from mpiflow.dataset import consumer_indices

WORLD = 2
N = 60  # samples per rank
KILL_AT = 8  # samples per rank before the first kill
# A rank that gets here before B is back waits, so that some of its share is left: more samples
# than the stream can hold on its way (the gRPC windows grow with the rate; 34 crops are 10 MB).
HOLD_AT = N - 34
FOLLOW = 5  # samples after a kill in which its stall is looked for
SEED = 11
FIELDS = ["image1", "image2", "flow", "valid", "occlusion"]
RESUME_RE = re.compile(r"resuming rank (\d+) at index (\d+) on (\S+)")


class _Rank(threading.Thread):
    """One trainer rank: iterates its MPIFlowDataset as fast as it can, recording each sample
    and the time the loop received it."""

    def __init__(self, rank: int, addresses: str, crop, hold: threading.Event):
        super().__init__(name=f"trainer-rank{rank}", daemon=True)
        self.rank = rank
        self.ds = mpiflow.MPIFlowDataset(
            addresses, seed=SEED, count=WORLD * N, rank=rank, world_size=WORLD, crop=crop,
            fields=FIELDS, prefetch=2, timeout=60, retry_timeout=60,
        )
        self.indices: List[int] = []
        self.times: List[float] = []  # when the loop received each sample
        self.waits: List[float] = []  # how long it waited for it (the gap to the one before)
        self.hold = hold
        self.samples: Dict[int, dict] = {}
        self.error: Optional[BaseException] = None

    def run(self) -> None:
        try:
            it = iter(self.ds)
            while True:
                if len(self.indices) >= HOLD_AT:
                    self.hold.wait()  # not counted as a gap
                t_ask = time.monotonic()
                try:
                    d = next(it)
                except StopIteration:
                    break
                t = time.monotonic()
                self.times.append(t)
                self.waits.append(t - t_ask)
                self.indices.append(int(d["index"]))
                self.samples[int(d["index"])] = d
        except BaseException as e:  # re-raised in the test
            self.error = e

    def count(self) -> int:
        return len(self.indices)


def _wait(cond, what: str, ranks: List[_Rank], timeout: float = 60.0) -> None:
    deadline = time.monotonic() + timeout
    while not cond():
        for r in ranks:
            if r.error is not None:
                raise AssertionError(f"rank {r.rank} failed while waiting for {what}") from r.error
        if all(not r.is_alive() for r in ranks):
            raise AssertionError(f"all ranks ended before {what}")
        if time.monotonic() > deadline:
            raise AssertionError(f"timed out waiting for {what}: {[r.count() for r in ranks]}")
        time.sleep(0.005)


def _after(r: _Rank, t_event: float) -> List[int]:
    """Positions of the first FOLLOW samples the rank received after t_event."""
    return [k for k, t in enumerate(r.times) if t > t_event][:FOLLOW]


def _stall(r: _Rank, t_event: float) -> Dict[str, float]:
    """The longest gap between consecutive samples among the first FOLLOW received after
    t_event (the gap spanning the event included), and how long those FOLLOW took."""
    after = _after(r, t_event)
    gaps = [r.waits[k] for k in after if k > 0]
    return {
        "max_gap_s": round(max(gaps), 4) if gaps else 0.0,
        "follow_s": round(r.times[after[-1]] - t_event, 4) if after else float("nan"),
    }


def _resumes(records, t0_wall: float) -> List[dict]:
    out = []
    for rec in records:
        m = RESUME_RE.search(rec.getMessage())
        if m:
            out.append({"rank": int(m.group(1)), "index": int(m.group(2)), "address": m.group(3),
                        "wall": rec.created - t0_wall})
    return out


def test_three_replicas_two_ranks_sigkill_and_restart(spawn, caplog, tmp_path):
    caplog.set_level(logging.INFO, logger="mpiflow")
    a, b, c = spawn(), spawn(), spawn()
    crop = a.crop
    names = {a.address: "A", b.address: "B", c.address: "C"}
    hold = threading.Event()
    ranks = [_Rank(r, ",".join([a.address, b.address, c.address]), crop, hold) for r in range(WORLD)]
    t0, t0_wall = time.monotonic(), time.time()
    for r in ranks:
        r.start()
    events: Dict[str, float] = {}

    # 1. SIGKILL B (rank 1's replica) mid-stream.
    _wait(lambda: all(r.count() >= KILL_AT for r in ranks), "the first samples", ranks)
    events["kill_B"] = time.monotonic()
    b.kill()
    # 2. Restart B on its port once both ranks go on (on A and C); a rank already waiting at
    # HOLD_AT (rank 0 can get there before rank 1 has KILL_AT samples) gets nothing more now.
    _wait(lambda: any(x["rank"] == 1 for x in _resumes(caplog.records, t0_wall))
          and all(len(_after(r, events["kill_B"])) >= 2 or r.count() >= HOLD_AT for r in ranks),
          "rank 1 resumed elsewhere", ranks)
    events["restart_B"] = time.monotonic()
    b.start()
    assert names.get(b.address) == "B"  # the same port
    events["B_ready"] = time.monotonic()
    # 3. Once the first kill's aftermath is measured (FOLLOW samples on every rank, or a rank
    # waiting at HOLD_AT), kill A and C together: the rest can only come from the restarted B.
    _wait(lambda: all(len(_after(r, events["kill_B"])) >= FOLLOW or r.count() >= HOLD_AT for r in ranks),
          "the first kill's aftermath", ranks)
    events["kill_A_C"] = time.monotonic()
    a.kill()
    c.kill()
    hold.set()
    for r in ranks:
        r.join(90)
        assert not r.is_alive(), f"rank {r.rank} did not finish ({r.count()} samples)"
        if r.error is not None:
            raise r.error
    t_end = time.monotonic()

    # Exactly once per rank, in order.
    for r in ranks:
        want = list(consumer_indices(0, r.rank, WORLD, WORLD * N))
        assert len(want) == N
        assert r.indices == want, f"rank {r.rank}: {r.indices}"

    # Where the streams resumed: rank 1 left B for another replica after the first kill, and
    # after the second kill the streams resumed on the restarted B. (A rank whose remaining
    # samples were all on their way already, in gRPC's receive window and the prefetch buffer,
    # had nothing left to resume; at least one rank must have resumed.)
    resumes = _resumes(caplog.records, t0_wall)
    for x in resumes:
        x["replica"] = names.get(x["address"], x["address"])
    t_kill1_wall = events["kill_B"] - t0
    t_kill2_wall = events["kill_A_C"] - t0
    first = [x for x in resumes if x["rank"] == 1 and t_kill1_wall <= x["wall"] < t_kill2_wall]
    assert first and first[0]["replica"] in ("A", "C"), resumes
    assert not [x for x in resumes if x["rank"] == 0 and x["wall"] < t_kill2_wall], resumes
    last = [x for x in resumes if x["wall"] >= t_kill2_wall]
    assert last and all(x["replica"] == "B" for x in last), resumes

    # Content: the samples equal GetSample of their index (asked of B, the only one left, for
    # samples most of which other replicas streamed).
    check = {0, N - 1}
    for x in resumes:
        check.add((x["index"] - x["rank"]) // WORLD)  # position in that rank's list
    client = mpiflow.Client(b.address, timeout=60)
    try:
        for r in ranks:
            for k in sorted(p for p in check if 0 <= p < N):
                i = r.indices[k]
                ref = mpiflow.to_raft_dict(client.get_sample(i, seed=SEED, crop=crop, crop_mode="random",
                                                            fields=FIELDS))
                got = r.samples[i]
                arrays = sorted(k2 for k2, v in ref.items() if isinstance(v, np.ndarray))
                assert arrays and set(arrays) >= {"img1", "img2", "flow", "valid", "occlusion"}, arrays
                for name in arrays:
                    assert got[name].dtype == ref[name].dtype and got[name].shape == ref[name].shape, name
                    np.testing.assert_array_equal(got[name], ref[name], err_msg=f"{name} of index {i}")
    finally:
        client.close()

    # The stall the training loop saw.
    report = {
        "kind": a.kind,
        "samples_per_rank": N,
        "crop": list(crop),
        "fields": FIELDS,
        "seconds": round(t_end - t0, 2),
        "restart_B_s": round(events["B_ready"] - events["restart_B"], 3),
        "events_s": {k: round(v - t0, 3) for k, v in events.items()},
        # from each kill to the first stream resumed elsewhere (detection + replica choice)
        "failover_s": {
            ev: round(min((x["wall"] for x in resumes if x["wall"] >= events[ev] - t0), default=float("nan"))
                      - (events[ev] - t0), 3)
            for ev in ("kill_B", "kill_A_C")
        },
        "resumes": [
            {"rank": x["rank"], "index": x["index"], "on": x["replica"], "at_s": round(x["wall"], 3)}
            for x in resumes
        ],
        "ranks": [],
    }
    for r in ranks:
        # Steady state: every gap but the first sample's and those right after the kills.
        near = set(_after(r, events["kill_B"])) | set(_after(r, events["kill_A_C"])) | {0}
        gaps = np.asarray([w for k, w in enumerate(r.waits) if k not in near])
        report["ranks"].append({
            "rank": r.rank,
            "median_gap_s": round(float(statistics.median(gaps)), 4),
            "mean_gap_s": round(float(gaps.mean()), 4),
            "max_steady_gap_s": round(float(gaps.max()), 4),
            "first_sample_s": round(r.waits[0], 4),  # a new stream on a fresh replica
            "gaps_ms": [round(w * 1e3) for w in r.waits],
            "kill_B": _stall(r, events["kill_B"]),
            "kill_A_C": _stall(r, events["kill_A_C"]),
        })
    (tmp_path / "fleet_stall.json").write_text(json.dumps(report, indent=2))
    if os.environ.get("MPIFLOW_FLEET_REPORT"):
        with open(os.environ["MPIFLOW_FLEET_REPORT"], "a") as f:
            f.write(json.dumps(report) + "\n")
    lines = [f"fleet ({a.kind}, {N}/rank, crop {crop[0]}x{crop[1]}, {report['seconds']} s; "
             f"B restarted in {report['restart_B_s']} s) -> {tmp_path / 'fleet_stall.json'}"]
    for x in report["ranks"]:
        lines.append(
            f"  rank {x['rank']}: gaps median {x['median_gap_s'] * 1e3:.0f} ms, mean "
            f"{x['mean_gap_s'] * 1e3:.0f} ms, max {x['max_steady_gap_s'] * 1e3:.0f} ms; after SIGKILL B max gap "
            f"{x['kill_B']['max_gap_s'] * 1e3:.0f} ms; after SIGKILL A+C max gap "
            f"{x['kill_A_C']['max_gap_s'] * 1e3:.0f} ms"
        )
    print("\n" + "\n".join(lines))
