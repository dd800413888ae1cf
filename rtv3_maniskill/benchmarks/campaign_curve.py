"""The paper-prior campaign's learning curve: each stage of a ``scripts/train_paper_prior.sh`` output on the
validation block, in training order, paired with the reference prior (``rtv3 learning-curve``).

A stage folder (``OUT/demos_K``, ``OUT/dagger_R``, ``OUT/long``) holds ``cache/summary.json`` (trajectories and
frames trained on), ``run/checkpoints/last/model.safetensors`` (its step), ``planning/`` from ``rtv3 evaluate
planning`` and, where present, ``shared/`` from ``rtv3 benchmark-shared`` with RT-V3 for the noisy and
single-DoF users. ``OUT/reference`` holds the same validation runs of the checkpoint to beat (``planning/``;
``shared/`` with Direct beside RT-V3): each stage is paired with it trial for trial, and the figure draws it and
Direct as lines.
"""

from __future__ import annotations

import csv
import json
import re
from pathlib import Path

from safetensors import safe_open

from rtv3_maniskill.benchmarks import planning_records, shared_statistics
from rtv3_maniskill.benchmarks.shared_results import read_results

STAGE = re.compile(r"^(?:(?:demos|dagger)_\d+|long)$")
USERS = ("noisy", "single_dof")
"""The simulated users of the RT-V3 validation rows."""
FIELDS = ("stage", "trajectories", "frames", "model_step", "trials", "SR", "CR", "TOR", "wins", "losses",
          "reachable_trials", "reachable_SR",
          *(f"{user}_{column}" for user in USERS for column in ("SR", "wins", "losses")))
"""Columns of ``curve.csv``: rates are fractions; ``wins`` / ``losses`` are paired with ``OUT/reference``;
``reachable_*``: the planning trials whose target the arm can reach (empty for runs made before the check)."""


def _model_step(weights: Path) -> int:
    with safe_open(str(weights), framework="pt") as f:
        return int(f.get_tensor("train_step").item()) if "train_step" in f.keys() else 0


def _rows(folder: Path, method: str, name: str | None = None) -> list[dict]:
    """The trials of ``method`` in a ``benchmark-shared`` folder, renamed ``name`` so that two runs can be paired."""
    return [dict(row, method=name or method) for row in read_results(folder / "results.csv") if row["method"] == method]


def _success_rate(rows: list[dict], user: str) -> float | None:
    trials = [r for r in rows if r["user"] == user]
    return sum(r["outcome"] == "success" for r in trials) / len(trials) if trials else None


def _shared(folder: Path, reference: list[dict]) -> dict:
    """RT-V3 SR per user of a finished ``benchmark-shared`` run, and wins / losses against ``reference``: the
    reference's RT-V3 trials, named ``"reference"`` (none: no pairing)."""
    if not (folder / "summary.csv").is_file():
        return {}
    rows = _rows(folder, "rtv3", "stage")
    paired = shared_statistics.paired_with_baseline(rows + reference, "reference") if reference else {}
    out = {}
    for user in USERS:
        if (sr := _success_rate(rows, user)) is not None:
            out[f"{user}_SR"] = sr
            out.update({f"{user}_{k}": paired[(user, "stage")][k] for k in ("wins", "losses")
                        if (user, "stage") in paired})
    return out


def stages(out: Path) -> list[dict]:
    """One row per evaluated stage, in training order: each stage trains on every dataset so far, from the one
    before, so the order is that of (trajectories seen, model step), however chunks and DAgger rounds interleave."""
    reference = out / "reference"
    finished = (reference / "shared" / "summary.csv").is_file()
    reference_rtv3 = _rows(reference / "shared", "rtv3", "reference") if finished else []
    found = []
    for folder in out.iterdir():
        planning = folder / "planning"
        if not STAGE.match(folder.name) or not (planning / "planning_summary.json").is_file():
            continue
        cache = json.loads((folder / "cache" / "summary.json").read_text())
        plan = json.loads((planning / "planning_summary.json").read_text())
        row = dict(stage=folder.name, trajectories=cache["episodes"], frames=cache["frames"],
                   model_step=_model_step(folder / "run" / "checkpoints" / "last" / "model.safetensors"),
                   trials=plan["trials"], SR=plan["SR"], CR=plan["CR"], TOR=plan["TOR"],
                   checkpoint=str(folder / "run" / "checkpoints" / "last"))
        if "arm_reachable" in plan:
            row.update(reachable_trials=plan["arm_reachable"]["trials"], reachable_SR=plan["arm_reachable"]["SR"])
        if all((f / "planning_trials.csv").is_file() for f in (planning, reference / "planning")):
            paired = planning_records.paired_with_baseline(
                planning_records.read_trials(planning / "planning_trials.csv"), reference / "planning")
            row.update(wins=paired["wins"], losses=paired["losses"])
        row.update(_shared(folder / "shared", reference_rtv3))
        found.append(row)
    return sorted(found, key=lambda row: (row["trajectories"], row["model_step"]))


