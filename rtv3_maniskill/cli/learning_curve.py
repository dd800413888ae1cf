"""``rtv3 learning-curve OUT``: the paper-prior campaign's learning curve (validation against trajectories seen).

Writes ``OUT/curve.csv`` and ``OUT/curve.png`` (:mod:`rtv3_maniskill.benchmarks.campaign_curve`: planning and the
RT-V3 rows of every stage, paired with ``OUT/reference``) and prints one line per stage; with ``--best`` it prints
the checkpoint folder of the stage with the highest mean validation SR over planning and the RT-V3 rows (only
stages with every row that any stage has compete; fewer planning collisions break a tie) instead.
"""

from __future__ import annotations

import argparse
import sys
from pathlib import Path


def add_arguments(parser: argparse.ArgumentParser) -> None:
    parser.add_argument("out", type=Path, help="the campaign's output folder (OUT)")
    parser.add_argument("--best", action="store_true", help="print the best stage's checkpoint folder")


def _pair_text(row: dict, prefix: str = "") -> str:
    return f" ({row[prefix + 'wins']} / {row[prefix + 'losses']})" if prefix + "wins" in row else ""


def run(args: argparse.Namespace) -> int:
    from rtv3_maniskill.benchmarks import campaign_curve

    if not args.out.is_dir():
        print(f"error: no campaign output folder {args.out}", file=sys.stderr)
        return 1
    rows = campaign_curve.stages(args.out)
    if not rows:
        print(f"error: no evaluated stage in {args.out} yet", file=sys.stderr)
        return 1
    if args.best:
        print(campaign_curve.best(rows)["checkpoint"])
        return 0
    campaign_curve.write_curve(rows, args.out)
    for r in rows:
        shared = "".join(f", RT-V3 {user} {100 * r[user + '_SR']:.1f}{_pair_text(r, user + '_')}"
                         for user in campaign_curve.USERS if user + "_SR" in r)
        print(f"{r['stage']:>9}: {r['trajectories']:>6} trajectories, step {r['model_step']:>6}: "
              f"SR {100 * r['SR']:.1f}{_pair_text(r)} CR {100 * r['CR']:.1f} TOR {100 * r['TOR']:.1f} "
              f"({r['trials']} trials){shared}")
    if any("wins" in r for r in rows):
        print("(wins / losses: paired with the reference's trials)")
    return 0
