"""Time of the expert's free-space plan (``PandaPlanner.plan_to_pose``) on paper-preset scenes, 3 cm clearance.

Usage: ``python benchmarks/benchmark_planner.py [--scenes 4] [--targets 8] [--seed 31] [--clearance 0.03]
[--objects ycb+procedural+random_urdfs] [--repeats 3]``

The demonstrations' planning problem as ``rtv3 generate --preset paper`` poses it: for each of ``--scenes`` scenes
(seeds as ``rtv3 generate --seed``), ``--targets`` grasp candidates, a start drawn from the authors' start
distribution (the recorder's ``draw_start``), the plan to the candidate's pre-grasp with the recorder's 3 s budget.
Only ``plan_to_pose`` is timed (IK, RRTConnect with the clearance search first, shortcutting, TOPP-RA); each repeat
plans every problem again with the same seeds. Prints the median plan time per outcome and per repeat, and a digest
of the found paths: planning is reproducible per seed, so two versions of the planner that find the same paths print
the same digest (unless a search ran into its time budget, which depends on the machine's speed).
"""

from __future__ import annotations

import argparse
import hashlib
import statistics
import time

import gymnasium as gym
import numpy as np
import torch

import rtv3_maniskill  # noqa: F401  (registers GraspClutter-v1)
from rtv3_maniskill import features
from rtv3_maniskill.datagen.demonstrations import draw_start
from rtv3_maniskill.presets import get_preset
from rtv3_maniskill.robot.planner import PandaPlanner
from rtv3_maniskill.robot.planner_config import with_clearance


def problems(args: argparse.Namespace) -> list[tuple[PandaPlanner, np.ndarray, np.ndarray, int]]:
    """``(planner, q_start (7,), pre-grasp (4, 4), seed)`` per target, scenes drawn as ``rtv3 generate`` does."""
    env = gym.make("GraspClutter-v1", obs_mode="state_dict", control_mode="pd_joint_pos_vel",
                   scene_type=get_preset("paper").scene_type, object_source=args.objects, reconfiguration_freq=0)
    out = []
    config = with_clearance(args.clearance)
    try:
        for i in range(args.scenes):
            scene_seed = args.seed * 100000 + i
            env.reset(seed=scene_seed, options=dict(reconfigure=True))
            base = env.unwrapped
            planner = PandaPlanner(base.layouts[0], config=config)
            grasps = base.grasp_sets[0].poses
            for g in range(min(args.targets, len(grasps))):
                q = draw_start(planner, np.random.default_rng(scene_seed * 1000 + g))
                if q is not None:
                    pregrasp = features.pregrasp_poses(torch.from_numpy(np.asarray(grasps[g]))).numpy()
                    out.append((planner, q, pregrasp, scene_seed * 1000 + g))
    finally:
        env.close()
    return out


def main(argv: list[str] | None = None) -> int:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--scenes", type=int, default=4)
    parser.add_argument("--targets", type=int, default=8, help="grasp candidates per scene")
    parser.add_argument("--seed", type=int, default=31, help="scene seed block (rtv3 generate --seed)")
    parser.add_argument("--clearance", type=float, default=0.03, help="m (rtv3 generate --clearance)")
    parser.add_argument("--objects", default="ycb+procedural+random_urdfs",
                        help="object source (rtv3 generate --objects)")
    parser.add_argument("--timeout", type=float, default=3.0, help="s per plan (the recorder's budget)")
    parser.add_argument("--repeats", type=int, default=3)
    args = parser.parse_args(argv)
    if min(args.scenes, args.targets, args.repeats) < 1:
        parser.error("--scenes, --targets and --repeats must be >= 1")
    torch.set_num_threads(1)
    cases = problems(args)
    print(f"{len(cases)} planning problems ({args.scenes} scenes, clearance {args.clearance} m)")
    repeat_medians = []
    for r in range(args.repeats):
        times: dict[str, list[float]] = {}
        digest = hashlib.sha256()
        for planner, q_start, pregrasp, seed in cases:
            t0 = time.perf_counter()
            result = planner.plan_to_pose(q_start, pregrasp, timeout=args.timeout, seed=seed)
            elapsed = time.perf_counter() - t0
            outcome = "success" if result.success else result.failure_reason
            times.setdefault(outcome, []).append(elapsed)
            digest.update(outcome.encode())
            if result.success:
                digest.update(np.round(result.waypoints, 9).tobytes())
        every = [t for ts in times.values() for t in ts]
        repeat_medians.append(statistics.median(every))
        per_outcome = ", ".join(f"{k} {len(v)} x {1000 * statistics.median(v):.0f} ms"
                                for k, v in sorted(times.items()))
        print(f"repeat {r + 1}: median {1000 * repeat_medians[-1]:.0f} ms, total {sum(every):.1f} s ({per_outcome}); "
              f"paths {digest.hexdigest()[:16]}")
    print(f"median plan time over the repeats' medians: {1000 * statistics.median(repeat_medians):.0f} ms")
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
