#!/usr/bin/env python3
"""torchvision's RAFT (raft_small, untrained) trained from an mpiflow server, measured.

    python examples/train_torchvision_raft.py --addr 127.0.0.1:50051 --steps 60 \
        --batch-size 2 --crop 320x256

The model is `torchvision.models.optical_flow.raft_small(weights=None)` (torchvision's own
implementation), trained with RAFT's recipe: the sequence loss over every refinement (written
out below), AdamW, gradient clipping and the one-cycle schedule. Prints the loss of every step,
then the fraction of step time spent blocked in the DataLoader iterator (the data wait) and
samples/s, both over steps 1.. (step 0 includes connecting and the workers' start).

Data: `--dataset stream` (default) is `MPIFlowDataset`, an endless stream that shards itself
over ranks and DataLoader workers (no sampler, no shuffle); `--dataset map` is
`MPIFlowMapDataset` of `--length` samples with `DataLoader(shuffle=True)`, or with
`DistributedSampler` under torchrun (RANK/WORLD_SIZE set). `--spawn "SERVE ARGS"` starts
`$MPIFLOW_BIN serve --addr 127.0.0.1:0 SERVE ARGS` (default binary: `mpiflow` on PATH) for
the run and stops it at the end; otherwise the server at `--addr` is used. See docs/trainers.md.
"""
from __future__ import annotations

import argparse
import math
import os
import shlex
import subprocess
import sys
import tempfile
import time
from pathlib import Path
from typing import Iterator, List, Optional, Tuple

import torch
from torch.utils.data import DataLoader, DistributedSampler
from torchvision.models.optical_flow import raft_small

sys.path.insert(0, str(Path(__file__).resolve().parents[1] / "clients" / "python"))  # run from the repo without installing
from mpiflow import MPIFlowDataset, MPIFlowMapDataset  # noqa: E402

MAX_FLOW = 400.0  # RAFT excludes larger displacements from the loss


def sequence_loss(preds: List[torch.Tensor], flow: torch.Tensor, valid: torch.Tensor,
                  gamma: float = 0.8) -> Tuple[torch.Tensor, torch.Tensor]:
    """RAFT's loss: the L1 error of every refinement, weighted gamma^(N - i - 1), on valid pixels
    with |flow| < MAX_FLOW (averaged over all pixels, as RAFT does); and the final end-point error
    per valid pixel."""
    mask = (valid >= 0.5) & (flow.norm(dim=1) < MAX_FLOW)
    n = len(preds)
    loss = flow.new_zeros(())
    for i, pred in enumerate(preds):
        loss = loss + gamma ** (n - i - 1) * (mask[:, None] * (pred - flow).abs()).mean()
    epe = (preds[-1] - flow).norm(dim=1)[mask]
    return loss, epe


def batches(loader: DataLoader, sampler: Optional[DistributedSampler]) -> Iterator[dict]:
    """The loader's batches without end: the stream has no epochs; the map dataset starts the
    next epoch (a new order from the sampler) when one ends."""
    epoch = 0
    while True:
        if sampler is not None:
            sampler.set_epoch(epoch)
        yield from loader
        epoch += 1


def parse_size(text: str) -> Tuple[int, int]:
    w, h = (int(v) for v in text.lower().split("x"))
    if w % 8 or h % 8 or w < 128 or h < 128:
        # torchvision's RAFT: /8 features, then a 4-level correlation pyramid of >= 16 cells
        raise SystemExit(f"--crop {text}: RAFT needs a width and height divisible by 8, >= 128")
    return w, h


def spawn_server(serve_args: str) -> Tuple[subprocess.Popen, str, str]:
    """`$MPIFLOW_BIN serve` on a free loopback port: (process, address, log path)."""
    exe = os.environ.get("MPIFLOW_BIN") or "mpiflow"
    log = tempfile.NamedTemporaryFile(prefix="mpiflow-serve-", suffix=".log", delete=False)
    proc = subprocess.Popen([exe, "serve", "--addr", "127.0.0.1:0", *shlex.split(serve_args)],
                            stdout=subprocess.PIPE, stderr=log, stdin=subprocess.DEVNULL, text=True)
    assert proc.stdout is not None
    for line in proc.stdout:  # the server prints its address once bound
        if line.startswith("mpiflow serving on "):
            return proc, line.strip().rsplit(" ", 1)[1], log.name
    code = proc.wait()
    raise SystemExit(f"{exe} serve exited ({code}) before serving:\n{Path(log.name).read_text()[-2000:]}")


