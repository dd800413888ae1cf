#!/usr/bin/env python
"""End-to-end training throughput of ``lerobot-train --policy.type=rtv3``: old vs. new data path.

Old: ``--baseline COMMIT``'s code (e.g. 735c219, the commit before the training cache: LeRobot windows
``action`` over H = 12 frames, re-reading each frame's point cloud and grasps). New: this tree (one row
per sample, windows cut from the policy's in-memory training cache). Both run LeRobot's own training
script on the same dataset and batch size, with 1 data worker and 1 thread each by default (as the
measurement in docs/RESULTS.md, "Training throughput"), interleaved (old, new, new, old, ...) so that drifts of the
machine's speed hit both alike.

Samples/s of a run come from LeRobot's training log: every ``--log_freq`` steps it prints the mean
``updt_s`` (forward, backward, optimiser) and ``data_s`` (waiting for the next batch + pre-processor)
of those steps; one window's rate is ``batch_size / (updt_s + data_s)``. The first window (worker
start-up, first-touch allocations) is dropped. Prints every run, the median per path and the ratio.

``--compact`` adds a third path, the compact-cache trainer (``rtv3 compact-cache``: the dataset reduced
once to a cache, then ``python -m rtv3_maniskill.cli.compact_cache train``, PyTorch alone, same batch
size and threads); its samples/s per run is the trainer's own median over its logging windows after the
first.

Example (dataset: ``rtv3 generate --num-scenes 20 --grasps-per-scene 8 --num-points 512
--output /tmp/bench_ds --seed 3 --context mesh``)::

    .venv/bin/python benchmarks/benchmark_training.py --dataset /tmp/bench_ds --batch-size 64 --baseline 735c219
"""

from __future__ import annotations

import argparse
import json
import os
import re
import statistics
import subprocess
import sys
import tempfile
import time
from pathlib import Path

BASELINE_SRC: Path | None = None
"""The extracted ``rtv3_maniskill`` package of that commit, put first on the old runs' path."""
WINDOW = re.compile(r"step:(\S+) .*updt_s:([0-9.]+) data_s:([0-9.]+)")


def run_training(dataset: Path, path: str, batch_size: int, steps: int, log_freq: int,
                 num_workers: int | None, threads: int | None, extra: list[str]) -> list[float]:
    """One ``lerobot-train`` run; samples/s of each logged window after the first."""
    repo_id = json.loads((dataset / "meta" / "info.json").read_text()).get("repo_id") or "local/rtv3_grasp_clutter"
    with tempfile.TemporaryDirectory(prefix="rtv3_bench_train_") as tmp:
        cmd = [
            sys.executable, "-m", "lerobot.scripts.lerobot_train", f"--dataset.repo_id={repo_id}",
            f"--dataset.root={dataset}", "--policy.type=rtv3", "--policy.device=cpu", "--policy.push_to_hub=false",
            f"--steps={steps}", f"--batch_size={batch_size}", f"--log_freq={log_freq}", "--save_checkpoint=false",
            f"--output_dir={Path(tmp) / 'out'}", "--wandb.enable=false", *extra,
        ]
        if num_workers is not None:
            cmd.append(f"--num_workers={num_workers}")
        env = dict(os.environ, **({"OMP_NUM_THREADS": str(threads)} if threads else {}))
        if path == "old":  # the whole old code, with its own default data path
            env["PYTHONPATH"] = os.pathsep.join(filter(None, [str(BASELINE_SRC), env.get("PYTHONPATH")]))
        # cwd: a neutral folder (python -m puts the working directory first on the path)
        result = subprocess.run(cmd, capture_output=True, text=True, env=env, cwd=tmp)
    if result.returncode != 0:
        raise RuntimeError(f"lerobot-train ({path}) failed:\n{result.stderr[-3000:]}")
    windows = [(float(u), float(d)) for _, u, d in WINDOW.findall(result.stdout + result.stderr)]
    if len(windows) < 2:
        raise RuntimeError(f"lerobot-train ({path}) logged {len(windows)} windows; raise --steps")
    return [batch_size / (u + d) for u, d in windows[1:]]


