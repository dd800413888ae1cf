"""Trace closed-loop planning trials: where does the prior go wrong, translation or rotation?

Runs trials of the planning benchmark (same start poses, success rule and contact rule as
``rtv3 evaluate planning``) and writes, per trial, a CSV of every step (pose distance,
translation error m, rotation error deg to the target's pre-grasp, commanded |v| and |w|)
and one figure with all trials.

Usage: ``python scripts/trace_planning_trial.py [--policy.path DIR] --trial 900006:0 --trial 900004:17
[--output outputs/planning_trace]``
"""

from __future__ import annotations

import argparse
import csv
import math
from pathlib import Path

import numpy as np
import torch


def _trial(text: str) -> tuple[int, int]:
    try:
        scene, grasp = (int(v) for v in text.split(":"))
    except ValueError:
        raise argparse.ArgumentTypeError(f"expected SCENE_SEED:GRASP_INDEX, got {text!r}") from None
    return scene, grasp


def main() -> None:
    from rtv3_maniskill.policies.rtv3.checkpoints import SHIPPED_CHECKPOINT, load_policy

    parser = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    parser.add_argument("--policy.path", dest="policy_path", type=Path, default=SHIPPED_CHECKPOINT)
    parser.add_argument("--trial", dest="trials", type=_trial, action="append", required=True,
                        help="SCENE_SEED:GRASP_INDEX (repeatable)")
    parser.add_argument("--max-steps", type=int, default=150)
    parser.add_argument("--output", type=Path, default=Path("outputs/planning_trace"))
    args = parser.parse_args()

    from rtv3_maniskill.experiments.planning import PlanningBenchmark, PlanningConfig

    torch.set_num_threads(1)
    policy = load_policy(args.policy_path)
    bench = PlanningBenchmark(PlanningConfig(output=args.output, policy_path=args.policy_path, scenes=1,
                                             max_steps=args.max_steps), policy)
    args.output.mkdir(parents=True, exist_ok=True)
    traces = {}
    try:
        for scene, grasp in args.trials:
            valid = bench.load_scene(scene)
            if grasp not in valid:
                raise SystemExit(f"error: grasp {grasp} is not a valid grasp of scene {scene} (valid: {valid})")
            trace: list[dict[str, float]] = []
            row = bench.run_trial(grasp, trace)
            traces[(scene, grasp)] = (row, trace)
            path = args.output / f"trace_{scene}_{grasp}.csv"
            with path.open("w", newline="") as f:
                writer = csv.DictWriter(f, fieldnames=list(trace[0]) if trace else ["step"])
                writer.writeheader()
                writer.writerows(trace)
            cos_v = float(np.median([r["linear_alignment"] for r in trace])) if trace else float("nan")
            cos_w = float(np.median([r["angular_alignment"] for r in trace])) if trace else float("nan")
            touched = f" with the {row['contact']}" if row["contact"] else ""
            last = trace[-1] if trace else {}
            print(f"scene {scene} grasp {grasp}: {row['outcome']}{touched} after {row['steps']} steps "
                  f"(start distance {row['start_distance']}, final {row['final_distance']}; median cosine with "
                  f"the way to the pre-grasp: v {cos_v:.2f}, w {cos_w:.2f}); last step: TCP "
                  f"{last.get('tcp_height', math.nan):.3f} m above the table, "
                  f"{last.get('translation_error', math.nan):.3f} m from the pre-grasp, approach "
                  f"{last.get('approach_error_deg', math.nan):.0f} deg and roll "
                  f"{last.get('roll_error_deg', math.nan):.0f} deg off; wrote {path}")
    finally:
        bench.close()

    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    fig, axes = plt.subplots(1, 4, figsize=(18, 3.8))
    for (scene, grasp), (row, trace) in traces.items():
        steps = [r["step"] for r in trace]
        label = f"{scene}:{grasp} ({row['outcome']})"
        line = axes[0].plot(steps, [r["translation_error"] for r in trace], label=label)[0]
        axes[1].plot(steps, [r["rotation_error_deg"] for r in trace], color=line.get_color())
        axes[2].plot(steps, [r["angular_speed"] for r in trace], color=line.get_color())
        axes[3].plot(steps, [r["angular_alignment"] for r in trace], color=line.get_color())
    titles = ("translation error to pre-grasp (m)", "rotation error (deg)", "commanded |w| (rad/s)",
              "cosine of w with the turn to the pre-grasp")
    for ax, title in zip(axes, titles):
        ax.set_title(title)
        ax.set_xlabel("step (20 Hz)")
        ax.grid(alpha=0.3)
    axes[0].legend(fontsize=8)
    fig.suptitle(f"closed-loop most-likely actions of {args.policy_path.name}")
    fig.tight_layout()
    fig.savefig(args.output / "trace.png", dpi=110)
    print(f"wrote {args.output / 'trace.png'}")


if __name__ == "__main__":
    main()
