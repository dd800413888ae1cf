"""``rtv3 benchmark-shared``: simulated users x assistance methods over clutter scenes (paper Table II).

The options are made from the fields of :class:`~rtv3_maniskill.benchmarks.shared_config.BenchmarkConfig`
(their help and defaults live there), plus ``--preset`` and its scene overrides, the RT-V3 fusion's
single settings, and how to run (``--workers``, ``--executor``).

Resumable: run the same command again after an interruption; finished trials in
``OUTPUT/results.csv`` are skipped. Parallel: run disjoint ``--users`` / ``--methods`` in several
processes, each with its own ``--output``, then ``--merge DIR DIR ... --output NEW``.
"""

from __future__ import annotations

import argparse
import dataclasses
import typing
from collections.abc import Callable, Sequence
from pathlib import Path
from typing import Any

from rtv3_maniskill.benchmarks.shared_config import BenchmarkConfig
from rtv3_maniskill.cli.scene_args import add_executor_arguments, add_scene_arguments, scene_settings
from rtv3_maniskill.presets import get_preset


def _names(text: str) -> list[str]:
    return [part.strip() for part in text.split(",") if part.strip()]


class _Shown:
    """Text made when argparse shows the help, so that building the parser imports no registry (torch)."""

    def __init__(self, make: Callable[[], str]) -> None:
        self.make = make

    def __str__(self) -> str:
        return self.make()


def _parse_type(annotation: Any) -> Callable[[str], Any]:
    """How an option's text becomes a field's value, from the field's type (``X | None`` as ``X``)."""
    if typing.get_origin(annotation) is Sequence:
        return _names
    options = [a for a in typing.get_args(annotation) if a is not type(None)] or [annotation]
    if len(options) == 1 and options[0] in (int, float, str, Path):
        return options[0]
    raise TypeError(f"no command-line form for a field of type {annotation}")


def _default_text(spec: dataclasses.Field) -> Any:
    if spec.default_factory is not dataclasses.MISSING:
        return _Shown(lambda: ",".join(spec.default_factory()))
    if isinstance(spec.default, (tuple, list)):
        return ",".join(spec.default)
    return spec.default


def _option_fields() -> list[dataclasses.Field]:
    return [spec for spec in dataclasses.fields(BenchmarkConfig) if spec.metadata.get("option", True)]


def add_config_arguments(parser: argparse.ArgumentParser) -> None:
    """One option per :class:`BenchmarkConfig` field that has one, with the field's help and default
    (``--preset`` fields default to the preset's value)."""
    hints = typing.get_type_hints(BenchmarkConfig)
    for spec in _option_fields():
        meta = spec.metadata
        text = meta["help"]
        if "known" in meta:
            text += ": %(known)s"
        preset = meta.get("preset", False)
        if not preset and (spec.default is not None or spec.default_factory is not dataclasses.MISSING):
            text += "; default: %(shown_default)s"
        default = None if preset or spec.default is dataclasses.MISSING else spec.default
        action = parser.add_argument(*meta.get("flags", (f"--{spec.name.replace('_', '-')}",)), dest=spec.name,
                                     type=_parse_type(hints[spec.name]), default=default, choices=meta.get("choices"),
                                     help=text)
        known = meta.get("known")
        action.known = _Shown(lambda known=known: ", ".join(known())) if known else None
        action.shown_default = _default_text(spec)


def config_settings(args: argparse.Namespace) -> dict[str, Any]:
    """The :class:`BenchmarkConfig` fields the parsed options set (an option left out keeps the field's default;
    a preset field not given takes the preset's value)."""
    settings: dict[str, Any] = {}
    for spec in _option_fields():
        if (value := getattr(args, spec.name)) is not None:
            settings[spec.name] = value
        elif spec.metadata.get("preset", False):
            settings[spec.name] = getattr(get_preset(args.preset), spec.name)
    return settings


def add_arguments(parser: argparse.ArgumentParser) -> None:
    add_config_arguments(parser)
    add_scene_arguments(parser)
    parser.add_argument("--prior-covariance-scale", type=float, default=None,
                        help="factor on the prior's step-0 covariances before the gate and the fusion (tuned 100, "
                             "paper 1); larger gives the user's command more weight against an overconfident prior")
    parser.add_argument("--goal-belief-margin", type=_margin, default=None, metavar="NATS|off",
                        help="RT-V3 hands its prior only the grasp candidates within NATS of the most likely goal "
                             "under a recursive belief over the candidates (tuned 1); off: every candidate (paper)")
    parser.add_argument("--workers", type=int, default=1,
                        help="run the scenes in this many processes (one core each; the results are the same as "
                             "one process's, trial for trial)")
    add_executor_arguments(parser)
    parser.add_argument("--no-progress", action="store_true", help="no progress bar")
    parser.add_argument("--merge", type=Path, nargs="+", metavar="DIR", default=None,
                        help="run nothing: combine finished runs of disjoint users or methods (e.g. one process per "
                             "method) into --output, which must be new")


def _margin(text: str) -> float | str:
    """``--goal-belief-margin``: a positive number of nats, or ``off``."""
    if text.strip().lower() == "off":
        return "off"
    try:
        value = float(text)
    except ValueError:
        raise argparse.ArgumentTypeError(f"expected a number of nats or 'off', got {text!r}") from None
    if not value > 0:
        raise argparse.ArgumentTypeError(f"the margin must be > 0 nats (or 'off'), got {text!r}")
    return value


def shared_control_overrides(args: argparse.Namespace) -> dict[str, Any]:
    """The ``SharedControlConfig`` fields the command line sets (``off`` -> None), the others left to the preset."""
    return {
        key: (None if value == "off" else value)
        for key in ("prior_covariance_scale", "goal_belief_margin")
        if (value := getattr(args, key, None)) is not None
    }


def run(args: argparse.Namespace) -> int:
    from rtv3_maniskill.benchmarks.shared_config import BenchmarkError
    from rtv3_maniskill.benchmarks.shared_merge import merge_runs
    from rtv3_maniskill.benchmarks.shared_report import summary_markdown
    from rtv3_maniskill.benchmarks.shared_runner import run_benchmark
    from rtv3_maniskill.scene_pool import SceneWorkerError

    if args.merge is not None:
        try:
            summary = merge_runs(args.merge, args.output)
        except BenchmarkError as err:
            raise SystemExit(f"error: {err}") from None
        print(summary_markdown(summary))
        print(f"merged {len(args.merge)} runs: {args.output}/results.csv, summary.csv, summary.md, success_rates.png")
        return 0

    try:
        config = BenchmarkConfig(**config_settings(args), **scene_settings(args),
                                 shared_control=shared_control_overrides(args))
        summary = run_benchmark(config, progress=not args.no_progress, workers=args.workers,
                                executor=args.executor, ray_address=args.ray_address)
    except (BenchmarkError, FileNotFoundError, SceneWorkerError) as err:
        raise SystemExit(f"error: {err}") from None
    print((args.output / "summary.md").read_text())
    print(f"results: {args.output}/results.csv, goals.csv, summary.csv, summary.md, success_rates.png")
    return 0
