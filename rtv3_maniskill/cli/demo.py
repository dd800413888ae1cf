"""``rtv3 demo``: the main job. Until the shared-control demo lands it renders a scene."""

from __future__ import annotations

import argparse

from rtv3_maniskill.cli import scene


def add_arguments(parser: argparse.ArgumentParser) -> None:
    scene.add_arguments(parser)


def run(args: argparse.Namespace) -> int:
    return scene.run(args)
