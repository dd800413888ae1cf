"""``rtv3 evaluate``: the RT-V3 prior's benchmarks (paper Table I).

* ``rtv3 evaluate prediction --policy.path P --dataset.root D (--scene-seeds A:B | --last-fraction F | --all-scenes)``:
  ADE/FDE x1000, Best-of-Mode and Most-Likely, on held-out 20-step windows of a dataset.
* ``rtv3 evaluate planning --policy.path P [--scenes 20] [--seed 9] [--max-grasps-per-scene 2] [--output DIR]``:
  closed-loop planning in GraspClutter-v1: SR / CR / TOR (resumable).
* ``rtv3 evaluate ablations --runs DIR --dataset.root D [--step N] [--scenes 20]``: Table I's ablation rows,
  both benchmarks above for each ``lerobot-train`` run of DIR at one common step (resumable).

See ``rtv3_maniskill/benchmarks/prediction.py`` and ``planning.py`` for the protocols.
"""

from __future__ import annotations

import argparse
import json
from pathlib import Path
from typing import Any

from rtv3_maniskill.cli.scene_args import add_scene_arguments, policy_path, scene_settings


def _seed_range(text: str) -> tuple[int, int]:
    from rtv3_maniskill.benchmarks.held_out_windows import parse_seed_range

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
                      help="RT-V3 checkpoint folder or Hub repo id (default: the scene preset's; unused with --planner "
                           "neoss)")
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
    plan.add_argument("--compare-with", type=Path, default=None, metavar="DIR",
                      help="a finished run's output folder (e.g. another checkpoint on the same --seed and --scenes): "
                           "wins / losses against it on the trials both ran, with an exact McNemar test")
    plan.set_defaults(_evaluate=_run_planning)

    abl = sub.add_parser(
        "ablations", help="Table I ablation rows: prediction and planning of each run at one common step",
        description="For each lerobot-train output folder RUNS/ROW (ROW: " + ", ".join(ABLATION_ROWS) + ") "
        "the checkpoint at --step (default: the largest step every row has saved, so all rows had the same "
        "budget) runs `evaluate prediction --all-scenes` and `evaluate planning`; writes table1.md and "
        "table1.json into RUNS. Finished evaluations are reused, planning resumes.",
    )
    abl.add_argument("--runs", type=Path, default=Path("outputs/ablations"), help="folder of the run folders")
    abl.add_argument("--dataset.root", dest="dataset_root", type=Path, default=Path("data/heldout"),
                     help="held-out LeRobot dataset (generated with a seed no training data used)")
    abl.add_argument("--step", type=int, default=None, help="checkpoint step (default: the largest common one)")
    abl.add_argument("--scenes", type=int, default=20, help="planning scenes (2 target grasps each)")
    abl.set_defaults(_evaluate=_run_ablations)


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
            output=args.output, policy_path=None if args.planner == "neoss" else policy_path(args),
            scenes=args.scenes, seed=args.seed,
            max_grasps_per_scene=None if args.max_grasps_per_scene == 0 else args.max_grasps_per_scene,
            context=args.context, point_cloud=args.point_cloud, **scene_settings(args), max_steps=args.max_steps,
            planner=args.planner,
        )
        summary = run_planning_benchmark(config, baseline=args.compare_with)
    except (FileNotFoundError, ValueError) as err:
        raise SystemExit(f"error: {err}") from None
    def rates(stats: dict) -> str:
        return "  ".join(f"{k} {'n/a' if stats[k] is None else f'{100 * stats[k]:.1f} %'}" for k in ("SR", "CR", "TOR"))

    print(f"{summary['trials']} trials ({summary['no_start_pose']} without a start pose left out): {rates(summary)}")
    reachable, checks = summary["arm_reachable"], summary["goal_checks"]
    others = ", ".join(f"{n} {c}" for c, n in checks.items() if c != "feasible") or "none"
    print(f"on the {reachable['trials']} trials whose target the arm can reach (others: {others}): {rates(reachable)}")
    shown = ("success", "collision", "timeout", "mean_steps_success", "collisions_with")
    print(json.dumps({k: summary[k] for k in shown}))
    if "paired_with" in summary:
        paired = summary["paired_with"]
        print(f"against {paired['baseline']} on the {paired['paired_trials']} trials both ran: SR "
              f"{100 * paired['SR']:.1f} vs {100 * paired['baseline_SR']:.1f} %, wins / losses {paired['wins']} / "
              f"{paired['losses']}, exact McNemar p {paired['mcnemar_p']:.3g}")
    print(f"wrote {config.output / 'planning_trials.csv'} and {config.output / 'planning_summary.json'}")
    return 0


