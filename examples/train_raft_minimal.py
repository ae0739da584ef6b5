#!/usr/bin/env python3
"""A minimal optical-flow training loop fed by mpiflow (torch): the RAFT swap-in, measured.

    python examples/train_raft_minimal.py --addr 127.0.0.1:50051 --steps 50 --batch-size 4 \
        --workers 2 --crop 320x240

Prints samples/s and the fraction of step time spent waiting for data (time blocked in the
DataLoader over the whole step time). A small encoder-decoder stands in for RAFT; the dataset
part is exactly what a RAFT trainer uses. Under torchrun (RANK/WORLD_SIZE set) every rank gets
its own disjoint shard. `--checkpoint FILE` saves the data cursor with the model; run again with
the same file to resume with exactly the samples not yet seen.
"""
from __future__ import annotations

import argparse
import os
import sys
import time
from pathlib import Path

import torch
import torch.nn as nn
import torch.nn.functional as F
from torch.utils.data import DataLoader

sys.path.insert(0, str(Path(__file__).resolve().parents[1] / "clients" / "python"))  # run from the repo without installing
from mpiflow import MPIFlowDataset  # noqa: E402


class TinyFlowNet(nn.Module):
    """image pair -> flow at 1/4 resolution, upsampled (a stand-in for RAFT)."""

    def __init__(self, c: int = 32):
        super().__init__()

        def block(i, o, s):
            return nn.Sequential(nn.Conv2d(i, o, 3, s, 1), nn.GroupNorm(8, o), nn.ReLU(inplace=True))

        self.enc = nn.Sequential(block(6, c, 2), block(c, c, 1), block(c, 2 * c, 2), block(2 * c, 2 * c, 1))
        self.head = nn.Sequential(block(2 * c, 2 * c, 1), nn.Conv2d(2 * c, 2, 3, 1, 1))

    def forward(self, img1, img2):
        x = torch.cat([img1, img2], 1) / 127.5 - 1.0  # RAFT normalises the same way
        flow = self.head(self.enc(x)) * 4.0
        return F.interpolate(flow, size=img1.shape[-2:], mode="bilinear", align_corners=False) * 4.0


def main() -> int:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--addr", default="127.0.0.1:50051", help="server address(es), comma-separated")
    ap.add_argument("--steps", type=int, default=50)
    ap.add_argument("--batch-size", type=int, default=4)
    ap.add_argument("--workers", type=int, default=2, help="DataLoader worker processes")
    ap.add_argument("--crop", default="320x240", help="WxH random crop made by the server")
    ap.add_argument("--lz4", action="store_true")
    ap.add_argument("--seed", type=int, default=0)
    ap.add_argument("--lr", type=float, default=4e-4)
    ap.add_argument("--device", default="cuda" if torch.cuda.is_available() else "cpu")
    ap.add_argument("--checkpoint", default=None, help="save/resume model + data cursor here")
    a = ap.parse_args()

    if "RANK" in os.environ and "WORLD_SIZE" in os.environ and not torch.distributed.is_initialized():
        torch.distributed.init_process_group("nccl" if a.device.startswith("cuda") else "gloo")
    rank = torch.distributed.get_rank() if torch.distributed.is_initialized() else 0

    w, h = (int(v) for v in a.crop.lower().split("x"))
    # --- the RAFT swap-in: these lines replace `fetch_dataloader(args)` ---------------------------
    train_dataset = MPIFlowDataset(a.addr, seed=a.seed, crop=(w, h), crop_mode="random", lz4=a.lz4)
    train_loader = DataLoader(train_dataset, batch_size=a.batch_size, num_workers=a.workers,
                              pin_memory=a.device.startswith("cuda"), drop_last=True,
                              persistent_workers=a.workers > 0)
    # -------------------------------------------------------------------------------------------

    model = TinyFlowNet().to(a.device)
    opt = torch.optim.AdamW(model.parameters(), lr=a.lr)
    step0 = 0
    if a.checkpoint and Path(a.checkpoint).exists():
        ck = torch.load(a.checkpoint, map_location=a.device, weights_only=False)
        model.load_state_dict(ck["model"])
        opt.load_state_dict(ck["opt"])
        train_dataset.load_state_dict(ck["data"][rank])
        step0 = ck["step"]
        print(f"resumed at step {step0}, data cursors {ck['data'][rank]['cursors']}")

    wait = compute = 0.0
    samples = 0
    it = iter(train_loader)
    t_start = time.perf_counter()
    for step in range(step0, step0 + a.steps):
        t0 = time.perf_counter()
        batch = next(it)  # endless stream: no epochs
        train_dataset.track(batch)  # the cursor of what this loop received (for --checkpoint)
        img1 = batch["img1"].to(a.device, non_blocking=True)
        img2 = batch["img2"].to(a.device, non_blocking=True)
        flow = batch["flow"].to(a.device, non_blocking=True)
        valid = batch["valid"].to(a.device, non_blocking=True)
        t1 = time.perf_counter()
        pred = model(img1, img2)
        # RAFT's loss on valid pixels with a sane magnitude, without the iteration sequence
        mask = (valid >= 0.5) & (flow.norm(dim=1) < 400)
        loss = ((pred - flow).abs().sum(1) * mask).sum() / mask.sum().clamp(min=1)
        opt.zero_grad(set_to_none=True)
        loss.backward()
        opt.step()
        if a.device.startswith("cuda"):
            torch.cuda.synchronize()
        t2 = time.perf_counter()
        if step > step0:  # the first step includes connecting and the workers' start
            wait += t1 - t0
            compute += t2 - t1
            samples += img1.shape[0]
        if step % 10 == 0 or step == step0 + a.steps - 1:
            epe = ((pred - flow).norm(dim=1)[mask]).mean().item() if mask.any() else float("nan")
            print(f"step {step}: loss {loss.item():.3f}, epe {epe:.2f} px, "
                  f"indices {batch['index'][:4].tolist()}...")
    total = wait + compute
    print(f"{samples} samples in {total:.2f} s: {samples / max(total, 1e-9):.2f} samples/s; "
          f"waiting for data {wait / max(total, 1e-9):.1%} of step time "
          f"(wall {time.perf_counter() - t_start:.2f} s incl. start-up)")

    if a.checkpoint:
        state = train_dataset.state_dict()
        states = [state]
        if torch.distributed.is_initialized():
            states = [None] * torch.distributed.get_world_size()
            torch.distributed.all_gather_object(states, state)
        if rank == 0:
            torch.save({"model": model.state_dict(), "opt": opt.state_dict(), "data": states,
                        "step": step0 + a.steps}, a.checkpoint)
            print(f"saved {a.checkpoint} (data cursors {state['cursors']})")
    del it
    return 0


if __name__ == "__main__":
    sys.exit(main())
