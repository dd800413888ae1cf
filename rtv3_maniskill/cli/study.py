"""``rtv3 study``: plan a counterbalanced user study, analyze its recorded sessions."""

from __future__ import annotations

import argparse


def add_arguments(parser: argparse.ArgumentParser) -> None:
    pass


def run(args: argparse.Namespace) -> int:
    return 0
