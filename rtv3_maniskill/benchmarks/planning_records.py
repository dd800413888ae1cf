"""The planning benchmark's records: ``planning_trials.csv`` (one row per trial), ``planning_scenes.csv``
(the valid grasps of each scene built), ``planning_goals.csv`` (the arm-reach check of each target), the
SR / CR / TOR summary of trial rows, and the paired comparison of two runs on the trials both ran (two
checkpoints on one validation block).

A resumed run reads the files back (torn or foreign rows are skipped) and must use the same
settings (``planning_config.json``).
"""

from __future__ import annotations

import json
from collections.abc import Iterable
from pathlib import Path
from typing import Any

import numpy as np

from rtv3_maniskill.benchmarks.outcomes import CONTACT_KINDS, OUTCOMES
from rtv3_maniskill.benchmarks.shared_results import GOAL_FIELDS
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
    return RecordStore.read(path, TRIAL_FIELDS, _is_complete_trial, key=("scene_seed", "grasp_index"))


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


_POLICY_SETTINGS = ("policy_path", "planner")
"""Settings two paired runs may differ in: what drives the arm. Every other setting decides the trials."""


def _setting(settings: dict[str, Any], key: str) -> str:
    """A recorded setting for a message; a key a run leaves out holds its default."""
    return repr(settings[key]) if key in settings else "the default"


def check_baseline(baseline: Path, settings: dict[str, Any]) -> None:
    """Refuse a run to pair with (``rtv3 evaluate planning --compare-with``) that is not a finished planning
    run, or whose trials other settings decided: only :data:`_POLICY_SETTINGS` may differ from ``settings``
    (this run's ``planning_config.json``).

    Raises:
        FileNotFoundError: ``baseline`` holds no ``planning_trials.csv`` or ``planning_config.json``.
        ValueError: the baseline was run with other scene or trial settings (the message names them).
    """
    baseline = Path(baseline)
    if not (baseline / "planning_trials.csv").is_file() or not (baseline / "planning_config.json").is_file():
        raise FileNotFoundError(f"--compare-with {baseline}: no planning_trials.csv and planning_config.json there "
                                "(a finished `rtv3 evaluate planning` output folder is expected)")
    other = json.loads((baseline / "planning_config.json").read_text())
    keys = (settings.keys() | other.keys()) - set(_POLICY_SETTINGS)
    differ = sorted(k for k in keys if settings.get(k) != other.get(k))
    if differ:
        raise ValueError(f"--compare-with {baseline}: its trials were run with other settings ("
                         + ", ".join(f"{k}: {_setting(other, k)} there, {_setting(settings, k)} here" for k in differ)
                         + "); pair runs that differ only in what drives the arm")


def _successes(rows: Iterable[dict[str, Any]]) -> dict[tuple[int, int], bool]:
    """``{(scene_seed, grasp_index): succeeded}`` of the trials that had a start pose."""
    return {(int(r["scene_seed"]), int(r["grasp_index"])): r["outcome"] == "success"
            for r in rows if r["outcome"] != NO_START_POSE}


def paired_with_baseline(rows: Iterable[dict[str, Any]], baseline: Path) -> dict[str, Any]:
    """This run's trials (``rows``) against the finished run in folder ``baseline`` (accepted by
    :func:`check_baseline`) on the (scene, grasp) trials both ran with a start pose: ``paired_trials``,
    ``SR`` and ``baseline_SR`` on them, ``wins`` (this run succeeded, the baseline did not), ``losses``
    (the reverse) and the exact McNemar p. Scenes and starts are seeded, so two checkpoints (or a
    checkpoint and the NeoSS planner) run with the same other settings meet the same trials.

    Raises:
        ValueError: the runs share no trial.
    """
    ran, other = _successes(rows), _successes(read_trials(Path(baseline) / "planning_trials.csv"))
    shared = sorted(ran.keys() & other.keys())
    if not shared:
        raise ValueError(f"--compare-with {baseline}: no trial in common with this run (other scenes?)")
    wins = sum(ran[k] and not other[k] for k in shared)
    losses = sum(other[k] and not ran[k] for k in shared)
    return dict(baseline=str(baseline), paired_trials=len(shared), SR=sum(ran[k] for k in shared) / len(shared),
                baseline_SR=sum(other[k] for k in shared) / len(shared), wins=wins, losses=losses,
                mcnemar_p=mcnemar_exact(wins, losses))


def goals_store(output: Path, settings: dict[str, Any]) -> RecordStore:
    """``planning_goals.csv``: the arm-reach check (``benchmarks.goals.check_goal``) of every target so far, in the
    columns of ``benchmark-shared``'s ``goals.csv`` (``shared_results.GOAL_FIELDS``)."""
    return RecordStore(output / "planning_goals.csv", GOAL_FIELDS, ("scene_seed", "grasp_index"), settings)


def by_goal_check(rows: Iterable[dict[str, Any]], goals: dict[tuple[int, int], str]) -> dict[str, Any]:
    """The targets per goal check (``goal_checks``) and :func:`summarize` of the trials whose target passes
    the arm-reach check (``arm_reachable``: the arm can stand collision-free at its pre-grasp and move straight
    in), the set the authors' planning targets came from. ``goals``: ``{(scene_seed, grasp_index): check}``."""
    rows = list(rows)
    checks = [goals[(int(r["scene_seed"]), int(r["grasp_index"]))] for r in rows]
    return dict(goal_checks={c: checks.count(c) for c in sorted(set(checks))},
                arm_reachable=summarize(r for r, c in zip(rows, checks) if c == "feasible"))


def scene_index(output: Path, settings: dict[str, Any]) -> RecordStore:
    """``planning_scenes.csv``: the valid grasp indices (space-separated) of every scene built so
    far, so that a resumed run picks the same targets without building finished scenes again."""
    return RecordStore(output / "planning_scenes.csv", SCENE_FIELDS, ("scene_seed",), settings)
