"""``rtv3 learning-curve OUT``: the paper-prior campaign's learning curve (validation planning against trajectories).

Reads every stage folder of a ``scripts/train_paper_prior.sh`` output (``OUT/demos_K``, ``OUT/dagger_R``, ``OUT/long``:
``cache/summary.json``, ``run/checkpoints/last/model.safetensors``, ``planning/planning_summary.json``) and
writes ``OUT/curve.csv`` and ``OUT/curve.png``; with ``--best`` it prints the checkpoint folder of the stage
with the highest validation SR (fewer collisions break a tie) instead.
"""

from __future__ import annotations

import argparse
import csv
import json
import re
import sys
from pathlib import Path

from safetensors import safe_open

STAGE = re.compile(r"^(?:(?:demos|dagger)_\d+|long)$")
FIELDS = ("stage", "trajectories", "frames", "model_step", "trials", "SR", "CR", "TOR")


def _model_step(weights: Path) -> int:
    with safe_open(str(weights), framework="pt") as f:
        return int(f.get_tensor("train_step").item()) if "train_step" in f.keys() else 0


def stages(out: Path) -> list[dict]:
    """One row per evaluated stage, in training order: each stage trains on every dataset so far, from the one
    before, so the order is that of (trajectories seen, model step), however chunks and DAgger rounds interleave."""
    found = []
    for folder in out.iterdir():
        planning = folder / "planning" / "planning_summary.json"
        if not STAGE.match(folder.name) or not planning.is_file():
            continue
        cache = json.loads((folder / "cache" / "summary.json").read_text())
        plan = json.loads(planning.read_text())
        found.append(dict(
            stage=folder.name, trajectories=cache["episodes"], frames=cache["frames"],
            model_step=_model_step(folder / "run" / "checkpoints" / "last" / "model.safetensors"),
            trials=plan["trials"], SR=plan["SR"], CR=plan["CR"], TOR=plan["TOR"],
            checkpoint=str(folder / "run" / "checkpoints" / "last")))
    return sorted(found, key=lambda row: (row["trajectories"], row["model_step"]))


def plot(rows: list[dict], path: Path) -> None:
    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    fig, ax = plt.subplots(figsize=(6, 3.6))
    x = [r["trajectories"] for r in rows]
    ax.plot(x, [100 * r["SR"] for r in rows], "o-", label="SR")
    ax.plot(x, [100 * r["CR"] for r in rows], "s--", label="CR")
    for r in rows:
        ax.annotate(r["stage"], (r["trajectories"], 100 * r["SR"]), fontsize=7, xytext=(3, 4),
                    textcoords="offset points")
    ax.set_xlabel("trajectories seen (demonstrations + relabels)")
    ax.set_ylabel("validation planning, % of trials")
    ax.set_title(f"paper prior from scratch ({rows[-1]['trials']} trials per stage, seed block 8)", fontsize=9)
    ax.set_ylim(0, 100)
    ax.grid(alpha=0.3)
    ax.legend()
    fig.tight_layout()
    fig.savefig(path, dpi=130)
    plt.close(fig)


def add_arguments(parser: argparse.ArgumentParser) -> None:
    parser.add_argument("out", type=Path, help="the campaign's output folder (OUT)")
    parser.add_argument("--best", action="store_true", help="print the best stage's checkpoint folder")


def run(args: argparse.Namespace) -> int:
    if not args.out.is_dir():
        print(f"error: no campaign output folder {args.out}", file=sys.stderr)
        return 1
    rows = stages(args.out)
    if not rows:
        print(f"error: no evaluated stage in {args.out} yet", file=sys.stderr)
        return 1
    if args.best:
        print(max(rows, key=lambda r: (r["SR"], -r["CR"]))["checkpoint"])
        return 0
    with open(args.out / "curve.csv", "w", newline="") as f:
        writer = csv.DictWriter(f, fieldnames=FIELDS, extrasaction="ignore")
        writer.writeheader()
        writer.writerows(rows)
    plot(rows, args.out / "curve.png")
    for r in rows:
        print(f"{r['stage']:>9}: {r['trajectories']:>6} trajectories, step {r['model_step']:>6}: "
              f"SR {100 * r['SR']:.1f} CR {100 * r['CR']:.1f} TOR {100 * r['TOR']:.1f} ({r['trials']} trials)")
    return 0