def main() -> int:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--addr", default="127.0.0.1:50051", help="server address(es), comma-separated")
    ap.add_argument("--spawn", nargs="?", const="", default=None, metavar="SERVE_ARGS",
                    help="start `$MPIFLOW_BIN serve SERVE_ARGS` for this run instead of using --addr "
                         "(one argument: --spawn '--size 640x480 --workers 1' or --spawn=--workers=1)")
    ap.add_argument("--dataset", choices=("stream", "map"), default="stream")
    ap.add_argument("--length", type=int, default=10_000, help="samples of the map-style dataset")
    ap.add_argument("--steps", type=int, default=50)
    ap.add_argument("--batch-size", type=int, default=2)
    ap.add_argument("--workers", type=int, default=2, help="DataLoader worker processes")
    ap.add_argument("--crop", default="320x256", help="WxH random crop made by the server")
    ap.add_argument("--iters", type=int, default=12, help="RAFT refinements per forward pass")
    ap.add_argument("--lr", type=float, default=4e-4)
    ap.add_argument("--wdecay", type=float, default=1e-4)
    ap.add_argument("--clip", type=float, default=1.0)
    ap.add_argument("--gamma", type=float, default=0.8)
    ap.add_argument("--seed", type=int, default=0, help="the data seed and the model's init seed")
    ap.add_argument("--threads", type=int, default=0, help="torch CPU threads (0: torch's default)")
    ap.add_argument("--lz4", action="store_true")
    ap.add_argument("--device", default="cuda" if torch.cuda.is_available() else "cpu")
    a = ap.parse_args()
    if a.steps < 1:
        raise SystemExit("--steps must be >= 1")
    w, h = parse_size(a.crop)
    if a.threads > 0:
        torch.set_num_threads(a.threads)
    torch.manual_seed(a.seed)

    server = None
    if a.spawn is not None:
        server, a.addr, log = spawn_server(a.spawn)
        print(f"spawned mpiflow serve {a.spawn} on {a.addr} (log {log})")
    distributed = "RANK" in os.environ and "WORLD_SIZE" in os.environ
    if distributed:
        torch.distributed.init_process_group("nccl" if a.device.startswith("cuda") else "gloo")
    rank = torch.distributed.get_rank() if distributed else 0

    # --- the data: these lines replace RAFT's `fetch_dataloader(args)` -------------------------
    sampler = None
    if a.dataset == "stream":
        # endless, sharded over ranks x workers by the dataset itself: no sampler, no shuffle
        train_dataset = MPIFlowDataset(a.addr, seed=a.seed, crop=(w, h), lz4=a.lz4)
        loader_kw = {}
    else:
        # map-style: the sampler shards and shuffles, as with any Dataset
        train_dataset = MPIFlowMapDataset(a.addr, a.length, seed=a.seed, crop=(w, h), lz4=a.lz4)
        if distributed:
            sampler = DistributedSampler(train_dataset, shuffle=True, seed=a.seed)
            loader_kw = {"sampler": sampler}
        else:
            loader_kw = {"shuffle": True, "generator": torch.Generator().manual_seed(a.seed)}
    train_loader = DataLoader(train_dataset, batch_size=a.batch_size, num_workers=a.workers,
                              pin_memory=a.device.startswith("cuda"), drop_last=True,
                              persistent_workers=a.workers > 0, **loader_kw)
    # -------------------------------------------------------------------------------------------

    model = raft_small(weights=None, progress=False).to(a.device)
    model.train()
    if distributed:
        model = torch.nn.parallel.DistributedDataParallel(model)
    opt = torch.optim.AdamW(model.parameters(), lr=a.lr, weight_decay=a.wdecay, eps=1e-8)
    sched = torch.optim.lr_scheduler.OneCycleLR(opt, a.lr, a.steps + 100, pct_start=0.05,
                                                cycle_momentum=False, anneal_strategy="linear")
    print(f"rank {rank}: raft_small (weights=None, {sum(p.numel() for p in model.parameters())} "
          f"parameters) on {a.device}, {torch.get_num_threads()} threads; {a.dataset} dataset "
          f"from {a.addr}, crop {w}x{h}, batch {a.batch_size}, {a.workers} DataLoader workers")

    wait = total = 0.0
    samples = 0
    losses: List[float] = []
    it = batches(train_loader, sampler)
    t_start = time.perf_counter()
    try:
        for step in range(a.steps):
            t0 = time.perf_counter()
            batch = next(it)
            t1 = time.perf_counter()
            # torchvision's RAFT takes images in [-1, 1]; the dataset gives 0..255 (RAFT's range)
            img1 = batch["img1"].to(a.device, non_blocking=True) / 127.5 - 1.0
            img2 = batch["img2"].to(a.device, non_blocking=True) / 127.5 - 1.0
            flow = batch["flow"].to(a.device, non_blocking=True)
            valid = batch["valid"].to(a.device, non_blocking=True)
            preds = model(img1, img2, num_flow_updates=a.iters)
            loss, epe = sequence_loss(preds, flow, valid, a.gamma)
            opt.zero_grad(set_to_none=True)
            loss.backward()
            torch.nn.utils.clip_grad_norm_(model.parameters(), a.clip)
            opt.step()
            sched.step()
            if a.device.startswith("cuda"):
                torch.cuda.synchronize()
            t2 = time.perf_counter()
            value = loss.item()
            if not math.isfinite(value):
                raise SystemExit(f"step {step}: non-finite loss {value}")
            losses.append(value)
            if step > 0:  # step 0 includes connecting and the workers' start
                wait += t1 - t0
                total += t2 - t0
                samples += img1.shape[0]
            mean_epe = epe.mean().item() if epe.numel() else float("nan")
            print(f"step {step}: loss {value:.4f}, epe {mean_epe:.3f} px, data wait {t1 - t0:.3f} s, "
                  f"step {t2 - t0:.3f} s, indices {batch['index'].tolist()}", flush=True)
    finally:
        del it, train_loader  # stops the DataLoader workers (before the server they read from)
        if server is not None:
            server.terminate()
            server.wait(30)
    wall = time.perf_counter() - t_start
    if total > 0:
        print(f"rank {rank}: data-wait fraction {wait / total:.4f} ({wait:.2f} s of {total:.2f} s, "
              f"steps 1..{a.steps - 1}); {samples / total:.3f} samples/s; "
              f"loss {losses[0]:.4f} -> {losses[-1]:.4f}; wall {wall:.1f} s incl. start-up")
    else:
        print(f"rank {rank}: one step only: no steady-state figures; loss {losses[0]:.4f}; "
              f"wall {wall:.1f} s")
    if distributed:
        torch.distributed.destroy_process_group()
    return 0


if __name__ == "__main__":
    sys.exit(main())