def reference_lines(out: Path) -> dict[str, float]:
    """The reference checkpoint's validation SRs (``planning``, ``planning_reachable`` on the arm-reachable
    targets, ``rtv3_USER``) and Direct's (``direct_USER``),
    as fractions, for the runs ``OUT/reference`` holds."""
    lines = {}
    summary = out / "reference" / "planning" / "planning_summary.json"
    if summary.is_file():
        plan = json.loads(summary.read_text())
        lines["planning"] = plan["SR"]
        if "arm_reachable" in plan:
            lines["planning_reachable"] = plan["arm_reachable"]["SR"]
    shared = out / "reference" / "shared"
    if (shared / "summary.csv").is_file():
        for method in ("rtv3", "direct"):
            rows = _rows(shared, method)
            for user in USERS:
                if (sr := _success_rate(rows, user)) is not None:
                    lines[f"{method}_{user}"] = sr
    return lines


def best(rows: list[dict]) -> dict:
    """The stage with the highest mean SR over planning and the RT-V3 rows, among the stages with every row."""
    measures = ["SR", *(f"{user}_SR" for user in USERS if any(f"{user}_SR" in r for r in rows))]
    complete = [r for r in rows if all(m in r for m in measures)]
    return max(complete, key=lambda r: (sum(r[m] for m in measures) / len(measures), -r["CR"]))


def plot(rows: list[dict], lines: dict[str, float], path: Path) -> None:
    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    fig, ax = plt.subplots(figsize=(6.4, 4.0))
    x = [r["trajectories"] for r in rows]
    curves = [("SR", "planning SR", "o-", "C0"), ("reachable_SR", "planning SR, arm-reachable targets", "o:", "C4"),
              ("CR", "planning CR", "s--", "C3"),
              ("noisy_SR", "RT-V3 SR, noisy user", "^-", "C1"), ("single_dof_SR", "RT-V3 SR, single-DoF", "v-", "C2")]
    for key, label, style, color in curves:
        points = [(xi, 100 * r[key]) for xi, r in zip(x, rows) if key in r]
        if points:
            ax.plot(*zip(*points), style, color=color, label=label)
    reference_style = dict(ls=":", lw=1)
    direct_style = dict(ls="-.", lw=0.8, alpha=0.6)
    for key, color, style, label in (
            ("planning", "C0", reference_style, "reference prior (dotted)"),
            ("planning_reachable", "C4", reference_style, None),
            ("rtv3_noisy", "C1", reference_style, None), ("rtv3_single_dof", "C2", reference_style, None),
            ("direct_noisy", "C1", direct_style, "Direct (dash-dot)"), ("direct_single_dof", "C2", direct_style, None)):
        if key in lines:
            ax.axhline(100 * lines[key], color=color, label=label, **style)
    for r in rows:
        ax.annotate(r["stage"], (r["trajectories"], 100 * r["SR"]), fontsize=7, xytext=(3, 4),
                    textcoords="offset points")
    ax.set_xlabel("trajectories seen (demonstrations + relabels)")
    ax.set_ylabel("validation, % of trials")
    ax.set_title(f"paper prior from scratch (seed block 8; planning {rows[-1]['trials']} trials per stage)",
                 fontsize=9)
    ax.set_ylim(0, 100)
    ax.grid(alpha=0.3)
    ax.legend(fontsize=7, loc="center right")
    fig.tight_layout()
    fig.savefig(path, dpi=130)
    plt.close(fig)


def write_curve(rows: list[dict], out: Path) -> None:
    """``OUT/curve.csv`` (:data:`FIELDS`) and ``OUT/curve.png`` of :func:`stages`' rows."""
    with open(out / "curve.csv", "w", newline="") as f:
        writer = csv.DictWriter(f, fieldnames=FIELDS, extrasaction="ignore")
        writer.writeheader()
        writer.writerows(rows)
    plot(rows, reference_lines(out), out / "curve.png")
