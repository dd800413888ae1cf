"""``rtv3 benchmark-shared``: simulated users x assistance methods over clutter scenes (paper Table II).

Resumable: run the same command again after an interruption; finished trials in
``OUTPUT/results.csv`` are skipped. Parallel: run disjoint ``--users`` / ``--methods`` in several
processes, each with its own ``--output``, then ``--merge DIR DIR ... --output NEW``.
"""

from __future__ import annotations

import argparse
from pathlib import Path
from typing import Any

from rtv3_maniskill.cli.scene_args import add_executor_arguments, add_scene_arguments, scene_settings
from rtv3_maniskill.presets import GOAL_RULES, get_preset


def _names(text: str) -> list[str]:
    return [part.strip() for part in text.split(",") if part.strip()]


def add_arguments(parser: argparse.ArgumentParser) -> None:
    parser.add_argument("--policy.path", dest="policy_path", type=Path, default=None,
                        help="RT-V3 checkpoint folder (config.json + model.safetensors); "
                             "default: rtv3_maniskill/checkpoints/rtv3_grasp_clutter")
    parser.add_argument("--scenes", type=int, default=50, help="clutter scenes (scene i: seed SEED*100000 + i)")
    parser.add_argument("--output", type=Path, default=Path("outputs/benchmark_shared"),
                        help="folder for results.csv, summary.csv, summary.md, success_rates.png")
    parser.add_argument("--users", type=_names, default="noisy,laggy,mode_switching,single_dof,low_dof",
                        help="comma-separated simulated users "
                             "(ideal, noisy, laggy, mode_switching, single_dof, low_dof)")
    parser.add_argument("--methods", type=_names, default="direct,ho,rtv3",
                        help="comma-separated assistance methods (direct, ho, rtv3, oracle, oracle-goal, oracle-plan, "
                             "rtv3-goal; the oracles run RT-V3's fusion with a prior that knows every goal / the true "
                             "goal / the true goal and the motion planner's path there; rtv3-goal is RT-V3 with its "
                             "prior shown only the true target grasp)")
    parser.add_argument("--seed", type=int, default=9,
                        help="scene seed block (default 9, the test block: held out from training scenes of "
                             "`rtv3 generate --seed 0..8`)")
    parser.add_argument("--goals-per-scene", "--max-grasps-per-scene", dest="goals_per_scene", type=int, default=None,
                        help="feasible goals per scene (seeded random subset; default: every feasible grasp; the "
                             "paper ran 10-20)")
    parser.add_argument("--max-steps", type=int, default=150, help="control steps per trial (20 Hz)")
    parser.add_argument("--continue-after-contact", action="store_true",
                        help="let a trial go on after a robot contact (still counted as a collision) instead of "
                             "ending it there as a failure (the paper's protocol, the default)")
    parser.add_argument("--obs-mode", default="state_dict", choices=["state_dict", "pointcloud"],
                        help="state_dict: mesh-sampled scene cloud; pointcloud: depth camera rendered every step")
    parser.add_argument("--mesh-context", action="store_true",
                        help="state_dict mode: use the mesh-sampled scene cloud instead of rendering it once per "
                             "scene from the depth camera (the default, as `rtv3 generate` stores it)")
    add_scene_arguments(parser)
    parser.add_argument("--goals", choices=GOAL_RULES, default=None,
                        help="goal rule (default: the preset's): all (every floating-hand-feasible grasp, the "
                             "authors' rule; paper) or reachable (only grasps the arm can reach without contact; "
                             "easy); goals.csv and summary.md count both")
    parser.add_argument("--fusion", choices=["tuned", "paper"], default="tuned",
                        help="RT-V3 fusion preset: tuned (default, chosen on validation scenes: predictive gate at "
                             "alpha 0.99, recursive goal belief, prior covariance x100, a command's zero axes missing "
                             "away from the scene) or paper (class-covariance gate at 0.85, no memory, x1); "
                             "the options below override single settings")
    parser.add_argument("--ood-alpha", type=float, default=None,
                        help="RT-V3 OOD gate chi-square quantile (tuned 0.99, paper 0.85); "
                             "higher trusts the prior more")
    parser.add_argument("--ood-covariance", choices=["class", "predictive"], default=None,
                        help="RT-V3 OOD gate distance under the class covariance (paper) or class + user noise (tuned)")
    parser.add_argument("--prior-covariance-scale", type=float, default=None,
                        help="factor on the prior's step-0 covariances before the gate and the fusion (tuned 100, "
                             "paper 1); larger gives the user's command more weight against an overconfident prior")
    parser.add_argument("--goal-belief-margin", type=_margin, default=None, metavar="NATS|off",
                        help="RT-V3 hands its prior only the grasp candidates within NATS of the most likely goal "
                             "under a recursive belief over the candidates (tuned 1); off: every candidate (paper)")
    parser.add_argument("--safety-filter", choices=["neoss"], default=None,
                        help="put the NEO collision damper in front of every method (the paper's 'w. NeoSS' rows; "
                             "results are named METHOD+neoss)")
    parser.add_argument("--workers", type=int, default=1,
                        help="run the scenes in this many processes (one core each; the results are the same as "
                             "one process's, trial for trial)")
    add_executor_arguments(parser)
    parser.add_argument("--no-progress", action="store_true", help="no progress bar")
    parser.add_argument("--merge", type=Path, nargs="+", metavar="DIR", default=None,
                        help="run nothing: combine finished runs of disjoint users or methods (e.g. one process per "
                             "method) into --output, which must be new")


