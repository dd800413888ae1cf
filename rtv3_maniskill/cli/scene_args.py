"""The options the commands share: ``--preset`` and the settings it fills in, RT-V3's ``--fusion``,
the scene pool's executor, and ``--push-to-hub``.

``--preset paper`` (the authors' protocol) or ``--preset easy`` sets the layout, the object set,
the twist execution and the contact rule (and, for the benchmark, the goal rule); an explicit
``--scene-type``, ``--objects``, ``--execution`` or ``--self-contacts`` overrides the preset's value,
and ``--fusion`` the preset's RT-V3 fusion (``tuned_ycb`` for paper, ``tuned`` for easy).
"""

from __future__ import annotations

import argparse
from pathlib import Path
from typing import Any

from rtv3_maniskill.datagen.hub import HubPushError, check_repo_id, push_dataset
from rtv3_maniskill.presets import PRESETS, get_preset
from rtv3_maniskill.robot.execution import EXECUTIONS
from rtv3_maniskill.robot.planner_config import DEFAULT_CLEARANCE

SCENE_TYPE_CHOICES = ("pile", "packed", "packed_ycb", "mixed")


def add_scene_arguments(parser: argparse.ArgumentParser, default_preset: str = "easy", execution: bool = True) -> None:
    """``--preset`` and its overrides (defaults None: taken from the preset); ``execution=False`` leaves
    out the options of commands that do not execute twists (planner demonstrations)."""
    parser.add_argument("--preset", choices=tuple(PRESETS), default=default_preset,
                        help="scene preset: paper (the authors' protocol: YCB-sized objects packed upright, every "
                             "floating-hand-feasible grasp a goal, their twist execution, self contacts not counted) "
                             f"or easy (procedural piles and packs, arm-reach goals); default {default_preset}")
    parser.add_argument("--scene-type", choices=SCENE_TYPE_CHOICES, default=None,
                        help="layout (default: the preset's): pile, packed (VGN), packed_ycb (the authors' YCB "
                             "validation scenes) or mixed (pile or packed)")
    parser.add_argument("--objects", default=None,
                        help="object source (default: the preset's): 'ycb' (YCB objects at nominal sizes, built "
                             "in), 'procedural', 'random_urdfs', 'procedural+random_urdfs' or a folder of meshes "
                             "(e.g. ManiSkill's YCB models folder once downloaded)")
    if not execution:
        return
    parser.add_argument("--execution", choices=tuple(EXECUTIONS), default=None,
                        help="twist execution (default: the preset's): capped (as commanded, <= 0.3 m/s) or "
                             "tracked (the authors': 0.75 of the command per step, no speed cap)")
    parser.add_argument("--self-contacts", choices=("count", "ignore"), default=None,
                        help="whether a robot self contact is a collision (default: the preset's; paper: ignore)")


def add_fusion_argument(parser: argparse.ArgumentParser) -> None:
    """``--fusion``: RT-V3's fusion preset (default None: the scene preset's, :func:`fusion_name`)."""
    parser.add_argument("--fusion", default=None,
                        help="RT-V3 fusion preset (SharedControlConfig.preset): tuned (chosen on the easy preset's "
                             "scenes), tuned_ycb (on the paper preset's) or paper (the paper's reading); default: the "
                             "scene preset's")


def fusion_name(args: argparse.Namespace) -> str:
    """RT-V3's fusion preset of the parsed options: ``--fusion``, else the scene preset's. The name is
    checked where the fusion is built (``SharedControlConfig.preset``: a clear error naming the known ones)."""
    return args.fusion or get_preset(args.preset).fusion


def policy_path(args: argparse.Namespace) -> Path:
    """RT-V3's checkpoint of the parsed options: ``--policy.path``, else the scene preset's (checked where it
    is loaded: ``resolve_checkpoint``, a clear error naming the missing file)."""
    return args.policy_path or get_preset(args.preset).policy_path


def add_clearance_argument(parser: argparse.ArgumentParser) -> None:
    """``--clearance``: how far (m) the expert's free-space motion keeps from the objects."""
    parser.add_argument("--clearance", type=float, default=DEFAULT_CLEARANCE,
                        help=f"m the planner's free-space motion keeps from the objects (default {DEFAULT_CLEARANCE}; "
                             "the paper preset's prior is trained on 0.03, docs/RESULTS.md); the table keeps 5 mm and "
                             "the straight 5 cm approach its own margins")


def add_executor_arguments(parser: argparse.ArgumentParser) -> None:
    """``--executor`` and ``--ray-address``: where the scene pool's workers run (``--workers`` of them)."""
    parser.add_argument("--executor", choices=("local", "ray"), default="local",
                        help="local processes (default) or Ray tasks (pip install -e '.[ray]'); a run made with "
                             "one resumes with the other")
    parser.add_argument("--ray-address", default=None,
                        help="with --executor ray: the cluster to join (e.g. 'auto' or HOST:6379); default: a "
                             "local Ray instance with --workers CPUs")


def add_push_argument(parser: argparse.ArgumentParser, what: str = "the dataset") -> None:
    """``--push-to-hub REPO_ID``."""
    parser.add_argument("--push-to-hub", metavar="REPO_ID", default=None,
                        help=f"after the run, push {what} to this Hugging Face Hub dataset repo (OWNER/NAME), with "
                             "a dataset card naming the task, the features and this command")


def check_push_argument(args: argparse.Namespace) -> None:
    """Refuse a malformed ``--push-to-hub`` before any work."""
    if getattr(args, "push_to_hub", None) is not None:
        try:
            check_repo_id(args.push_to_hub)
        except ValueError as err:
            raise SystemExit(f"error: {err}") from None


def push_if_asked(args: argparse.Namespace, root, kind: str) -> None:
    """Push the dataset in ``root`` when ``--push-to-hub`` was given (``kind``: what its episodes are)."""
    if getattr(args, "push_to_hub", None) is None:
        return
    try:
        push_dataset(root, args.push_to_hub, kind)
    except HubPushError as err:
        raise SystemExit(f"error: {err}") from None
    print(f"pushed {root} to the Hub dataset repo {args.push_to_hub}")


def scene_settings(args: argparse.Namespace) -> dict[str, Any]:
    """``GraspClutter-v1`` keyword arguments of the parsed options: the preset, then the overrides
    (only the options the command has)."""
    settings = get_preset(args.preset).env_kwargs()
    for key, option in (("scene_type", "scene_type"), ("object_source", "objects"), ("execution", "execution")):
        if getattr(args, option, None) is not None:
            settings[key] = getattr(args, option)
    if getattr(args, "self_contacts", None) is not None:
        settings["self_contacts"] = args.self_contacts == "count"
    if not hasattr(args, "execution"):
        settings.pop("execution")
        settings.pop("self_contacts")
    return settings


def resolve_scene_arguments(args: argparse.Namespace) -> argparse.Namespace:
    """Fill the preset's values into ``args.scene_type`` and ``args.objects`` (and ``args.execution``,
    ``args.self_contacts`` as a bool, where the command has them), in place; returns ``args``."""
    settings = scene_settings(args)
    args.scene_type, args.objects = settings["scene_type"], settings["object_source"]
    if "execution" in settings:
        args.execution, args.self_contacts = settings["execution"], settings["self_contacts"]
    return args
