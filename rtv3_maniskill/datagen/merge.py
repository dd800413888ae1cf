"""Merge RT-V3 LeRobot datasets (planner demonstrations, DAgger rounds) into one training set.

LeRobot's ``merge_datasets`` (0.4.4) labels each episode-metadata row with the source's file
index plus an offset instead of the file it was written to. Once a merge's episode metadata
spills into a second file, both files say ``meta/episodes/file_index`` 0; the dataset still loads
(LeRobot reads every file), but merging it again reads only the rows of file 0 and drops the
others without a word. :func:`repair_episode_file_labels` rewrites the labels from where each
row lies, and :func:`merge` repairs its sources and its output and checks that no episode or
frame went missing.

Datasets written before the scene summary existed lack ``observation.environment_state``; it is derived
from each frame's point cloud and grasps, so :func:`add_scene_summary` adds it (with its statistics), and
:func:`merge` adds it to every source that lacks it before merging.
"""

from __future__ import annotations

import json
import logging
import shutil
from pathlib import Path

import numpy as np
import pyarrow as pa
import pyarrow.parquet as pq
from lerobot.datasets.compute_stats import get_feature_stats
from lerobot.datasets.dataset_tools import add_features, merge_datasets
from lerobot.datasets.lerobot_dataset import LeRobotDataset
from lerobot.datasets.utils import write_stats

from rtv3_maniskill import features
from rtv3_maniskill.datagen.lerobot_export import dataset_features
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


def has_scene_summary(root: str | Path) -> bool:
    """Whether the dataset at ``root`` stores ``observation.environment_state``."""
    info = json.loads((Path(root) / "meta" / "info.json").read_text())
    return features.ENV_STATE in info["features"]


def add_scene_summary(source: str | Path, output: str | Path) -> LeRobotDataset:
    """A copy of the dataset ``source`` in ``output`` with ``observation.environment_state``, the scene summary
    (``features.scene_summary``) of each frame's point cloud and grasps, and its statistics in ``meta/stats.json``.

    Raises ``FileExistsError`` when ``output`` exists and ``ValueError`` when ``source`` already has the feature;
    a half-written copy is removed.
    """
    source, output = Path(source), Path(output)
    if output.exists():
        raise FileExistsError(f"{output} exists; remove it or choose another folder")
    if has_scene_summary(source):
        raise ValueError(f"{source} already has '{features.ENV_STATE}'")
    dataset = LeRobotDataset(REPO_ID, root=source)
    max_grasps = features.rows_of(features.GRASPS, dataset.meta.features[features.GRASPS]["shape"])
    spec = dataset_features(1, max_grasps)[features.ENV_STATE]
    summaries: list[np.ndarray] = []

    def summary(row: dict, episode: int, frame: int) -> np.ndarray:
        value = features.scene_summary(row[features.POINT_CLOUD], row[features.POINT_CLOUD_MASK],
                                       row[features.GRASPS], row[features.GRASPS_MASK]).numpy()
        summaries.append(value)
        return value

    try:
        add_features(dataset, {features.ENV_STATE: (summary, spec)}, output_dir=output, repo_id=REPO_ID)
        stats = json.loads((output / "meta" / "stats.json").read_text())
        stats = {k: {s: np.asarray(v) for s, v in d.items()} for k, d in stats.items()}
        stats[features.ENV_STATE] = get_feature_stats(np.stack(summaries), axis=0, keepdims=False)
        write_stats(stats, output)
    except BaseException:
        shutil.rmtree(output, ignore_errors=True)
        raise
    logging.info("%s: added '%s' to %d frames", output, features.ENV_STATE, len(summaries))
    return LeRobotDataset(REPO_ID, root=output)


def merge(sources: list[Path], output: Path):
    """Merge ``sources`` (LeRobot roots, episodes kept in order, source by source) into ``output``.

    Raises ``FileNotFoundError`` for a source without ``meta/info.json``, ``FileExistsError`` when
    ``output`` exists, and ``RuntimeError`` (removing ``output``) when the merged metadata does not
    hold every source episode.
    """
    missing = [str(s) for s in sources if not (Path(s) / "meta" / "info.json").is_file()]
    if missing:
        raise FileNotFoundError(f"not a LeRobot dataset (no meta/info.json): {', '.join(missing)}")
    output = Path(output)
    if output.exists():
        raise FileExistsError(f"{output} exists; remove it or choose another folder")
    for source in sources:
        repair_episode_file_labels(source)
    converted = output.parent / f".{output.name}.with-summary"
    shutil.rmtree(converted, ignore_errors=True)  # left by a merge that was killed
    try:
        # The scene summary is derived: a source without it gets it in a converted copy first.
        datasets = []
        for i, source in enumerate(sources):
            if not has_scene_summary(source):
                datasets.append(add_scene_summary(source, converted / str(i)))
            else:
                datasets.append(LeRobotDataset(REPO_ID, root=source))
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
    finally:
        shutil.rmtree(converted, ignore_errors=True)
    return merged, datasets
