"""The user study: a counterbalanced plan, per-trial measures from recorded sessions, statistics, box plots.

* :func:`plan_study`: per participant, every method once on its own scene group, the method order
  and the method-to-group pairing from a Latin square (row = participant), the trials inside a
  block shuffled; practice trials on their own scenes before each block.
* :func:`load_trials`: every trial of recorded session folders (``rtv3 teleop --record``) with its
  measures (:func:`trial_measures`): completion time, number of inputs, translation and rotation
  path length of the TCP, and the same paths adjusted (without the steps the robot moved on its
  own: RT-V3's autonomous mode and the scripted grasp motions).
* :func:`compare_methods`: Kruskal-Wallis over the methods, then pairwise two-sided Mann-Whitney U
  with Benjamini-Hochberg adjusted p-values (``scipy.stats.false_discovery_control``).
* :func:`plot_measures`: box plots, one panel per measure, methods side by side (paper Fig. 6).
"""

from __future__ import annotations

import csv
import itertools
from collections.abc import Sequence
from pathlib import Path
from typing import Any

import numpy as np

from rtv3_maniskill import features
from rtv3_maniskill.teleop.recorder import ASSIST_MODES, SESSIONS_CSV, USER_TWIST

PLAN_FIELDS = ("participant", "order", "block", "method", "scene_group", "trial", "scene_seed", "practice")
MEASURES = ("completion_time", "inputs", "translation_path", "rotation_path", "translation_path_adjusted",
            "rotation_path_adjusted")
UNITS = {"completion_time": "s", "inputs": "count", "translation_path": "m", "rotation_path": "rad",
         "translation_path_adjusted": "m", "rotation_path_adjusted": "rad"}
OUTCOME_COLUMNS = ("success", "timeout", "collision", "unmatched")
PRACTICE_SEED_OFFSET = 900000
"""Practice scenes are drawn from seeds ``scene_seed + PRACTICE_SEED_OFFSET + ...`` (never a study scene)."""
_ROBOT_MOVES = (ASSIST_MODES.index("autonomous"), ASSIST_MODES.index("scripted"))


# --------------------------------------------------------------------------- plan


def latin_square(n: int) -> list[list[int]]:
    """``n x n`` balanced Latin square (Williams design; each item follows every other once when ``n`` is
    even): row ``r`` is the presentation order for participant ``r mod n``."""
    if n < 1:
        raise ValueError(f"a Latin square needs n >= 1, got {n}")
    first, low, high = [0], 1, n - 1
    while len(first) < n:
        first.append(low)
        low += 1
        if len(first) < n:
            first.append(high)
            high -= 1
    return [[(x + r) % n for x in first] for r in range(n)]


def plan_study(participants: int, methods: Sequence[str], trials_per_block: int, practice_trials: int = 1,
               scene_seed: int = 0, seed: int = 0) -> list[dict[str, Any]]:
    """Rows of :data:`PLAN_FIELDS`, in the order they are run. Scene group ``g`` holds the scenes
    ``scene_seed + 1000 g + t`` (``t < trials_per_block``)."""
    if participants < 1 or trials_per_block < 1 or practice_trials < 0 or not methods:
        raise ValueError("need >= 1 participant, >= 1 method, >= 1 trial per block and >= 0 practice trials")
    k = len(methods)
    square = latin_square(k)
    rng = np.random.default_rng(seed)
    rows, order = [], 0
    for p in range(participants):
        method_order = square[p % k]
        for block, m in enumerate(method_order):
            group = square[(p + 1) % k][m] if k > 1 else 0  # pairing method -> scene group, rotated per participant
            for t in range(practice_trials):
                seed_t = scene_seed + PRACTICE_SEED_OFFSET + 1000 * p + 10 * block + t
                rows.append(dict(participant=f"P{p + 1:02d}", order=order, block=block, method=methods[m],
                                 scene_group=-1, trial=t, scene_seed=seed_t, practice=1))
                order += 1
            for t in rng.permutation(trials_per_block):
                rows.append(dict(participant=f"P{p + 1:02d}", order=order, block=block, method=methods[m],
                                 scene_group=group, trial=int(t), scene_seed=scene_seed + 1000 * group + int(t),
                                 practice=0))
                order += 1
    return rows


def write_csv(path: str | Path, rows: list[dict[str, Any]], fields: Sequence[str]) -> Path:
    """Write ``rows`` with the columns ``fields``; returns the path."""
    path = Path(path)
    path.parent.mkdir(parents=True, exist_ok=True)
    with open(path, "w", newline="") as f:
        writer = csv.DictWriter(f, fields)
        writer.writeheader()
        writer.writerows(rows)
    return path


