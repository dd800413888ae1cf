"""Merge RT-V3 LeRobot datasets (planner demonstrations, DAgger rounds) into one training set.

    python scripts/merge_datasets.py data/train_v2 data/dagger_r1 --output data/train_r1

Uses LeRobot's own ``merge_datasets`` (``lerobot.datasets.dataset_tools``); episodes keep their
order, source by source. The output folder must not exist (a half-written merge is removed).
"""

from __future__ import annotations

import argparse
import shutil
import sys
from pathlib import Path


def main(argv: list[str] | None = None) -> int:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("sources", nargs="+", type=Path, help="dataset folders (LeRobot roots)")
    parser.add_argument("--output", type=Path, required=True, help="new dataset folder")
    args = parser.parse_args(argv)
    missing = [str(s) for s in args.sources if not (s / "meta" / "info.json").is_file()]
    if missing:
        raise SystemExit(f"error: not a LeRobot dataset (no meta/info.json): {', '.join(missing)}")
    if args.output.exists():
        raise SystemExit(f"error: --output {args.output} exists; remove it or choose another folder")
    from lerobot.datasets.dataset_tools import merge_datasets
    from lerobot.datasets.lerobot_dataset import LeRobotDataset

    from rtv3_maniskill.datasets.lerobot_export import REPO_ID

    datasets = [LeRobotDataset(REPO_ID, root=s) for s in args.sources]
    try:
        merged = merge_datasets(datasets, output_repo_id=REPO_ID, output_dir=args.output)
    except BaseException:
        shutil.rmtree(args.output, ignore_errors=True)
        raise
    print(f"{args.output}: {merged.meta.total_episodes} episodes, {merged.meta.total_frames} frames "
          f"from {', '.join(f'{d.meta.total_episodes} ({s})' for d, s in zip(datasets, args.sources))}")
    return 0


if __name__ == "__main__":
    sys.exit(main())
