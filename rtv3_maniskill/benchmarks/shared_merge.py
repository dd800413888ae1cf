"""Merging shared-control benchmark runs made separately (other processes or machines) into one folder.

Runs of disjoint users or methods (e.g. ``--methods direct,ho`` and ``--methods rtv3``) that agree on
every setting they both record combine into one ``results.csv``, ``goals.csv`` and report.
"""

from __future__ import annotations

import csv
import json
import shutil
from collections.abc import Sequence
from pathlib import Path
from typing import Any

from rtv3_maniskill.benchmarks.shared_config import DEFAULT_USERS, BenchmarkError
from rtv3_maniskill.benchmarks.shared_report import write_summaries
from rtv3_maniskill.benchmarks.shared_results import RESULT_FIELDS, RESULT_KEY, result_rows
from rtv3_maniskill.shared_control.methods import METHOD_NAMES


def merge_runs(sources: Sequence[Path], output: Path) -> list[dict[str, Any]]:
    """Combine runs split over processes (e.g. ``--methods direct,ho`` and ``--methods rtv3``) into
    ``output`` (a new folder): ``results.csv``, the summaries and the plot; returns the summary rows.

    The runs must agree on every setting they both record (``config.json``; a run without RT-V3
    records no policy), and no trial may appear in two of them. ``output/config.json`` holds the
    combined settings, so the merged folder can be read and summarised but not resumed by a run
    that lacks one of the merged parts' settings.
    """
    sources = [Path(d) for d in sources]
    output = Path(output)
    if len(sources) < 2:
        raise BenchmarkError("give at least two benchmark output folders to merge")
    if output.resolve() in {d.resolve() for d in sources}:
        raise BenchmarkError(f"the merged output {output} must be a new folder, not one of the runs")
    if (output / "results.csv").exists():
        raise BenchmarkError(f"{output} already holds results.csv; choose a new --output for the merge")
    settings: dict[str, Any] = {}
    origin: dict[str, Path] = {}
    rows: list[dict[str, Any]] = []
    seen: dict[tuple[int, int, str, str], Path] = {}
    for folder in sources:
        config_path, results_path = folder / "config.json", folder / "results.csv"
        for path in (config_path, results_path):
            if not path.is_file():
                raise BenchmarkError(f"{folder} is not a benchmark output folder: {path.name} is missing")
        for key, value in json.loads(config_path.read_text()).items():
            if value is None:
                continue
            if key in settings and settings[key] != value:
                raise BenchmarkError(f"{origin[key]} and {folder} were run with other settings "
                                     f"({key}: {settings[key]!r} vs {value!r}); they cannot be merged")
            settings.setdefault(key, value)
            origin.setdefault(key, folder)
        for row in result_rows(results_path):
            key = tuple(row[k] for k in RESULT_KEY)
            if key in seen:
                raise BenchmarkError(f"trial {key} is in both {seen[key]} and {folder}; merge runs of disjoint "
                                     "users or methods")
            seen[key] = folder
            rows.append(row)
    output.mkdir(parents=True, exist_ok=True)
    (output / "config.json").write_text(json.dumps(settings, indent=2))
    goals = [folder / "goals.csv" for folder in sources if (folder / "goals.csv").is_file()]
    if goals:  # the goal checks of the scenes (the same in every run of these settings)
        shutil.copyfile(goals[0], output / "goals.csv")
    with (output / "results.csv").open("w", newline="") as f:
        writer = csv.DictWriter(f, RESULT_FIELDS)
        writer.writeheader()
        writer.writerows(rows)
    return write_summaries(output, DEFAULT_USERS, METHOD_NAMES)  # the usual order; other names follow