ABLATION_ROWS = {
    "full": "RT-V3 (full)",
    "no_grasp_encoder": "w/o grasp encoder",
    "no_point_encoder": "w/o point-cloud encoder",
    "6d_pred": "6D pred (joint 6-D Gaussian)",
}
"""Run folder name -> table row; the rows train with ``--policy.use_grasp_encoder=false``,
``--policy.use_point_encoder=false`` and ``--policy.factorized_rotation=false`` (docs/RESULTS.md)."""
PAPER_ABLATIONS = {  # the paper's rows (their data and compute); their encoder-free row drops *both* encoders
    "full": {"ade_bom": 26.70, "fde_bom": 37.90, "ade_ml": 32.05, "fde_ml": 47.87, "SR": 0.904, "CR": 0.079,
             "TOR": 0.017},
    "no_point_encoder": {"ade_bom": 26.95, "fde_bom": 38.12, "ade_ml": 30.36, "fde_ml": 44.17, "SR": 0.788,
                         "CR": 0.103, "TOR": 0.109},
    "6d_pred": {"ade_bom": 21.05, "fde_bom": 34.55, "ade_ml": 22.50, "fde_ml": 37.65, "SR": 0.034, "CR": 0.687,
                "TOR": 0.279},
}
_PREDICTION = ("ade_bom", "fde_bom", "ade_ml", "fde_ml")
_PLANNING = ("SR", "CR", "TOR")


def saved_checkpoints(run: Path) -> dict[int, Path]:
    """Step -> ``pretrained_model`` folder of each complete checkpoint of a ``lerobot-train`` output folder."""
    root = run / "checkpoints"
    found = {}
    for folder in sorted(root.iterdir()) if root.is_dir() else ():
        model = folder / "pretrained_model"
        if folder.name.isdigit() and (model / "model.safetensors").is_file():
            found[int(folder.name)] = model
    return found


def ablation_table(rows: dict[str, dict[str, Any]], step: int, scenes: int) -> str:
    """Markdown table of the rows (values as in ``table1.json``), the paper's values in brackets."""

    def cell(row: str, key: str) -> str:
        scale, digits = (100.0, 1) if key in _PLANNING else (1.0, 2)
        text = f"{scale * rows[row][key]:.{digits}f}"
        paper = PAPER_ABLATIONS.get(row, {})
        return text + (f" ({scale * paper[key]:.{digits}f})" if key in paper else "")

    lines = [f"Table I at equal compute: every row at training step {step}. ADE/FDE x1000 on the held-out "
             f"scenes; planning on {scenes} scenes x 2 grasps. Paper values in brackets.", "",
             "| model | ADE BoM | FDE BoM | ADE ML | FDE ML | SR % | CR % | TOR % |",
             "|---|---|---|---|---|---|---|---|"]
    lines += [f"| {ABLATION_ROWS[row]} | " + " | ".join(cell(row, k) for k in _PREDICTION + _PLANNING) + " |"
              for row in rows]
    return "\n".join(lines) + "\n"


def _run_ablations(args: argparse.Namespace) -> int:
    runs = {row: saved_checkpoints(args.runs / row) for row in ABLATION_ROWS if (args.runs / row).is_dir()}
    if not runs:
        raise SystemExit(f"error: no run folder ({', '.join(ABLATION_ROWS)}) under {args.runs}")
    common = set.intersection(*(set(steps) for steps in runs.values()))
    step = max(common, default=None) if args.step is None else args.step
    if step is None or step not in common:
        raise SystemExit(f"error: step {step} is not saved by every row ({', '.join(runs)}); "
                         f"common steps: {sorted(common)}")
    print(f"rows {', '.join(runs)} at step {step}")
    parser = argparse.ArgumentParser(prog="rtv3 evaluate")
    add_arguments(parser)  # each evaluation runs as its own `rtv3 evaluate` command line would
    rows = {}
    for row, checkpoints in runs.items():
        ckpt, out = checkpoints[step], args.runs / f"eval_{row}_{step}"
        prediction, planning = out / "prediction.json", out / "planning"
        if not prediction.is_file():
            prediction.parent.mkdir(parents=True, exist_ok=True)
            evaluation = parser.parse_args(["prediction", "--policy.path", str(ckpt), "--dataset.root",
                                            str(args.dataset_root), "--all-scenes", "--output", str(prediction)])
            evaluation._evaluate(evaluation)
        evaluation = parser.parse_args(["planning", "--policy.path", str(ckpt), "--scenes", str(args.scenes),
                                        "--output", str(planning)])
        evaluation._evaluate(evaluation)
        pred = json.loads(prediction.read_text())
        plan = json.loads((planning / "planning_summary.json").read_text())
        rows[row] = {**{k: pred["metrics"][k] for k in _PREDICTION}, **{k: plan[k] for k in _PLANNING},
                     "planning_trials": plan["trials"], "prediction_windows": pred["num_windows"],
                     "checkpoint": str(ckpt)}
    report = {"step": step, "rows": rows, "paper": PAPER_ABLATIONS}
    (args.runs / "table1.json").write_text(json.dumps(report, indent=2))
    table = ablation_table(rows, step, args.scenes)
    (args.runs / "table1.md").write_text(table)
    print(table + f"wrote {args.runs / 'table1.md'} and {args.runs / 'table1.json'}")
    return 0


def run(args: argparse.Namespace) -> int:
    return int(args._evaluate(args) or 0)
