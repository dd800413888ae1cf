"""The planning benchmark's records: ``planning_trials.csv`` (one row per trial), ``planning_scenes.csv``
(the valid grasps of each scene built), the SR / CR / TOR summary of trial rows, and the paired
comparison of two runs on the trials both ran (two checkpoints on one validation block).

A resumed run reads both files back (torn or foreign rows are skipped) and must use the same
settings (``planning_config.json``).
"""

from __future__ import annotations

from collections.abc import Iterable
from pathlib import Path
from typing import Any

import numpy as np

from rtv3_maniskill.benchmarks.outcomes import CONTACT_KINDS, OUTCOMES
from rtv3_maniskill.benchmarks.shared_statistics import mcnemar_exact
from rtv3_maniskill.records import RecordStore

NO_START_POSE = "no_start_pose"
"""Outcome of a trial without a collision-free start pose (left out of the rates)."""
TRIAL_FIELDS = (
    "scene_seed", "grasp_index", "outcome", "steps", "start_distance", "final_distance", "min_distance",
    "reached_grasp", "context_grasps", "start_attempts", "wall_time_s", "contact",
)
SCENE_FIELDS = ("scene_seed", "valid_grasps")


def _is_complete_trial(row: dict[str, str]) -> bool:
    """A trial row with every column a finished trial writes (others are torn)."""
    if row["outcome"] not in (*OUTCOMES, NO_START_POSE) or row["wall_time_s"] == "":
        return False
    try:
        int(row["scene_seed"]), int(row["grasp_index"]), int(row["steps"])
    except ValueError:
        return False
    return True


def trials_store(output: Path, settings: dict[str, Any] | None) -> RecordStore:
    """``planning_trials.csv`` (one row per finished trial) guarded by ``planning_config.json``."""
    return RecordStore(output / "planning_trials.csv", TRIAL_FIELDS, ("scene_seed", "grasp_index"), settings,
                       settings_path=output / "planning_config.json", is_complete=_is_complete_trial)


def read_trials(path: Path) -> list[dict[str, str]]:
    """Complete rows of a trials file (a torn or foreign line is skipped)."""
    return RecordStore.read(path, TRIAL_FIELDS, _is_complete_trial)


def summarize(rows: Iterable[dict[str, Any]]) -> dict[str, Any]:
    """SR / CR / TOR over the trials with a start pose (None without any), their counts, mean steps of successes."""
    rows = list(rows)
    counts = {o: sum(1 for r in rows if r["outcome"] == o) for o in OUTCOMES}
    trials = sum(counts.values())
    success_steps = [int(r["steps"]) for r in rows if r["outcome"] == "success"]
    rate = (lambda k: counts[k] / trials) if trials else (lambda k: None)
    return dict(
        trials=trials,
        **{k: v for k, v in counts.items()},
        no_start_pose=sum(1 for r in rows if r["outcome"] == NO_START_POSE),
        SR=rate("success"),
        CR=rate("collision"),
        TOR=rate("timeout"),
        mean_steps_success=float(np.mean(success_steps)) if success_steps else None,
        collisions_with={k: sum(1 for r in rows if r["outcome"] == "collision" and k in r.get("contact", "").split("+"))
                         for k in CONTACT_KINDS},
    )


def paired_with_baseline(rows: Iterable[dict[str, Any]], baseline: Path) -> dict[str, Any]:
    """This run's trials against a finished run in folder ``baseline`` (its ``planning_trials.csv``) on the
    (scene, grasp) trials both ran with a start pose: ``paired_trials``, ``SR`` and ``baseline_SR`` on them,
    ``wins`` (this run succeeded, the baseline did not), ``losses`` (the reverse) and the exact McNemar p.
    The starts and scenes are seeded, so two checkpoints on one seed block meet the same trials.

    Raises:
        FileNotFoundError: ``baseline`` holds no ``planning_trials.csv``.
        ValueError: the runs share no trial (another seed block or scene set).
    """
    path = Path(baseline) / "planning_trials.csv"
    if not path.is_file():
        raise FileNotFoundError(f"--compare-with {baseline}: no planning_trials.csv there (a finished "
                                "`rtv3 evaluate planning` output folder is expected)")
    ran = {(int(r["scene_seed"]), int(r["grasp_index"])): r["outcome"] == "success"
           for r in rows if r["outcome"] != NO_START_POSE}
    other = {(int(r["scene_seed"]), int(r["grasp_index"])): r["outcome"] == "success"
             for r in read_trials(path) if r["outcome"] != NO_START_POSE}
    shared = sorted(ran.keys() & other.keys())
    if not shared:
        raise ValueError(f"--compare-with {baseline}: no trial in common with this run (another --seed or scenes?)")
    wins = sum(ran[k] and not other[k] for k in shared)
    losses = sum(other[k] and not ran[k] for k in shared)
    return dict(baseline=str(baseline), paired_trials=len(shared), SR=sum(ran[k] for k in shared) / len(shared),
                baseline_SR=sum(other[k] for k in shared) / len(shared), wins=wins, losses=losses,
                mcnemar_p=mcnemar_exact(wins, losses))


def scene_index(output: Path, settings: dict[str, Any]) -> RecordStore:
    """``planning_scenes.csv``: the valid grasp indices (space-separated) of every scene built so
    far, so that a resumed run picks the same targets without building finished scenes again."""
    return RecordStore(output / "planning_scenes.csv", SCENE_FIELDS, ("scene_seed",), settings)
