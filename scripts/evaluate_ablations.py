"""Paper Table I rows from the runs of ``scripts/train_ablations.sh``.

For every row (a ``lerobot-train`` output folder under ``--runs``) it takes the checkpoint
at ``--step`` (default: the largest step that every row has saved, so all rows had the same
budget), runs ``rtv3 evaluate prediction`` (ADE/FDE on the held-out dataset) and ``rtv3
evaluate planning`` (closed-loop SR/CR/TOR), and writes ``table1.md`` / ``table1.json`` and
a bar plot ``table1.png`` into ``--runs``. Finished evaluations are reused (resumable).

Usage: ``python scripts/evaluate_ablations.py [--runs outputs/ablations] [--step N]
[--dataset-root data/heldout] [--scenes 20]``
"""

from __future__ import annotations

import argparse
import json
import subprocess
import sys
from pathlib import Path

ROWS = {
    "full": "RT-V3 (full)",
    "no_grasp_encoder": "w/o grasp encoder",
    "no_point_encoder": "w/o point-cloud encoder",
    "6d_pred": "6D pred (joint 6-D Gaussian)",
}
PAPER = {  # paper Table I (their data and compute); their first row drops *both* encoders
    # (42.71 / 83.79 / 46.40 / 92.89, no planning numbers), so "w/o grasp encoder" has no paper twin.
    "full": {"ade_bom": 26.70, "fde_bom": 37.90, "ade_ml": 32.05, "fde_ml": 47.87,
             "SR": 0.904, "CR": 0.079, "TOR": 0.017},
    "no_point_encoder": {"ade_bom": 26.95, "fde_bom": 38.12, "ade_ml": 30.36, "fde_ml": 44.17,
                         "SR": 0.788, "CR": 0.103, "TOR": 0.109},
    "6d_pred": {"ade_bom": 21.05, "fde_bom": 34.55, "ade_ml": 22.50, "fde_ml": 37.65,
                "SR": 0.034, "CR": 0.687, "TOR": 0.279},
}
METRICS = ("ade_bom", "fde_bom", "ade_ml", "fde_ml")


def saved_steps(run: Path) -> set[int]:
    """Steps with a complete checkpoint (``checkpoints/<step>/pretrained_model``) in a lerobot-train folder."""
    root = run / "checkpoints"
    if not root.is_dir():
        return set()
    return {
        int(p.name) for p in root.iterdir()
        if p.name.isdigit() and (p / "pretrained_model" / "model.safetensors").is_file()
    }