# --------------------------------------------------------------------------- measures


def _rotation_angles(quats: np.ndarray) -> np.ndarray:
    """``(S, 4)`` wxyz -> ``(S - 1,)`` rotation angle (rad) between consecutive orientations."""
    q = quats / np.linalg.norm(quats, axis=1, keepdims=True)
    dots = np.clip(np.abs(np.sum(q[1:] * q[:-1], axis=1)), 0.0, 1.0)
    return 2.0 * np.arccos(dots)


def trial_measures(state: np.ndarray, user_twist: np.ndarray, assist_mode: np.ndarray, buttons: np.ndarray) -> dict:
    """Measures of one trial from its frames: ``state (S, 27)`` (before each step), ``user_twist (S, 6)``,
    ``assist_mode (S,)`` codes, ``buttons (S, 4)``. Path step ``t`` is the motion from frame ``t`` to
    ``t + 1``; adjusted paths skip the steps in autonomous or scripted mode. Inputs: the onsets of a
    non-zero command plus the button presses."""
    moving = np.abs(user_twist).sum(1) > 0
    onsets = int(moving[0]) + int(np.sum(moving[1:] & ~moving[:-1])) if len(moving) else 0
    translation = np.linalg.norm(np.diff(state[:, features.EE_POS], axis=0), axis=1)
    rotation = _rotation_angles(state[:, features.EE_QUAT])
    user_steps = ~np.isin(assist_mode[:-1], _ROBOT_MOVES)
    return dict(
        completion_time=len(state) * features.DT,
        inputs=onsets + int(np.sum(buttons)),
        translation_path=float(translation.sum()),
        rotation_path=float(rotation.sum()),
        translation_path_adjusted=float(translation[user_steps].sum()),
        rotation_path_adjusted=float(rotation[user_steps].sum()),
    )


def _frames(folder: Path) -> Any:
    import pandas as pd

    files = sorted((folder / "data").glob("*/*.parquet"))
    if not files:
        raise FileNotFoundError(f"{folder} holds no LeRobot data (data/*/*.parquet): not a recorded session")
    columns = ["episode_index", "frame_index", features.STATE, USER_TWIST, "assist_mode", "button_events"]
    try:
        frames = [pd.read_parquet(f, columns=columns) for f in files]
    except (KeyError, ValueError, OSError) as err:
        raise ValueError(f"{folder} is not a recorded session: its data lacks the session columns or cannot be read "
                         f"({type(err).__name__}: {str(err).splitlines()[0] if str(err) else ''})") from None
    return pd.concat(frames).sort_values(["episode_index", "frame_index"])


def load_trials(folders: Sequence[str | Path]) -> list[dict[str, Any]]:
    """One row per recorded trial of the session ``folders``: its ``sessions.csv`` row plus :data:`MEASURES`."""
    rows = []
    for folder in map(Path, folders):
        table = folder / SESSIONS_CSV
        if not table.exists():
            raise FileNotFoundError(f"{table} is missing: {folder} is not a session recorded by `rtv3 teleop --record`")
        with open(table, newline="") as f:
            sessions = list(csv.DictReader(f))
        frames = _frames(folder)
        for row in sessions:
            ep = frames[frames["episode_index"] == int(row["episode_index"])]
            if ep.empty:
                raise ValueError(f"{folder}: episode {row['episode_index']} of sessions.csv is not in the dataset")
            measures = trial_measures(
                np.stack(ep[features.STATE].to_numpy()), np.stack(ep[USER_TWIST].to_numpy()),
                np.concatenate([np.atleast_1d(x) for x in ep["assist_mode"].to_numpy()]),
                np.stack(ep["button_events"].to_numpy()))
            rows.append(dict(row, session=str(folder), **measures))
    return rows


# --------------------------------------------------------------------------- statistics


