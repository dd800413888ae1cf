"""``rtv3 evaluate``: the RT-V3 prior's benchmarks (paper Table I).

* ``rtv3 evaluate prediction --policy.path P --dataset.root D (--scene-seeds A:B | --last-fraction F | --all-scenes)``:
  ADE/FDE x1000, Best-of-Mode and Most-Likely, on held-out 20-step windows of a dataset.
* ``rtv3 evaluate planning --policy.path P [--scenes 20] [--seed 9] [--max-grasps-per-scene 2] [--output DIR]``:
  closed-loop planning in GraspClutter-v1: SR / CR / TOR (resumable).

See ``rtv3_maniskill/benchmarks/prediction.py`` and ``planning.py`` for the protocols.
"""

from __future__ import annotations

import argparse
import json
from pathlib import Path

from rtv3_maniskill.cli.scene_args import add_scene_arguments, scene_settings


def _seed_range(text: str) -> tuple[int, int]:
    from rtv3_maniskill.benchmarks.prediction import parse_seed_range

    try:
        return parse_seed_range(text)
    except ValueError as err:
        raise argparse.ArgumentTypeError(str(err)) from None


def add_arguments(parser: argparse.ArgumentParser) -> None:
    sub = parser.add_subparsers(dest="evaluation", metavar="BENCHMARK", required=True)

    pred = sub.add_parser(
        "prediction", help="ADE/FDE (x1000), Best-of-Mode and Most-Likely, on held-out dataset windows",
        description="Open-loop trajectory prediction on 20-step windows (T=8 history incl. the current step, "
        "H=12 future) of held-out episodes. Held-out = chosen by the dataset's scene_seed column.",
    )
    pred.add_argument("--policy.path", dest="policy_path", type=Path, required=True, help="RT-V3 checkpoint folder")
    pred.add_argument("--dataset.root", dest="dataset_root", type=Path, required=True, help="LeRobot dataset folder")
    held = pred.add_mutually_exclusive_group(required=True)
    held.add_argument("--scene-seeds", type=_seed_range, default=None, metavar="A:B",
                      help="evaluate the episodes with A <= scene_seed < B")
    held.add_argument("--last-fraction", type=float, default=None, metavar="F",
                      help="evaluate the last fraction F of the dataset's scenes (largest seeds)")
    held.add_argument("--all-scenes", action="store_true",
                      help="evaluate every episode (a dataset generated with a seed not used for training)")
    pred.add_argument("--max-windows", type=int, default=None, help="seeded random subset of the windows")
    pred.add_argument("--batch-size", type=int, default=64)
    pred.add_argument("--seed", type=int, default=0, help="seed of the --max-windows subset")
    pred.add_argument("--output", type=Path, default=None, help="JSON report file")
    pred.set_defaults(_evaluate=_run_prediction)

    plan = sub.add_parser(
        "planning", help="closed-loop planning in GraspClutter-v1: SR / CR / TOR (resumable)",
        description="The policy drives the robot with its most likely action from a random start to the "
        "target grasp's pre-grasp; success when the pose distance (rot weight 0.3/pi) is < 0.2, collision = "
        "any robot contact, timeout after 150 steps. Finished (scene, grasp) trials are skipped on a rerun.",
    )
    plan.add_argument("--policy.path", dest="policy_path", type=Path, default=None,
                      help="RT-V3 checkpoint folder (needed unless --planner neoss)")
    plan.add_argument("--planner", default="policy", choices=["policy", "neoss"],
                      help="policy: the prior's most likely actions; neoss: the paper's reactive baseline, a straight "
                           "twist to the pre-grasp through the NEO collision damper (Table I's NeoSS row)")
    plan.add_argument("--scenes", type=int, default=20, help="number of scenes")
    plan.add_argument("--seed", type=int, default=9,
                      help="scene i uses seed SEED*100000 + i (rtv3 generate's numbering): "
                           "pick one no training data used")
    plan.add_argument("--max-grasps-per-scene", type=int, default=2,
                      help="target grasps per scene (seeded random subset; the paper uses 2; 0 = all)")
    plan.add_argument("--context", default="target", choices=["target", "all"],
                      help="grasps the policy sees: only the trial's target (paper) or every candidate (success = any)")
    plan.add_argument("--point-cloud", default="rendered", choices=["rendered", "mesh"],
                      help="scene cloud source; match the training data (rtv3 generate --context)")
    add_scene_arguments(plan)
    plan.add_argument("--max-steps", type=int, default=150, help="steps before a timeout (150 = 7.5 s)")
    plan.add_argument("--output", type=Path, default=Path("outputs/planning"), help="results folder")
    plan.set_defaults(_evaluate=_run_planning)


def _run_prediction(args: argparse.Namespace) -> int:
    import torch

    from rtv3_maniskill.benchmarks.prediction import format_table, run_prediction_evaluation

    torch.set_num_threads(1)
    try:
        report = run_prediction_evaluation(
            args.policy_path, args.dataset_root, seed_range=args.scene_seeds, last_fraction=args.last_fraction,
            all_scenes=args.all_scenes, max_windows=args.max_windows, batch_size=args.batch_size, seed=args.seed,
            output=args.output,
        )
    except (FileNotFoundError, ValueError) as err:
        raise SystemExit(f"error: {err}") from None
    print(format_table(report))
    if args.output is not None:
        print(f"wrote {args.output}")
    return 0


def _run_planning(args: argparse.Namespace) -> int:
    from rtv3_maniskill.benchmarks.planning import PlanningConfig, run_planning_benchmark

    try:
        config = PlanningConfig(
            output=args.output, policy_path=args.policy_path, scenes=args.scenes, seed=args.seed,
            max_grasps_per_scene=None if args.max_grasps_per_scene == 0 else args.max_grasps_per_scene,
            context=args.context, point_cloud=args.point_cloud, **scene_settings(args), max_steps=args.max_steps,
            planner=args.planner,
        )
        summary = run_planning_benchmark(config)
    except (FileNotFoundError, ValueError) as err:
        raise SystemExit(f"error: {err}") from None
    rates = "  ".join(
        f"{k} {'n/a' if summary[k] is None else f'{100 * summary[k]:.1f} %'}" for k in ("SR", "CR", "TOR")
    )
    print(f"{summary['trials']} trials ({summary['no_start_pose']} without a start pose left out): {rates}")
    shown = ("success", "collision", "timeout", "mean_steps_success", "collisions_with")
    print(json.dumps({k: summary[k] for k in shown}))
    print(f"wrote {config.output / 'planning_trials.csv'} and {config.output / 'planning_summary.json'}")
    return 0


def run(args: argparse.Namespace) -> int:
    return int(args._evaluate(args) or 0)
