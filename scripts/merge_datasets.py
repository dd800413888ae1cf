"""Merge RT-V3 LeRobot datasets (planner demonstrations, DAgger rounds) into one training set.

    python scripts/merge_datasets.py data/train_v2 data/dagger_r1 --output data/train_r1

Uses LeRobot's own ``merge_datasets`` through ``rtv3_maniskill.datagen.merge`` (which mends its
episode-file labels, so a merged dataset can be merged again); episodes keep their order, source by
source. The output folder must not exist (a half-written merge is removed).
"""

from __future__ import annotations

import argparse
import sys
from pathlib import Path


def main(argv: list[str] | None = None) -> int:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("sources", nargs="+", type=Path, help="dataset folders (LeRobot roots)")
    parser.add_argument("--output", type=Path, required=True, help="new dataset folder")
    args = parser.parse_args(argv)
    from rtv3_maniskill.datagen.merge import merge

    try:
        merged, datasets = merge(args.sources, args.output)
    except (FileNotFoundError, FileExistsError) as error:
        raise SystemExit(f"error: {error}") from None
    print(f"{args.output}: {merged.meta.total_episodes} episodes, {merged.meta.total_frames} frames "
          f"from {', '.join(f'{d.meta.total_episodes} ({s})' for d, s in zip(datasets, args.sources))}")
    return 0


if __name__ == "__main__":
    sys.exit(main())
