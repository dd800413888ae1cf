"""The report of a shared-control benchmark run: ``summary.csv``, ``summary.md`` and ``success_rates.png``.

:func:`write_summaries` summarises every row of a run's ``results.csv``
(:func:`~rtv3_maniskill.benchmarks.shared_statistics.summarize`): ``summary.csv`` holds the numbers,
``summary.md`` a table with the methods' labels (:data:`~rtv3_maniskill.shared_control.methods.METHODS`),
each method paired with Direct, the paper's Table II success rates beside, the goal counts of
``goals.csv`` above and below the shares of the oracles' gains, each method paired with RT-V3 (when it ran)
and, under the goal rule ``all``, the success rate on the goals of each arm-reach check;
``success_rates.png`` plots SR and CR
per user and method.
"""

from __future__ import annotations

import csv
import json
import math
from collections.abc import Sequence
from pathlib import Path
from typing import Any

import numpy as np

from rtv3_maniskill.benchmarks.shared_results import goal_rows, read_results
from rtv3_maniskill.benchmarks.shared_statistics import (
    SUMMARY_FIELDS,
    paired_with_baseline,
    success_by_goal_check,
    summarize,
)
from rtv3_maniskill.shared_control.methods import CEILINGS, METHODS

PAPER_TABLE2_SR = {
    "noisy": {"rtv3": 84.1, "direct": 62.4, "ho": 42.8, "direct+neoss": 72.0, "ho+neoss": 49.1, "rtv3+neoss": 82.2},
    "laggy": {"rtv3": 86.1, "direct": 80.3, "ho": 9.4, "direct+neoss": 79.7, "ho+neoss": 9.9, "rtv3+neoss": 84.0},
    "mode_switching": {"rtv3": 83.3, "direct": 74.2, "ho": 18.0, "direct+neoss": 81.5, "ho+neoss": 17.6,
                       "rtv3+neoss": 81.1},
    "single_dof": {"rtv3": 69.8, "direct": 50.5, "ho": 23.1, "direct+neoss": 62.0, "ho+neoss": 25.5,
                   "rtv3+neoss": 67.6},
}
"""The paper's Table II success rates (%) per user and method (their simulation; ``+neoss``: the "w. NeoSS" rows)."""


def method_label(name: str) -> str:
    """Table label of a method name: ``"direct+neoss"`` -> ``"Direct w. NeoSS"``."""
    base, _, safety = name.partition("+")
    label = METHODS[base].label if base in METHODS else base
    return f"{label} w. NeoSS" if safety == "neoss" else label


def _percent(fraction: float) -> str:
    """A fraction as a whole percentage (``-0.003`` -> ``"0"``)."""
    return str(int(round(100 * fraction)))


def _fmt(value: float, digits: int = 1) -> str:
    return "-" if value is None or (isinstance(value, float) and math.isnan(value)) else f"{value:.{digits}f}"


def _paired_text(s: dict[str, Any]) -> tuple[str, str]:
    if s.get("wins") is None:
        return "-", "-"
    return f"{s['wins']} / {s['losses']}", f"{s['mcnemar_p']:.3g}"


def _paper_text(s: dict[str, Any]) -> str:
    paper = PAPER_TABLE2_SR.get(s["user"], {}).get(s["method"])
    return "-" if paper is None else f"{paper:.1f}"

def goal_counts(rows: Sequence[dict[str, str]]) -> dict[str, int]:
    """Candidates per goal check (the rows of ``goals.csv``), plus ``candidates`` and ``scenes``."""
    counts = {check: sum(1 for r in rows if r["check"] == check) for check in sorted({r["check"] for r in rows})}
    return dict(counts, candidates=len(rows), scenes=len({r["scene_seed"] for r in rows}))


