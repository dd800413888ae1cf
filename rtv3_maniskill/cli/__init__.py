"""The ``rtv3`` command: one home for every subcommand (``rtv3 --help`` lists them)."""

from __future__ import annotations

import argparse
import importlib
import sys

from rtv3_maniskill.records import FolderBusy

# name -> (module under rtv3_maniskill.cli, one-line help). Modules load lazily so that
# `rtv3 --help` stays fast.
SUBCOMMANDS: dict[str, tuple[str, str]] = {
    "demo": ("demo", "the main job: shared-control demo in a clutter scene (video + plots)"),
    "scene": ("scene", "render a random clutter scene; save an image with its point cloud and grasp candidates"),
    "generate": ("generate", "expert demonstrations from the motion planner -> LeRobot v3 dataset (resumable)"),
    "dagger": ("dagger", "DAgger round: roll out the prior / users, re-plan from visited states -> LeRobot dataset"),
    "merge": ("merge", "merge LeRobot datasets (demonstrations, DAgger rounds) into one training set, in order"),
    "visualize-episode": ("visualize_episode",
                          "plot one dataset episode: scene, grasps, target and executed trajectory"),
    "evaluate": ("evaluate",
                 "RT-V3 prior benchmarks: trajectory prediction (ADE/FDE), closed-loop planning (SR/CR/TOR), "
                 "Table I's ablation rows"),
    "benchmark-env": ("benchmark_env",
                      "time GraspClutter-v1: steps/s, reset incl. grasp sampling, point-cloud capture"),
    "teleop": ("teleop", "interactive shared-control grasping by keyboard, gamepad or simulated user (recorded)"),
    "study": ("study", "user study: plan a counterbalanced schedule, analyze recorded sessions (stats + box plots)"),
    "compact-cache": ("compact_cache",
                      "train the prior from a compact cache of a dataset (build / train, e.g. on a GPU / finish)"),
    "train-copilot": ("train_copilot",
                      "train the diffusion copilot (LeRobot's DiffusionPolicy) on demonstrations with lerobot-train"),
    "learning-curve": ("learning_curve",
                       "the paper-prior campaign's learning curve: validation planning against trajectories seen"),
    "benchmark-shared": ("benchmark_shared",
                         "simulated users x Direct / HO / RT-V3 / oracles: SR, CR, iterations, paired (resumable)"),
}


class UsageError(Exception):
    """A bad option value found after parsing: printed as one ``error:`` line, exit status 2 (as argparse's)."""


def build_parser() -> argparse.ArgumentParser:
    parser = argparse.ArgumentParser(prog="rtv3", description="RT-V3 shared control on ManiSkill3 and LeRobot.")
    sub = parser.add_subparsers(dest="command", metavar="COMMAND")
    for name, (module, help_text) in SUBCOMMANDS.items():
        sp = sub.add_parser(name, help=help_text, description=help_text)
        sp.set_defaults(_module=module)
        importlib.import_module(f"rtv3_maniskill.cli.{module}").add_arguments(sp)
    return parser


def main(argv: list[str] | None = None) -> int:
    parser = build_parser()
    args = parser.parse_args(argv)
    if args.command is None:
        parser.print_help()
        return 0
    module = importlib.import_module(f"rtv3_maniskill.cli.{args._module}")
    try:
        return int(module.run(args) or 0)
    except UsageError as err:
        print(f"rtv3 {args.command}: error: {err}", file=sys.stderr)
        raise SystemExit(2) from None
    except FolderBusy as err:  # another run writes the output folder
        print(f"rtv3 {args.command}: error: {err}", file=sys.stderr)
        raise SystemExit(1) from None
    except KeyboardInterrupt:  # Ctrl-C: what each command has written so far is kept (its records resume)
        print(f"\nrtv3 {args.command}: interrupted", file=sys.stderr)
        return 130


if __name__ == "__main__":
    sys.exit(main())
