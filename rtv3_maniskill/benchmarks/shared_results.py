"""The files of a shared-control benchmark run: ``results.csv`` (one row per trial) and ``goals.csv``.

Both are :class:`~rtv3_maniskill.records.RecordStore` files, appended and flushed as trials and goal
checks finish, so a rerun skips what is done. ``results.csv`` is guarded by the run's ``config.json``
(:meth:`~rtv3_maniskill.benchmarks.shared_config.BenchmarkConfig.fingerprint`), ``goals.csv`` by the
settings that decide the scenes and their goal checks. A folder whose files have other columns, or
that was made with other settings, is refused (:class:`BenchmarkError`).
"""

from __future__ import annotations

from pathlib import Path
from typing import Any

from rtv3_maniskill.benchmarks.shared_config import BenchmarkError
from rtv3_maniskill.records import RecordStore

RESULT_FIELDS = (
    "scene_seed", "grasp_index", "user", "method", "outcome", "success", "collision", "steps",
    "final_distance", "autonomous_steps", "user_only_steps", "user_seed", "wall_time_s", "qp_infeasible_steps",
    "contact", "twist_deviation",
)
"""Columns of ``results.csv``: the trial (scene, target, user, method), its outcome (``success``,
``collision`` or ``timeout``), ``success`` (the pre-grasp was reached, contact or not), ``collision``,
control steps, the final pose distance, steps per assistance mode, the user's noise seed, seconds,
steps a safety filter's QP had no solution, what the first contact touched, and ``twist_deviation``: the mean
over the trial's steps of ``||robot twist - user twist||`` (the 6-D TCP body twists, m/s and rad/s taken as
numbers; for Direct only its speed limit), how far the method moved the user's command."""
RESULT_KEY = ("scene_seed", "grasp_index", "user", "method")
GOAL_FIELDS = ("scene_seed", "grasp_index", "check")
"""Columns of ``goals.csv``: every grasp candidate of a scene and its goal check (``benchmarks.goals.GOAL_CHECKS``)."""
GOAL_SETTINGS = ("seed", "scene_type", "protocol", "object_source")
"""The settings of ``config.json`` that decide the scenes and their goal checks (``goals.settings.json``)."""


def _is_complete_result(row: dict[str, str]) -> bool:
    return row["outcome"] in ("success", "collision", "timeout") and row["wall_time_s"] != ""


def _store(path: Path, fields: tuple[str, ...], key: tuple[str, ...], settings: dict[str, Any] | None,
           **kwargs: Any) -> RecordStore:
    try:
        return RecordStore(path, fields, key, settings, **kwargs)
    except ValueError as err:  # other columns, or SettingsMismatch: other settings
        raise BenchmarkError(str(err)) from None


def results_store(output: Path, settings: dict[str, Any] | None) -> RecordStore:
    """``output/results.csv``, guarded by ``output/config.json`` (``settings``: the run's fingerprint)."""
    return _store(output / "results.csv", RESULT_FIELDS, RESULT_KEY, settings, settings_path=output / "config.json",
                  is_complete=_is_complete_result)


def goals_store(output: Path, settings: dict[str, Any]) -> RecordStore:
    """``output/goals.csv``, guarded by the fingerprint's :data:`GOAL_SETTINGS`."""
    return _store(output / "goals.csv", GOAL_FIELDS, ("scene_seed", "grasp_index"),
                  {k: settings[k] for k in GOAL_SETTINGS})


def result_rows(path: Path) -> list[dict[str, str]]:
    """The complete rows of a ``results.csv`` (strings; a torn last row is left out)."""
    try:
        return RecordStore.read(path, RESULT_FIELDS, _is_complete_result, key=RESULT_KEY)
    except ValueError as err:
        raise BenchmarkError(str(err)) from None


def read_results(path: Path) -> list[dict[str, Any]]:
    """Rows of ``results.csv`` with the numbers the summaries use parsed (a torn last row is left out)."""
    return [{
        **row,
        "scene_seed": int(row["scene_seed"]), "grasp_index": int(row["grasp_index"]),
        "success": int(row["success"]), "collision": int(row["collision"]), "steps": int(row["steps"]),
    } for row in result_rows(path)]


def goal_rows(path: Path) -> list[dict[str, str]]:
    """The rows of a ``goals.csv`` (none when the file is missing)."""
    if not Path(path).is_file():
        return []
    try:
        return RecordStore.read(path, GOAL_FIELDS, key=("scene_seed", "grasp_index"))
    except ValueError as err:
        raise BenchmarkError(str(err)) from None