def run_cli(args: list[str]) -> None:
    cmd = [sys.executable, "-m", "rtv3_maniskill.cli", *args]
    print("$ rtv3 " + " ".join(args), flush=True)
    subprocess.run(cmd, check=True)


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    parser.add_argument("--runs", type=Path, default=Path("outputs/ablations"))
    parser.add_argument("--step", type=int, default=None, help="checkpoint step (default: largest common step)")
    parser.add_argument("--dataset-root", type=Path, default=Path("data/heldout"))
    parser.add_argument("--scenes", type=int, default=20, help="planning scenes (2 grasps each)")
    args = parser.parse_args()

    rows = [r for r in ROWS if (args.runs / r).is_dir()]
    if not rows:
        raise SystemExit(f"error: no run folder of {list(ROWS)} under {args.runs} (run scripts/train_ablations.sh)")
    common = set.intersection(*(saved_steps(args.runs / r) for r in rows))
    step = args.step if args.step is not None else max(common, default=None)
    if step is None or step not in common:
        raise SystemExit(f"error: step {step} is not saved by every row {rows}; common steps: {sorted(common)}")
    print(f"rows {rows} at step {step}")

    table = {}
    for row in rows:
        ckpt = args.runs / row / "checkpoints" / f"{step:06d}" / "pretrained_model"
        if not ckpt.is_dir():
            ckpt = args.runs / row / "checkpoints" / str(step) / "pretrained_model"
        out = args.runs / f"eval_{row}_{step}"
        out.mkdir(parents=True, exist_ok=True)
        pred_json = out / "prediction.json"
        if not pred_json.is_file():
            run_cli(["evaluate", "prediction", "--policy.path", str(ckpt), "--dataset.root", str(args.dataset_root),
                     "--all-scenes", "--output", str(pred_json)])
        run_cli(["evaluate", "planning", "--policy.path", str(ckpt), "--scenes", str(args.scenes),
                 "--output", str(out / "planning")])  # resumes from its own trial log
        pred = json.loads(pred_json.read_text())
        plan = json.loads((out / "planning" / "planning_summary.json").read_text())
        table[row] = {**{m: pred["metrics"][m] for m in METRICS}, **{k: plan[k] for k in ("SR", "CR", "TOR")},
                      "planning_trials": plan["trials"], "prediction_windows": pred["num_windows"],
                      "checkpoint": str(ckpt)}
        baselines = pred["baselines"]

    report = {"step": step, "rows": table, "paper": PAPER, "constant_velocity": {
        "ade": baselines["constant_velocity_ade"], "fde": baselines["constant_velocity_fde"]}}
    (args.runs / "table1.json").write_text(json.dumps(report, indent=2))

    lines = [f"Table I at equal compute: every row trained {step} steps (batch and data as in "
             "scripts/train_ablations.sh). ADE/FDE x1000 on the held-out scenes; planning on "
             f"{args.scenes} scenes x 2 grasps. Paper values in brackets.", "",
             "| model | ADE BoM | FDE BoM | ADE ML | FDE ML | SR % | CR % | TOR % |",
             "|---|---|---|---|---|---|---|---|"]
    for row, r in table.items():
        paper = PAPER.get(row, {})

        def cell(key: str, scale: float = 1.0, r=r, paper=paper) -> str:
            text = f"{scale * r[key]:.1f}" if scale != 1.0 else f"{r[key]:.2f}"
            if key in paper:
                text += f" ({scale * paper[key]:.1f})" if scale != 1.0 else f" ({paper[key]:.2f})"
            return text

        lines.append(f"| {ROWS[row]} | "
                     + " | ".join([*(cell(m) for m in METRICS), *(cell(k, 100.0) for k in ("SR", "CR", "TOR"))])
                     + " |")
    cv = report["constant_velocity"]
    lines.append(f"| constant velocity | — | — | {cv['ade']:.2f} | {cv['fde']:.2f} | — | — | — |")
    (args.runs / "table1.md").write_text("\n".join(lines) + "\n")
    print("\n".join(lines))

    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    fig, axes = plt.subplots(1, 2, figsize=(10, 3.5))
    names = [ROWS[r] for r in table]
    for ax, keys, title in ((axes[0], ("ade_ml", "fde_ml"), "prediction (x1000, lower is better)"),
                            (axes[1], ("SR", "CR", "TOR"), "planning (%)")):
        width = 0.8 / len(keys)
        for i, key in enumerate(keys):
            scale = 100.0 if key in ("SR", "CR", "TOR") else 1.0
            ax.bar([j + i * width for j in range(len(names))], [scale * table[r][key] for r in table], width, label=key)
        ax.set_xticks([j + 0.4 - width / 2 for j in range(len(names))], names, rotation=15, fontsize=8)
        ax.set_title(title)
        ax.set_ylim(top=1.3 * ax.get_ylim()[1])  # head room for the legend
        ax.legend(ncol=len(keys), loc="upper center", fontsize=8)
    fig.suptitle(f"RT-V3 ablations at {step} training steps each")
    fig.tight_layout()
    fig.savefig(args.runs / "table1.png", dpi=120)
    print(f"wrote {args.runs / 'table1.md'}, table1.json, table1.png")


if __name__ == "__main__":
    main()
