"""``rtv3 merge SRC... --output DST``: merge LeRobot datasets (demonstrations, DAgger rounds) into one.

Episodes keep their order, source by source. LeRobot's own ``merge_datasets`` does the work, through
``rtv3_maniskill.datagen.merge`` (which mends its episode-file labels, so that a merged dataset can be
merged again, and checks that no episode or frame went missing). The output folder must not exist; a
half-written merge is removed.
"""

from __future__ import annotations

import argparse
from pathlib import Path


def add_arguments(parser: argparse.ArgumentParser) -> None:
    parser.add_argument("sources", nargs="+", type=Path, metavar="SRC",
                        help="dataset folders (LeRobot roots, e.g. rtv3 generate / rtv3 dagger --output)")
    parser.add_argument("--output", type=Path, required=True, help="the merged dataset's folder (must not exist)")


def run(args: argparse.Namespace) -> int:
    missing = [str(s) for s in args.sources if not s.is_dir()]
    if missing:
        raise SystemExit(f"error: no such dataset folder: {', '.join(missing)}")
    from rtv3_maniskill.datagen.merge import merge

    try:
        merged, datasets = merge(args.sources, args.output)
    except (FileNotFoundError, FileExistsError) as err:
        raise SystemExit(f"error: {err}") from None
    parts = ", ".join(f"{d.meta.total_episodes} ({s})" for d, s in zip(datasets, args.sources))
    print(f"{args.output}: {merged.meta.total_episodes} episodes, {merged.meta.total_frames} frames from {parts}")
    return 0
