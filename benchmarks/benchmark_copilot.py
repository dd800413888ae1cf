"""Latency of one diffusion-copilot step on CPU (target: median <= 40 ms on one thread, inside the 20 Hz loop).

Usage: ``python benchmarks/benchmark_copilot.py [--copilot-path DIR] [--gammas 0.1,0.2,0.5,1.0] [--steps 200]
[--repeats 3] [--threads 1]``

Times :meth:`DiffusionCopilot.step` (scene summary of the point cloud and grasps, normalisation, forward
noising to gamma and round(gamma * reverse_steps) DDIM steps of LeRobot's U-Net, unnormalisation) on real
``GraspClutter-v1`` observations. The env is stepped between calls with the copilot's output under a noisy
simulated user, but only the copilot call is timed. The step's cost grows with gamma (more reverse steps), so
each gamma is a row; each row pools ``--repeats`` loops of ``--steps`` steps, and its last column is the
median of the repeats' medians (on a shared VM they drift from minute to minute).
"""

from __future__ import annotations

import argparse
import statistics
import time

import numpy as np
import torch
from tqdm import tqdm

from rtv3_maniskill.benchmarks.episodes import SharedControlEnv
from rtv3_maniskill.features import observation_from_env
from rtv3_maniskill.shared_control import make_user
from rtv3_maniskill.shared_control.copilot import SHIPPED_COPILOT, DiffusionCopilot

BUDGET_MS = 40.0


def main(argv: list[str] | None = None) -> int:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--copilot-path", default=str(SHIPPED_COPILOT),
                        help="the copilot's pretrained_model folder (default: the shipped one)")
    parser.add_argument("--gammas", default="0.1,0.2,0.5,1.0", help="comma-separated noising fractions to time")
    parser.add_argument("--reverse-steps", type=int, default=None, help="DDIM steps (default: the checkpoint's)")
    parser.add_argument("--steps", type=int, default=200, help="timed steps per repeat")
    parser.add_argument("--warmup", type=int, default=10, help="untimed steps first")
    parser.add_argument("--repeats", type=int, default=3)
    parser.add_argument("--threads", type=int, default=1, help="torch intra-op threads")
    parser.add_argument("--seed", type=int, default=900000, help="scene seed")
    args = parser.parse_args(argv)
    if args.steps < 1 or args.threads < 1 or args.repeats < 1:
        parser.error("--steps, --repeats and --threads must be >= 1")
    try:
        gammas = [float(g) for g in args.gammas.split(",") if g.strip()]
    except ValueError:
        parser.error(f"--gammas: not a comma-separated list of numbers: {args.gammas!r}")
    torch.set_num_threads(args.threads)
    try:
        copilot = DiffusionCopilot.from_pretrained(args.copilot_path, reverse_steps=args.reverse_steps)
    except FileNotFoundError as err:
        parser.error(f"{err} (train one with rtv3 train-copilot)")
    params = sum(p.numel() for p in copilot.policy.parameters()) / 1e6
    print(f"copilot: {args.copilot_path}; {params:.2f} M parameters, {copilot.reverse_steps} DDIM steps, "
          f"{torch.get_num_threads()} thread(s)")

    env = SharedControlEnv(max_grasps=copilot.max_grasps)
    user = make_user("noisy", seed=0)
    print(f"{'gamma':>6s} {'reverse':>7s} {'n':>5s} {'median ms':>10s} {'p95 ms':>8s} {'max ms':>8s} "
          f"{'median of repeats':>18s}")
    verdicts = []
    for gamma in gammas:
        copilot.gamma = gamma
        steps_run = max(1, round(gamma * copilot.reverse_steps)) if gamma > 0 else 0
        pooled, medians = [], []
        for repeat in range(args.repeats):
            env.reset(seed=args.seed)
            copilot.reset()
            user.reset(env.user_goal())
            obs = env._obs
            times = []
            for i in tqdm(range(args.warmup + args.steps), desc=f"gamma {gamma} {repeat + 1}/{args.repeats}",
                          unit="step", leave=False):
                command = user(env.base.tcp_pose_matrix[0].double())[None]
                observation = observation_from_env(obs)
                start = time.perf_counter()
                twist = copilot.step(observation, command)
                elapsed = 1000 * (time.perf_counter() - start)
                if i >= args.warmup:
                    times.append(elapsed)
                obs, _, _, _, info = env.env.step(torch.cat([twist[0].float(), torch.ones(1)])[None])
                if bool(info["success"][0]) or i % 90 == 89:  # restart the approach
                    env.reset(seed=args.seed)
                    copilot.reset()
                    user.reset(env.user_goal())
                    obs = env._obs
            pooled += times
            medians.append(statistics.median(times))
        median = statistics.median(medians)
        verdicts.append(median)
        print(f"{gamma:6.2f} {steps_run:7d} {len(pooled):5d} {statistics.median(pooled):10.2f} "
              f"{float(np.percentile(pooled, 95)):8.2f} {max(pooled):8.2f} {median:18.2f}")
    env.close()
    worst = max(verdicts)
    print(f"slowest gamma's median step: {worst:.2f} ms (target <= {BUDGET_MS:.0f} ms on one thread: "
          f"{'met' if worst <= BUDGET_MS else 'NOT met'})")
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