def compare_methods(values: dict[str, Sequence[float]]) -> dict[str, Any]:
    """Kruskal-Wallis over the groups of ``values`` (method -> samples), then pairwise two-sided
    Mann-Whitney U, p-values Benjamini-Hochberg adjusted over the pairs.

    Returns ``{"kruskal": (H, p), "pairs": [(a, b, U, p, p_bh), ...]}``; groups with fewer than 2
    samples are left out (NaN statistics when fewer than 2 groups remain).
    """
    from scipy import stats

    groups = {k: np.asarray(v, dtype=float) for k, v in values.items() if len(v) >= 2}
    out: dict[str, Any] = {"kruskal": (float("nan"), float("nan")), "pairs": []}
    if len(groups) < 2:
        return out
    samples = list(groups.values())
    if np.ptp(np.concatenate(samples)) > 0:
        h = stats.kruskal(*samples)
        out["kruskal"] = (float(h.statistic), float(h.pvalue))
    pairs = list(itertools.combinations(groups, 2))
    tests = [stats.mannwhitneyu(groups[a], groups[b], alternative="two-sided") for a, b in pairs]
    p = np.array([t.pvalue for t in tests], dtype=float)
    p_bh = stats.false_discovery_control(np.nan_to_num(p, nan=1.0)) if len(p) else p
    out["pairs"] = [(a, b, float(t.statistic), float(pv), float(pa))
                    for (a, b), t, pv, pa in zip(pairs, tests, p, p_bh)]
    return out


def summarize(trials: list[dict[str, Any]]) -> list[dict[str, Any]]:
    """Per participant and method: trial count, outcome counts and the mean of every measure over
    the successful trials."""
    rows = []
    keys = sorted({(t["participant"], t["method"]) for t in trials})
    for participant, method in keys:
        mine = [t for t in trials if t["participant"] == participant and t["method"] == method]
        ok = [t for t in mine if t["outcome"] == "success"]
        row: dict[str, Any] = dict(participant=participant, method=method, trials=len(mine))
        row.update({o: sum(t["outcome"] == o for t in mine) for o in OUTCOME_COLUMNS})
        row.update({m: float(np.mean([t[m] for t in ok])) if ok else float("nan") for m in MEASURES})
        rows.append(row)
    return rows


def measure_tests(trials: list[dict[str, Any]], methods: Sequence[str]) -> list[dict[str, Any]]:
    """:func:`compare_methods` for every measure over the successful trials; rows for a CSV."""
    ok = [t for t in trials if t["outcome"] == "success"]
    rows = []
    for m in MEASURES:
        result = compare_methods({k: [t[m] for t in ok if t["method"] == k] for k in methods})
        h, p = result["kruskal"]
        rows.append(dict(measure=m, test="kruskal", a="all", b="", statistic=h, p=p, p_bh=p))
        rows += [dict(measure=m, test="mannwhitneyu", a=a, b=b, statistic=u, p=pv, p_bh=pa)
                 for a, b, u, pv, pa in result["pairs"]]
    return rows


def plot_measures(trials: list[dict[str, Any]], methods: Sequence[str], path: str | Path,
                  tests: list[dict[str, Any]] | None = None) -> Path:
    """Box plots of :data:`MEASURES` over the successful trials, one panel each, ``methods`` side by
    side; pairs with a BH-adjusted p < 0.05 are marked with a bracket and stars."""
    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    ok = [t for t in trials if t["outcome"] == "success"]
    fig, axes = plt.subplots(1, len(MEASURES), figsize=(3.0 * len(MEASURES), 3.6))
    for ax, m in zip(axes, MEASURES):
        data = [[t[m] for t in ok if t["method"] == k] for k in methods]
        ax.boxplot([d if d else [np.nan] for d in data], tick_labels=list(methods), showfliers=True)
        ax.set_title(m.replace("_", " "), fontsize=9)
        ax.set_ylabel(UNITS[m], fontsize=8)
        top = max((max(d) for d in data if d), default=1.0)
        step = 0.08 * (abs(top) + 1e-9)
        level = top
        for row in tests or []:
            if row["measure"] == m and row["test"] == "mannwhitneyu" and row["p_bh"] < 0.05:
                i, j = list(methods).index(row["a"]) + 1, list(methods).index(row["b"]) + 1
                level += step
                stars = "***" if row["p_bh"] < 0.001 else "**" if row["p_bh"] < 0.01 else "*"
                ax.plot([i, i, j, j], [level - step / 3, level, level, level - step / 3], color="k", lw=0.8)
                ax.text((i + j) / 2, level, stars, ha="center", va="bottom", fontsize=8)
    fig.tight_layout()
    path = Path(path)
    path.parent.mkdir(parents=True, exist_ok=True)
    fig.savefig(path, dpi=110)
    plt.close(fig)
    return path


__all__ = ["MEASURES", "OUTCOME_COLUMNS", "PLAN_FIELDS", "compare_methods", "latin_square", "load_trials",
           "measure_tests", "plan_study", "plot_measures", "summarize", "trial_measures", "write_csv"]
