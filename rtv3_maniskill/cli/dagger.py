"""``rtv3 dagger``: one DAgger round with the motion planner as the expert -> LeRobot v3 dataset.

Resumable: rerun the same command after an interruption (finished rollouts and relabels are kept).
"""

from __future__ import annotations

import argparse
import json
from pathlib import Path

from rtv3_maniskill.cli.scene_args import (
    add_clearance_argument,
    add_executor_arguments,
    add_fusion_argument,
    add_push_argument,
    add_scene_arguments,
    check_push_argument,
    fusion_name,
    policy_path,
    push_if_asked,
    resolve_scene_arguments,
)
from rtv3_maniskill.datagen.dagger_config import DEFAULT_DRIVERS, FAILURE_WINDOW_STEPS, FAILURE_WINDOWS, DaggerConfig


def add_arguments(parser: argparse.ArgumentParser) -> None:
    parser.add_argument("--policy.path", dest="policy_path", type=Path, default=None,
                        help="checkpoint whose closed loop is rolled out (default: the scene preset's)")
    parser.add_argument("--output", type=Path, required=True, help="dataset folder (LeRobot root)")
    parser.add_argument("--num-scenes", type=int, default=50, help="training scenes to roll out in")
    parser.add_argument("--seed", type=int, default=5,
                        help="scene i uses seed SEED*100000 + i (keep it apart from the benchmark blocks 7-9)")
    parser.add_argument("--drivers", default=",".join(DEFAULT_DRIVERS),
                        help="comma list: 'prior' and METHOD:USER with METHOD direct or rtv3")
    parser.add_argument("--targets-per-scene", type=int, default=4, help="targets per scene (0 = all)")
    parser.add_argument("--relabels-per-rollout", type=int, default=3, help="visited states re-planned per rollout")
    parser.add_argument("--failure-relabels", type=int, default=0,
                        help=f"states re-planned from {FAILURE_WINDOW_STEPS} steps of a failed rollout instead "
                             "(0: spread like the others)")
    parser.add_argument("--failure-window", choices=FAILURE_WINDOWS, default="last",
                        help="where those steps lie: the rollout's last ones, or those from its closest approach "
                             "to the pre-grasp on (drift: where a rollout that ran off turned away)")
    add_scene_arguments(parser)
    add_fusion_argument(parser)
    parser.add_argument("--plan-timeout", type=float, default=3.0, help="seconds per OMPL query")
    add_clearance_argument(parser)
    parser.add_argument("--workers", type=int, default=1, help="parallel CPU workers (processes or Ray actors)")
    add_executor_arguments(parser)
    add_push_argument(parser)


def dagger_config(args: argparse.Namespace) -> DaggerConfig:
    """The round's settings from the parsed options (the preset's scenes, execution and RT-V3 fusion).

    Raises:
        ValueError: a bad option (the message names it).
    """
    resolve_scene_arguments(args)
    return DaggerConfig(
        output=args.output, policy_path=policy_path(args), scenes=args.num_scenes, seed=args.seed,
        drivers=tuple(d for d in args.drivers.split(",") if d.strip()),
        targets_per_scene=args.targets_per_scene or None, relabels_per_rollout=args.relabels_per_rollout,
        failure_relabels=args.failure_relabels, failure_window=args.failure_window,
        scene_type=args.scene_type, objects=args.objects,
        execution=args.execution, self_contacts=args.self_contacts, fusion=fusion_name(args),
        plan_timeout=args.plan_timeout, clearance=args.clearance, workers=args.workers)


def run(args: argparse.Namespace) -> int:
    from rtv3_maniskill.datagen.dagger import run_dagger
    from rtv3_maniskill.scene_pool import SceneWorkerError

    check_push_argument(args)

    from rtv3_maniskill.policies.rtv3.checkpoints import CheckpointError, resolve_checkpoint

    try:
        resolve_checkpoint(policy_path(args))
    except CheckpointError as err:
        raise SystemExit(f"error: {err}") from None
    try:
        config = dagger_config(args)
    except ValueError as err:
        raise SystemExit(f"error: {err}") from None
    if not config.output.parent.is_dir():
        raise SystemExit(f"error: the parent folder of --output does not exist: {config.output.parent}")
    try:
        summary = run_dagger(config, executor=args.executor, ray_address=args.ray_address)
    except (ValueError, SceneWorkerError) as err:  # a folder holding a round made with other settings, a worker
        raise SystemExit(f"error: {err}") from None
    print(json.dumps({k: v for k, v in summary.items() if k != "config"}, indent=2))
    push_if_asked(args, config.output, "DAgger relabels (the motion planner re-planning from states visited by the "
                  "RT-V3 prior and by simulated users)")
    return 0
