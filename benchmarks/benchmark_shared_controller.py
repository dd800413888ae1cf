"""Latency of one RT-V3 shared-control step on CPU, prior included (target <= 10 ms).

Usage: ``python benchmarks/benchmark_shared_controller.py [--policy.path DIR] [--steps 200] [--repeats 3] [--threads 1]
[--goal-belief-margin NATS|off]``

Times :meth:`SharedController.step` (prior forward pass + posterior fusion + mode search) on real
``GraspClutter-v1`` observations, the checkpoint's N points and M grasps (N = 2048, M = 64
without one), one intra-op thread. The env is stepped between calls (with the controller's
output; a mode-switching simulated user who pauses 10 steps after every 20 drives) but only the
controller call is timed, per mode the step ran in (``shared``, ``autonomous``, ``user_only``:
every mode runs the prior) and over ``all`` steps. Without a checkpoint an untrained ``RTV3Policy(RTV3Config())``
of the same size is used (latency does not depend on the weights). The timed loop runs ``--repeats`` times (the same
scene and user each time); the table pools every step, and the last line gives each repeat's
median (on a shared VM they drift by 20-50 % from minute to minute) and the median of them.
"""

from __future__ import annotations

import argparse
import statistics
import time

import numpy as np
import torch


def _percentile(values: list[float], q: float) -> float:
    return float(np.percentile(np.asarray(values), q))


def main(argv: list[str] | None = None) -> int:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--policy.path", dest="policy_path", default=None,
                        help="RT-V3 checkpoint folder (default: the shipped one, else an untrained policy)")
    parser.add_argument("--steps", type=int, default=200, help="timed steps per case")
    parser.add_argument("--warmup", type=int, default=10, help="untimed steps first")
    parser.add_argument("--repeats", type=int, default=3, help="timed loops (each --steps steps)")
    parser.add_argument("--threads", type=int, default=1, help="torch intra-op threads")
    parser.add_argument("--num-points", type=int, default=2048)
    parser.add_argument("--max-grasps", type=int, default=64)
    parser.add_argument("--seed", type=int, default=900000, help="scene seed")
    parser.add_argument("--goal-belief-margin", default="1.0", metavar="NATS|off",
                        help="the controller's goal belief over the grasp candidates (tuned: 1.0; off: none)")
    args = parser.parse_args(argv)
    if args.steps < 1 or args.threads < 1 or args.repeats < 1:
        parser.error("--steps, --repeats and --threads must be >= 1")
    torch.set_num_threads(args.threads)
    from tqdm import tqdm

    from rtv3_maniskill.benchmarks.episodes import SharedControlEnv
    from rtv3_maniskill.features import observation_from_env
    from rtv3_maniskill.policies.rtv3.checkpoints import SHIPPED_CHECKPOINT, load_policy
    from rtv3_maniskill.policies.rtv3.configuration_rtv3 import RTV3Config
    from rtv3_maniskill.policies.rtv3.modeling_rtv3 import RTV3Policy
    from rtv3_maniskill.shared_control import SharedControlConfig, SharedController, make_user

    path = args.policy_path or (SHIPPED_CHECKPOINT if (SHIPPED_CHECKPOINT / "model.safetensors").is_file() else None)
    if path is not None:
        policy = load_policy(path)
        source = str(path)
    else:
        torch.manual_seed(0)
        policy = RTV3Policy(RTV3Config(device="cpu", num_points=args.num_points, max_grasps=args.max_grasps)).eval()
        source = "untrained RTV3Policy (no checkpoint found)"
    n, m = policy.config.num_points, policy.config.max_grasps
    print(f"policy: {source}; N={n} points, M={m} grasps, K={policy.config.num_maneuver_classes} classes, "
          f"{sum(p.numel() for p in policy.parameters()) / 1e6:.2f} M parameters, {torch.get_num_threads()} thread(s)")

    env = SharedControlEnv(num_points=n, max_grasps=m)
    # The timed controller is driven directly (no wrapper method) so only step() is measured.
    margin = None if args.goal_belief_margin.strip().lower() == "off" else float(args.goal_belief_margin)
    config = SharedControlConfig(max_linear_speed=0.3, max_angular_speed=1.2, goal_belief_margin=margin)
    controller = SharedController(policy, config)
    # A mode-switching user who pauses (20 steps of commands, 10 of none) gives shared,
    # user-only (OOD window) and, away from the scene surface, autonomous steps; every step
    # runs the prior, so all of them count.
    results: dict[str, list[float]] = {"shared": [], "autonomous": [], "user_only": [], "all": []}
    repeat_medians: list[float] = []
    user = make_user("mode_switching", seed=0, pauses=(20, 10))
    for repeat in range(args.repeats):
        env.reset(seed=args.seed)
        controller.reset()
        user.reset(env.user_goal())
        obs = env._obs
        this_repeat: list[float] = []
        for i in tqdm(range(args.warmup + args.steps), desc=f"SharedController.step {repeat + 1}/{args.repeats}",
                      unit="step"):
            pose = env.base.tcp_pose_matrix[0].double()
            command = user(pose)[None]
            observation = observation_from_env(obs)
            start = time.perf_counter()
            twist = controller.step(observation, command)
            elapsed = time.perf_counter() - start
            if i >= args.warmup:
                results[controller.last_diagnostics.modes[0]].append(elapsed)
                results["all"].append(elapsed)
                this_repeat.append(elapsed)
            obs, _, _, _, info = env.env.step(torch.cat([twist[0].float(), torch.ones(1)])[None])
            if bool(info["success"][0]) or i % 90 == 89:  # restart the approach
                env.reset(seed=args.seed)
                controller.reset()
                user.reset(env.user_goal())
                obs = env._obs
        repeat_medians.append(1000 * statistics.median(this_repeat))
    env.close()

    print(f"{'case':12s} {'n':>5s} {'median ms':>10s} {'p90 ms':>8s} {'max ms':>8s}")
    for case, values in results.items():
        if not values:
            print(f"{case:12s} {0:5d}  (no step in this mode)")
            continue
        ms = [1000 * v for v in values]
        print(f"{case:12s} {len(ms):5d} {statistics.median(ms):10.2f} {_percentile(ms, 90):8.2f} {max(ms):8.2f}")
    median = statistics.median(repeat_medians)
    print("per-repeat medians (ms): " + ", ".join(f"{m:.2f}" for m in repeat_medians))
    print(f"median SharedController.step latency: {median:.2f} ms (median of {args.repeats} repeat medians; "
          f"target <= 10 ms: {'met' if median <= 10 else 'NOT met'})")
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
