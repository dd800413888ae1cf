"""Plot closed-loop planning SR / CR / TOR per training round and per training hour.

    python scripts/plot_training_rounds.py --round "stage 3 (old)":0:outputs/plan_stage3 \
        --round "fine-tune":0.8:outputs/plan_ft --round "DAgger r1":1.6:outputs/plan_r1 \
        --output docs/figures/training_rounds.png

Each ``--round LABEL:HOURS:DIR`` names a checkpoint, the cumulative training hours (CPU) behind it,
and the ``rtv3 evaluate planning --output DIR`` run that measured it (its planning_summary.json).
Writes the figure and a markdown table beside it (same name, .md).
"""

from __future__ import annotations

import argparse
import json
import sys
from pathlib import Path


def _round(text: str) -> tuple[str, float, Path]:
    label, hours, folder = text.rsplit(":", 2)
    summary = Path(folder) / "planning_summary.json"
    if not summary.is_file():
        raise argparse.ArgumentTypeError(f"no planning_summary.json in {folder} (run rtv3 evaluate planning there)")
    return label, float(hours), summary


def main(argv: list[str] | None = None) -> int:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--round", dest="rounds", action="append", type=_round, required=True,
                        metavar="LABEL:HOURS:DIR")
    parser.add_argument("--output", type=Path, default=Path("outputs/training_rounds.png"))
    args = parser.parse_args(argv)
    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    rows = []
    for label, hours, path in args.rounds:
        s = json.loads(path.read_text())
        s = s.get("summary", s)
        rows.append(dict(label=label, hours=hours, trials=s["trials"], SR=100 * s["SR"], CR=100 * s["CR"],
                         TOR=100 * s["TOR"]))
    fig, axes = plt.subplots(1, 2, figsize=(10, 3.8), sharey=True)
    x = range(len(rows))
    for key, color in (("SR", "tab:green"), ("CR", "tab:red"), ("TOR", "tab:gray")):
        axes[0].plot(x, [r[key] for r in rows], "o-", color=color, label=key)
        axes[1].plot([r["hours"] for r in rows], [r[key] for r in rows], "o-", color=color, label=key)
    axes[0].set_xticks(list(x), [r["label"] for r in rows], rotation=20, ha="right")
    axes[0].set_ylabel("% of planning trials")
    axes[0].set_title("per training round")
    axes[1].set_xlabel("cumulative training hours (CPU)")
    axes[1].set_title("per training hour")
    for ax in axes:
        ax.grid(alpha=0.3)
        ax.set_ylim(-2, 102)
    axes[0].legend()
    fig.tight_layout()
    args.output.parent.mkdir(parents=True, exist_ok=True)
    fig.savefig(args.output, dpi=120)
    table = ["| round | training hours | trials | SR % | CR % | TOR % |", "|---|---:|---:|---:|---:|---:|"]
    table += [f"| {r['label']} | {r['hours']:.2f} | {r['trials']} | {r['SR']:.1f} | {r['CR']:.1f} | {r['TOR']:.1f} |"
              for r in rows]
    args.output.with_suffix(".md").write_text("\n".join(table) + "\n")
    print("\n".join(table))
    print(f"wrote {args.output}")
    return 0


if __name__ == "__main__":
    sys.exit(main())
