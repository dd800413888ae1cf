"""``rtv3 benchmark-env``: medians for GraspClutter-v1 on this machine (one CPU thread)."""

from __future__ import annotations

import argparse
import json
import time
from pathlib import Path


def add_arguments(parser: argparse.ArgumentParser) -> None:
    parser.add_argument("--steps", type=int, default=200, help="steps per timing run (state mode)")
    parser.add_argument("--repeats", type=int, default=5, help="timing runs for steps/s")
    parser.add_argument("--resets", type=int, default=10, help="scene resets (new clutter + grasp sampling) to time")
    parser.add_argument("--captures", type=int, default=20, help="point-cloud captures to time")
    parser.add_argument("--output", type=Path, default=None, help="optional JSON file for the numbers")


def _median(values: list[float]) -> float:
    import statistics

    return float(statistics.median(values))


def run(args: argparse.Namespace) -> int:
    import gymnasium as gym
    import torch
    from tqdm import tqdm

    import rtv3_maniskill  # noqa: F401

    torch.set_num_threads(1)
    results: dict[str, float] = {}

    env = gym.make("GraspClutter-v1", obs_mode="state", control_mode="pd_ee_twist")
    env.reset(seed=0)
    rates = []
    generator = torch.Generator().manual_seed(0)
    for _ in tqdm(range(args.repeats), desc="state-mode steps"):
        env.reset()
        actions = (torch.rand(args.steps, 1, 7, generator=generator) - 0.5) * torch.tensor(
            [0.2] * 3 + [0.8] * 3 + [0.0]
        )
        start = time.perf_counter()
        for action in actions:
            env.step(action)
        rates.append(args.steps / (time.perf_counter() - start))
    results["state_steps_per_s_median"] = _median(rates)

    resets = []
    for seed in tqdm(range(args.resets), desc="scene resets"):
        start = time.perf_counter()
        env.reset(seed=1000 + seed)
        resets.append(time.perf_counter() - start)
    results["reset_with_grasp_sampling_s_median"] = _median(resets)
    env.close()

    env = gym.make("GraspClutter-v1", obs_mode="pointcloud", control_mode="pd_ee_twist")
    env.reset(seed=0)
    base = env.unwrapped
    captures = []
    for _ in tqdm(range(args.captures), desc="point-cloud captures"):
        env.step(torch.zeros(1, 7))
        start = time.perf_counter()
        base.capture_point_cloud()
        captures.append(time.perf_counter() - start)
    results["point_cloud_capture_ms_median"] = 1000 * _median(captures)
    results["camera_resolution"] = base.camera_resolution
    env.close()

    for key, value in results.items():
        print(f"{key:40s} {value:10.3f}")
    if args.output is not None:
        args.output.parent.mkdir(parents=True, exist_ok=True)
        args.output.write_text(json.dumps(results, indent=2))
    return 0