def summary_markdown(summary: Sequence[dict[str, Any]], goals: dict[str, int] | None = None,
                     goal_rule: str = "reachable",
                     by_check: dict[tuple[str, str], dict[str, tuple[int, float]]] | None = None,
                     versus_rtv3: dict[tuple[str, str], dict[str, Any]] | None = None) -> str:
    """Markdown table: one row per (user, method), paired with Direct, the paper's SR beside; the goal
    counts of ``goals.csv`` under ``goal_rule`` above it; below, the shares of the ceilings' gains,
    with ``versus_rtv3`` (:func:`~rtv3_maniskill.benchmarks.shared_statistics.paired_with_baseline`
    with baseline ``"rtv3"``) each method paired with RT-V3 and, with ``by_check``
    (:func:`~rtv3_maniskill.benchmarks.shared_statistics.success_by_goal_check`), the success rate per
    goal check."""
    lines = []
    if goals and goals.get("candidates"):
        infeasible = ", ".join(f"{v} {k}" for k, v in goals.items() if k not in ("feasible", "candidates", "scenes"))
        if goal_rule == "all":
            lines += [f"Goals (rule `all`, the authors': every floating-hand-feasible grasp): {goals['candidates']} "
                      f"grasp candidates in {goals['scenes']} scenes, of which {goals.get('feasible', 0)} pass the "
                      f"arm-reach check (others: {infeasible or 'none'}).", ""]
        else:
            lines += [f"Goals (rule `reachable`): {goals.get('feasible', 0)} feasible of {goals['candidates']} grasp "
                      f"candidates in {goals['scenes']} scenes (infeasible, never run: {infeasible or 'none'}).", ""]
    lines += [
        "| User | Method | Trials | SR % (↑) | CR % (↓) | TOR % (↓) | reached % | Iter (↓) | W / L vs Direct "
        "| McNemar p | paper SR % |",
        "|---|---|---:|---:|---:|---:|---:|---:|---:|---:|---:|",
    ]
    for s in summary:
        paired, p = _paired_text(s)
        lines.append(
            f"| {s['user']} | {method_label(s['method'])} | {s['trials']} | {_fmt(s['SR'])} | "
            f"{_fmt(s['CR'])} | {_fmt(s['TOR'])} | {_fmt(s['reached'])} | {_fmt(s['mean_iterations'])} | "
            f"{paired} | {p} | {_paper_text(s)} |"
        )
    notes = (
        "\nOne outcome per trial: CR = a robot contact came first (the trial fails), SR = the target "
        "pre-grasp was reached first (pose distance < 0.1), TOR = neither within the step limit; reached: "
        "the pre-grasp was reached with or without a contact; Iter: mean control steps (20 Hz) of the "
        "successful trials. W / L: trials this method succeeded where Direct (behind the same safety "
        "filter) failed / the reverse, on the same goals and user noise; McNemar p: exact two-sided test "
        "of W against L. Paper SR: Table II "
        "(their simulation; their Direct took 81 / 58 / 118 / 129 iterations for noisy / laggy / "
        "mode-switching / single-DoF).\n"
    )
    for ceiling in CEILINGS:
        shares = [s for s in summary if s.get(f"{ceiling}_gain_share") is not None]
        if not shares:
            continue
        name = method_label(ceiling)
        notes += (
            f"\nShare of the {name} gain over Direct, (SR - Direct SR) / ({name} SR - Direct SR), on the goals "
            "all three ran, with a 95 % paired bootstrap interval over those goals:\n\n"
            f"| User | Method | share of the {name} gain % | 95 % interval |\n|---|---|---:|---:|\n"
        )
        for s in shares:
            low, high = s[f"{ceiling}_gain_share_low"], s[f"{ceiling}_gain_share_high"]
            interval = "-" if low is None else f"{_percent(low)} to {_percent(high)}"
            share = _percent(s[f"{ceiling}_gain_share"])
            notes += f"| {s['user']} | {method_label(s['method'])} | {share} | {interval} |\n"
    return ("\n".join(lines) + "\n" + notes + _versus_rtv3_markdown(summary, versus_rtv3 or {})
            + _by_check_markdown(summary, by_check or {}))


def _versus_rtv3_markdown(summary: Sequence[dict[str, Any]], versus: dict[tuple[str, str], dict[str, Any]]) -> str:
    """W / L of each method against RT-V3 behind the same safety filter, in ``summary``'s order; empty
    without RT-V3."""
    rows = [(s, versus[(s["user"], s["method"])]) for s in summary if (s["user"], s["method"]) in versus]
    if not rows:
        return ""
    text = ("\nEach method paired with RT-V3 (behind the same safety filter) on the same goals and user noise: "
            "W / L = trials it succeeded where RT-V3 failed / the reverse:\n\n"
            "| User | Method | paired trials | W / L vs RT-V3 | McNemar p |\n|---|---|---:|---:|---:|\n")
    for s, v in rows:
        paired, p = _paired_text(v)
        text += f"| {s['user']} | {method_label(s['method'])} | {v['paired_trials']} | {paired} | {p} |\n"
    return text