def run_compact(cache: Path, batch_size: int, steps: int, log_freq: int, threads: int | None) -> list[float]:
    """One compact-cache training run (fresh weights, as the lerobot-train runs); its median samples/s."""
    with tempfile.TemporaryDirectory(prefix="rtv3_bench_compact_") as tmp:
        cmd = [sys.executable, "-m", "rtv3_maniskill.cli.compact_cache", "train", f"--cache={cache}",
               f"--output={Path(tmp) / 'run'}", f"--steps={steps}", f"--batch-size={batch_size}",
               f"--log-freq={log_freq}", f"--save-freq={10 * steps}", "--device=cpu"]
        env = dict(os.environ, **({"OMP_NUM_THREADS": str(threads)} if threads else {}))
        result = subprocess.run(cmd, capture_output=True, text=True, env=env, cwd=tmp)
    if result.returncode != 0:
        raise RuntimeError(f"compact training failed:\n{result.stderr[-3000:]}")
    return [json.loads(result.stdout[result.stdout.index("{"):])["samples_per_s"]]


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    parser.add_argument("--dataset", type=Path, required=True, help="LeRobot dataset root (rtv3 generate --output)")
    parser.add_argument("--batch-size", type=int, default=64)
    parser.add_argument("--steps", type=int, default=30, help="training steps per run")
    parser.add_argument("--log-freq", type=int, default=5, help="steps per measured window")
    parser.add_argument("--rounds", type=int, default=3, help="old/new pairs, interleaved")
    parser.add_argument("--num-workers", type=int, default=1,
                        help="DataLoader workers (--num_workers; -1: LeRobot's default, 4)")
    parser.add_argument("--threads", type=int, default=1, help="OMP_NUM_THREADS of the training process (0: unset)")
    parser.add_argument("--baseline", required=True,
                        help="git commit whose rtv3_maniskill runs the old path (e.g. 735c219, the commit before the "
                             "training cache)")
    parser.add_argument("--compact", action="store_true",
                        help="also time the compact-cache trainer (rtv3 compact-cache) on the same data")
    parser.add_argument("extra", nargs="*", help="more lerobot-train flags for both paths (after --)")
    args = parser.parse_args()
    args.dataset = args.dataset.resolve()  # the runs start in a temporary folder

    global BASELINE_SRC
    tmp = tempfile.TemporaryDirectory(prefix="rtv3_bench_baseline_")
    repo = Path(__file__).resolve().parents[1]
    archive = subprocess.run(["git", "-C", str(repo), "archive", args.baseline, "rtv3_maniskill"], check=True,
                             capture_output=True).stdout
    subprocess.run(["tar", "-x", "-C", tmp.name], input=archive, check=True)
    BASELINE_SRC = Path(tmp.name)
    probe = subprocess.run([sys.executable, "-c", "import rtv3_maniskill; print(rtv3_maniskill.__file__)"],
                           capture_output=True, text=True, env=dict(os.environ, PYTHONPATH=tmp.name),
                           cwd=tempfile.gettempdir())
    if not probe.stdout.startswith(tmp.name):
        raise RuntimeError(f"the baseline package does not shadow the installed one: {probe.stdout}{probe.stderr}")
    rates: dict[str, list[float]] = {"old": [], "new": [], "compact": []}
    paths = ("old", "new", "compact") if args.compact else ("old", "new")
    if args.compact:
        cache = Path(tmp.name) / "compact_cache"
        subprocess.run([sys.executable, "-m", "rtv3_maniskill.cli", "compact-cache", "build",
                        f"--dataset.root={args.dataset}", f"--output={cache}", "--max-mib=100000"], check=True,
                       capture_output=True)
    for r in range(args.rounds):
        for path in paths if r % 2 == 0 else paths[::-1]:
            start = time.perf_counter()
            if path == "compact":
                windows = run_compact(cache, args.batch_size, args.steps, args.log_freq, args.threads)
            else:
                windows = run_training(args.dataset, path, args.batch_size, args.steps, args.log_freq,
                                       None if args.num_workers < 0 else args.num_workers, args.threads, args.extra)
            rates[path] += windows
            print(f"round {r} {path}: median {statistics.median(windows):7.1f} samples/s over {len(windows)} windows "
                  f"({time.perf_counter() - start:.0f} s wall)", flush=True)
    old, new = statistics.median(rates["old"]), statistics.median(rates["new"])
    print(f"batch {args.batch_size}, {args.rounds} interleaved rounds, {args.steps} steps per run, "
          f"num_workers {args.num_workers}, OMP_NUM_THREADS {args.threads or 'unset'}")
    print(f"old (commit {args.baseline}): {old:7.1f} samples/s  ({args.batch_size / old:.3f} s/step)")
    print(f"new (this tree, defaults): {new:7.1f} samples/s  ({args.batch_size / new:.3f} s/step)")
    print(f"ratio new/old: {new / old:.2f}x")
    if args.compact:
        compact = statistics.median(rates["compact"])
        print(f"compact-cache trainer: {compact:7.1f} samples/s  ({args.batch_size / compact:.3f} s/step); "
              f"ratio compact/new: {compact / new:.2f}x")
    tmp.cleanup()


if __name__ == "__main__":
    main()
