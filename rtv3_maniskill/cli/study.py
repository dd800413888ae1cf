"""``rtv3 study``: plan a counterbalanced user study, analyze its recorded sessions.

``rtv3 study plan --participants 12 --output study/plan.csv`` writes the schedule (one row per
trial: participant, block, method, scene seed, practice). Run each block with
``rtv3 teleop --method M --scene-seed S ... --participant P --record study/P01_M``.
``rtv3 study analyze study/P01_* ... --output study/analysis`` prints the per participant and method
table and the statistics, and writes trials.csv, summary.csv, stats.csv and boxplots.png.
"""

from __future__ import annotations

import argparse
from pathlib import Path

from rtv3_maniskill.cli import UsageError

STUDY_METHODS = ("direct", "ho", "rtv3")
"""The methods a person can drive with (``rtv3 teleop --method``)."""


def add_arguments(parser: argparse.ArgumentParser) -> None:
    sub = parser.add_subparsers(dest="study_command", metavar="{plan,analyze}", required=True)
    plan = sub.add_parser("plan", help="write a counterbalanced schedule (Latin square) with practice trials")
    plan.add_argument("--participants", type=int, default=12)
    plan.add_argument("--methods", default="direct,ho,rtv3", help="comma-separated methods")
    plan.add_argument("--trials-per-block", type=int, default=5, help="trials per method (its scene group)")
    plan.add_argument("--practice", type=int, default=1, help="practice trials before each block")
    plan.add_argument("--scene-seed", type=int, default=0, help="first study scene seed")
    plan.add_argument("--seed", type=int, default=0, help="seed of the trial shuffling")
    plan.add_argument("--output", type=Path, default=Path("outputs/study/plan.csv"))
    analyze = sub.add_parser("analyze", help="measures, Kruskal-Wallis + Mann-Whitney U (BH), box plots")
    analyze.add_argument("sessions", nargs="+", type=Path, help="session folders written by rtv3 teleop --record")
    analyze.add_argument("--output", type=Path, default=Path("outputs/study/analysis"))


def _fmt(value) -> str:
    return f"{value:.3g}" if isinstance(value, float) else str(value)


def _table(rows: list[dict], columns: list[str]) -> str:
    cells = [[_fmt(r[c]) for c in columns] for r in rows]
    widths = [max(len(c), *(len(row[i]) for row in cells)) for i, c in enumerate(columns)]
    lines = ["  ".join(c.rjust(w) for c, w in zip(columns, widths))]
    lines += ["  ".join(v.rjust(w) for v, w in zip(row, widths)) for row in cells]
    return "\n".join(lines)


def run(args: argparse.Namespace) -> int:
    from rtv3_maniskill.teleop import study

    if args.study_command == "plan":
        methods = [m.strip() for m in args.methods.split(",") if m.strip()]
        unknown = [m for m in methods if m not in STUDY_METHODS]
        if unknown or not methods:
            raise UsageError(f"--methods: unknown method(s) {', '.join(unknown) or '(none given)'}; "
                             f"a study compares {', '.join(STUDY_METHODS)}")
        for name in ("participants", "trials_per_block"):
            if getattr(args, name) < 1:
                raise UsageError(f"--{name.replace('_', '-')} must be >= 1, got {getattr(args, name)}")
        if args.practice < 0:
            raise UsageError(f"--practice must be >= 0, got {args.practice}")
        if args.output.exists() and args.output.is_dir():
            raise UsageError(f"--output {args.output} is a folder; give the schedule's CSV file name")
        rows = study.plan_study(args.participants, methods, args.trials_per_block, args.practice,
                                args.scene_seed, args.seed)
        path = study.write_csv(args.output, rows, study.PLAN_FIELDS)
        print(f"wrote {len(rows)} trials ({args.participants} participants x {len(methods)} methods) to {path}")
        return 0
    for folder in args.sessions:
        if not folder.is_dir():
            raise SystemExit(f"error: {folder} is not a folder (expected a session recorded by rtv3 teleop --record)")
    try:
        trials = study.load_trials(args.sessions)
    except (FileNotFoundError, ValueError, KeyError) as err:
        raise SystemExit(f"error: {str(err).strip() or type(err).__name__}") from None
    if not trials:
        raise SystemExit("error: the sessions hold no trials")
    methods = sorted({t["method"] for t in trials})
    summary = study.summarize(trials)
    tests = study.measure_tests(trials, methods)
    out = args.output
    study.write_csv(out / "trials.csv", trials, list(trials[0]))
    study.write_csv(out / "summary.csv", summary, list(summary[0]))
    study.write_csv(out / "stats.csv", tests, list(tests[0]))
    figure = study.plot_measures(trials, methods, out / "boxplots.png", tests)
    print(f"{len(trials)} trials from {len(args.sessions)} session(s)\n\nper participant and method "
          f"(measures: means over successful trials)")
    print(_table(summary, ["participant", "method", "trials", *study.OUTCOME_COLUMNS, *study.MEASURES]))
    print("\nstatistics over successful trials (Kruskal-Wallis; Mann-Whitney U, Benjamini-Hochberg p_bh)")
    print(_table(tests, ["measure", "test", "a", "b", "statistic", "p", "p_bh"]))
    print(f"\nwrote {out / 'trials.csv'}, summary.csv, stats.csv and {figure}")
    return 0