def _by_check_markdown(summary: Sequence[dict[str, Any]],
                       by_check: dict[tuple[str, str], dict[str, tuple[int, float]]]) -> str:
    """The SR per goal check, one row per (user, method) of ``summary``; empty with fewer than two checks."""
    checks = sorted({c for cells in by_check.values() for c in cells}, key=lambda c: (c != "feasible", c))
    if len(checks) < 2:
        return ""
    text = ("\nSR % by the goal's arm-reach check (trials in brackets): `feasible` goals are those the rule "
            "`reachable` keeps; `no_ik_pregrasp`: no collision-free IK solution was found at the exact pre-grasp "
            "(a trial succeeds within pose distance 0.1 of it); `blocked_approach`: the straight 5 cm approach "
            "from it collides:\n\n"
            f"| User | Method | {' | '.join(checks)} |\n|---|---|{'---:|' * len(checks)}\n")
    for s in summary:
        cells = by_check.get((s["user"], s["method"]), {})
        text += (f"| {s['user']} | {method_label(s['method'])} | "
                 + " | ".join(f"{_fmt(cells[c][1])} ({cells[c][0]})" if c in cells else "-" for c in checks) + " |\n")
    return text


def plot_success_rates(summary: Sequence[dict[str, Any]], path: Path) -> None:
    """Grouped bar plots: SR per user (groups) and method (bars) above, CR below."""
    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    users = list(dict.fromkeys(s["user"] for s in summary))
    methods = list(dict.fromkeys(s["method"] for s in summary))
    table = {(s["user"], s["method"]): s for s in summary}
    width = 0.8 / max(len(methods), 1)
    x = np.arange(len(users))
    fig, axes = plt.subplots(2, 1, figsize=(max(7, 1.9 * len(users)), 7), sharex=True)
    for ax, key, title in ((axes[0], "SR", "Success rate (%)"), (axes[1], "CR", "Collision rate (%)")):
        for j, m in enumerate(methods):
            values = [table[(u, m)][key] if (u, m) in table else 0.0 for u in users]
            bars = ax.bar(x + (j - (len(methods) - 1) / 2) * width, values, width, label=method_label(m))
            for bar, v in zip(bars, values):
                ax.annotate(f"{v:.0f}", (bar.get_x() + bar.get_width() / 2, v), ha="center", va="bottom", fontsize=7)
        ax.set_xticks(x, [u.replace("_", "-") for u in users])
        ax.set_ylim(0, 118)
        ax.set_yticks(range(0, 101, 20))
        ax.set_title(title)
        ax.grid(axis="y", alpha=0.3)
    axes[0].legend(loc="upper center", ncol=len(methods), fontsize=8, frameon=False)
    trials = sum(s["trials"] for s in summary)
    fig.suptitle(f"Simulated shared control ({trials} trials)")
    fig.tight_layout()
    fig.savefig(path, dpi=120)
    plt.close(fig)


def write_summaries(output: Path, users: Sequence[str] | None = None,
                    methods: Sequence[str] | None = None) -> list[dict[str, Any]]:
    """``summary.csv``, ``summary.md`` and ``success_rates.png`` from every row of ``output/results.csv``."""
    rows = read_results(output / "results.csv")
    summary = summarize(rows, users, methods)
    with (output / "summary.csv").open("w", newline="") as f:
        writer = csv.DictWriter(f, SUMMARY_FIELDS)
        writer.writeheader()
        for s in summary:
            writer.writerow({k: (f"{v:.3f}" if isinstance(v, float) else v) for k, v in s.items()})
    config_path = output / "config.json"
    goal_rule = json.loads(config_path.read_text()).get("goals", "reachable") if config_path.is_file() else "reachable"
    goals = goal_rows(output / "goals.csv")
    by_check = None
    if goal_rule == "all":
        checks = {(int(g["scene_seed"]), int(g["grasp_index"])): g["check"] for g in goals}
        by_check = success_by_goal_check(rows, checks)
    versus_rtv3 = paired_with_baseline(rows, baseline="rtv3")
    (output / "summary.md").write_text(summary_markdown(summary, goal_counts(goals), goal_rule, by_check, versus_rtv3))
    if summary:
        plot_success_rates(summary, output / "success_rates.png")
    return summary

