"""Merge RT-V3 LeRobot datasets (planner demonstrations, DAgger rounds) into one training set.

LeRobot's ``merge_datasets`` (0.4.4) labels each episode-metadata row with the source's file
index plus an offset instead of the file it was written to. Once a merge's episode metadata
spills into a second file, both files say ``meta/episodes/file_index`` 0; the dataset still loads
(LeRobot reads every file), but merging it again reads only the rows of file 0 and drops the
others without a word. :func:`repair_episode_file_labels` rewrites the labels from where each
row lies, and :func:`merge` repairs its sources and its output and checks that no episode or
frame went missing.
"""

from __future__ import annotations

import logging
import shutil
from pathlib import Path

import pyarrow as pa
import pyarrow.parquet as pq

from rtv3_maniskill.features import REPO_ID

_CHUNK, _FILE = "meta/episodes/chunk_index", "meta/episodes/file_index"


def repair_episode_file_labels(root: str | Path) -> int:
    """Set every episode-metadata row's ``meta/episodes/{chunk,file}_index`` to the file it lies in.

    Returns the number of rows that were relabelled (0 for a consistent dataset).
    """
    fixed = 0
    for path in sorted((Path(root) / "meta" / "episodes").glob("chunk-*/file-*.parquet")):
        chunk, file = int(path.parent.name.split("-")[1]), int(path.stem.split("-")[1])
        table = pq.read_table(path)
        wrong = sum(int(c) != chunk or int(f) != file
                    for c, f in zip(table.column(_CHUNK).to_pylist(), table.column(_FILE).to_pylist()))
        if wrong:
            for name, value in ((_CHUNK, chunk), (_FILE, file)):
                position = table.schema.get_field_index(name)
                column = pa.array([value] * table.num_rows, type=table.schema.field(name).type)
                table = table.set_column(position, name, column)
            pq.write_table(table, path)
            fixed += wrong
    if fixed:
        logging.info("%s: relabelled %d episode-metadata rows with the file they lie in", root, fixed)
    return fixed


def merge(sources: list[Path], output: Path):
    """Merge ``sources`` (LeRobot roots, episodes kept in order, source by source) into ``output``.

    Raises ``FileNotFoundError`` for a source without ``meta/info.json``, ``FileExistsError`` when
    ``output`` exists, and ``RuntimeError`` (removing ``output``) when the merged metadata does not
    hold every source episode.
    """
    missing = [str(s) for s in sources if not (Path(s) / "meta" / "info.json").is_file()]
    if missing:
        raise FileNotFoundError(f"not a LeRobot dataset (no meta/info.json): {', '.join(missing)}")
    if Path(output).exists():
        raise FileExistsError(f"{output} exists; remove it or choose another folder")
    from lerobot.datasets.dataset_tools import merge_datasets
    from lerobot.datasets.lerobot_dataset import LeRobotDataset

    for source in sources:
        repair_episode_file_labels(source)
    datasets = [LeRobotDataset(REPO_ID, root=s) for s in sources]
    try:
        merge_datasets(datasets, output_repo_id=REPO_ID, output_dir=output)
        repair_episode_file_labels(output)
        merged = LeRobotDataset(REPO_ID, root=output)
        expected = sum(d.meta.total_episodes for d in datasets)
        listed = len(merged.meta.episodes)  # the rows of every episode-metadata file
        if listed != expected or merged.meta.total_frames != sum(d.meta.total_frames for d in datasets):
            raise RuntimeError(f"merge lost data: {listed} episodes listed, {expected} expected")
    except BaseException:
        shutil.rmtree(output, ignore_errors=True)
        raise
    return merged, datasets
