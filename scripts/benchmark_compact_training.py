#!/usr/bin/env python
"""Training-step throughput of the compact-cache trainer per batch size, and where a step's time goes.

Runs the trainer's step (``compact_training.training_step``: batch from the cache, grasp-subset
augmentation, RT-V3 loss, backward, Adam)
on ``--device`` for each ``--batch-sizes``: ``--warmup`` untimed steps, then ``--steps`` timed ones
(the device synchronised at both ends); prints samples/s and ms per step. ``--profile`` adds a
``torch.profiler`` table of the most expensive operators over 10 steps of the largest batch size,
by self CPU time (launch and host overheads) and, on CUDA, self device time. PyTorch alone is needed
(no LeRobot), as for ``scripts/train_compact_gpu.sh``::

    python scripts/benchmark_compact_training.py --cache CACHE --device cuda --batch-sizes 64 512 2048
"""

from __future__ import annotations

import argparse
import statistics
import sys
import time
from pathlib import Path
from types import SimpleNamespace

import torch

sys.path.insert(0, str(Path(__file__).resolve().parents[1]))

from rtv3_maniskill.policies.rtv3.compact_cache import CACHE_FILE, CompactCache  # noqa: E402
from rtv3_maniskill.policies.rtv3.compact_training import (  # noqa: E402
    build_optimizer,
    config_fields,
    training_step,
)
from rtv3_maniskill.policies.rtv3.model import RTV3Model  # noqa: E402


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    parser.add_argument("--cache", type=Path, required=True, help="folder written by `rtv3 compact-cache build`")
    parser.add_argument("--device", default="cpu")
    parser.add_argument("--batch-sizes", type=int, nargs="+", default=[64, 512])
    parser.add_argument("--steps", type=int, default=20, help="timed steps per batch size")
    parser.add_argument("--warmup", type=int, default=5)
    parser.add_argument("--repeats", type=int, default=3, help="timed blocks per batch size (median reported)")
    parser.add_argument("--profile", action="store_true")
    args = parser.parse_args()

    device = torch.device(args.device)
    if device.type == "cuda":
        torch.backends.cuda.matmul.allow_tf32 = torch.backends.cudnn.allow_tf32 = True
    cfg = config_fields(args.cache)
    windowed = CompactCache.load(args.cache / CACHE_FILE).windows()
    windowed.contexts_to(device)
    model = RTV3Model(SimpleNamespace(**cfg)).to(device).train()
    optimizer = build_optimizer(model, cfg)
    generator = torch.Generator().manual_seed(0)
    sync = torch.cuda.synchronize if device.type == "cuda" else (lambda: None)
    name = torch.cuda.get_device_name(device) if device.type == "cuda" else f"cpu, {torch.get_num_threads()} threads"
    print(f"torch {torch.__version__}, {name}; {windowed.compact.num_frames} frames in the cache")

    def step(batch_size: int) -> None:
        frames = torch.randint(windowed.compact.num_frames, (batch_size,), generator=generator)
        training_step(model, optimizer, windowed, frames, cfg, 20000, device)

    for batch_size in args.batch_sizes:
        for _ in range(args.warmup):
            step(batch_size)
        times = []
        for _ in range(args.repeats):
            sync()
            start = time.perf_counter()
            for _ in range(args.steps):
                step(batch_size)
            sync()
            times.append((time.perf_counter() - start) / args.steps)
        per_step = statistics.median(times)
        print(f"batch {batch_size:5d}: {batch_size / per_step:9.1f} samples/s, {1000 * per_step:7.1f} ms/step "
              f"(median of {args.repeats} x {args.steps} steps)", flush=True)
    if args.profile:
        from torch.profiler import ProfilerActivity, profile

        activities = [ProfilerActivity.CPU] + ([ProfilerActivity.CUDA] if device.type == "cuda" else [])
        with profile(activities=activities) as prof:
            for _ in range(10):
                step(max(args.batch_sizes))
            sync()
        print(prof.key_averages().table(sort_by="self_cpu_time_total", row_limit=15, max_name_column_width=40))
        if device.type == "cuda":
            print(prof.key_averages().table(sort_by="self_cuda_time_total", row_limit=10, max_name_column_width=40))


if __name__ == "__main__":
    main()