def _margin(text: str) -> float | str:
    """``--goal-belief-margin``: a positive number of nats, or ``off``."""
    if text.strip().lower() == "off":
        return "off"
    try:
        value = float(text)
    except ValueError:
        raise argparse.ArgumentTypeError(f"expected a number of nats or 'off', got {text!r}") from None
    if not value > 0:
        raise argparse.ArgumentTypeError(f"the margin must be > 0 nats (or 'off'), got {text!r}")
    return value


def shared_control_overrides(args: argparse.Namespace) -> dict[str, Any]:
    """The ``SharedControlConfig`` fields the command line sets (``off`` -> None), the others left to the preset."""
    return {
        key: (None if value == "off" else value)
        for key in ("ood_alpha", "ood_covariance", "prior_covariance_scale",
                    "goal_belief_margin")
        if (value := getattr(args, key, None)) is not None
    }


def run(args: argparse.Namespace) -> int:
    from rtv3_maniskill.benchmarks.shared_benchmark import (
        BenchmarkConfig,
        BenchmarkError,
        merge_runs,
        run_benchmark,
        summary_markdown,
    )
    from rtv3_maniskill.scene_pool import SceneWorkerError

    if args.merge is not None:
        try:
            summary = merge_runs(args.merge, args.output)
        except BenchmarkError as err:
            raise SystemExit(f"error: {err}") from None
        print(summary_markdown(summary))
        print(f"merged {len(args.merge)} runs: {args.output}/results.csv, summary.csv, summary.md, success_rates.png")
        return 0

    users = _names(args.users) if isinstance(args.users, str) else args.users
    methods = _names(args.methods) if isinstance(args.methods, str) else args.methods
    try:
        config = BenchmarkConfig(
            output=args.output, policy_path=args.policy_path, scenes=args.scenes, users=users, methods=methods,
            seed=args.seed, goals_per_scene=args.goals_per_scene, max_steps=args.max_steps,
            stop_on_contact=not args.continue_after_contact, safety_filter=args.safety_filter,
            obs_mode=args.obs_mode, rendered_context=not args.mesh_context, **scene_settings(args),
            goals=args.goals or get_preset(args.preset).goals, fusion=args.fusion,
            shared_control=shared_control_overrides(args),
        )
        summary = run_benchmark(config, progress=not args.no_progress, workers=args.workers,
                                executor=args.executor, ray_address=args.ray_address)
    except (BenchmarkError, FileNotFoundError, SceneWorkerError) as err:
        raise SystemExit(f"error: {err}") from None
    print((args.output / "summary.md").read_text())
    print(f"results: {args.output}/results.csv, goals.csv, summary.csv, summary.md, success_rates.png")
    return 0
