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

import datasets
import numpy as np
import pyarrow as pa
import pyarrow.parquet as pq
from lerobot.datasets.compute_stats import DEFAULT_QUANTILES, get_feature_stats
from lerobot.datasets.dataset_tools import merge_datasets
from lerobot.datasets.lerobot_dataset import LeRobotDataset
from lerobot.datasets.utils import get_hf_features_from_features, load_stats, write_info, write_stats
from tqdm import tqdm

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


_CONTEXT = (features.POINT_CLOUD, features.POINT_CLOUD_MASK, features.GRASPS, features.GRASPS_MASK)


def _with_scene_summary(table: pa.Table, schema: pa.Schema, rows: int = 2048) -> pa.Table:
    """``table`` (one data file) with the scene-summary column, ``rows`` frames at a time, cast to ``schema``."""
    parts = []
    for batch in table.select(list(_CONTEXT)).to_batches(max_chunksize=rows):
        columns = [np.stack(batch.column(k).to_numpy(zero_copy_only=False)) for k in _CONTEXT]
        summary = features.scene_summary(*columns).numpy()
        parts.append(pa.FixedSizeListArray.from_arrays(pa.array(summary.reshape(-1)), summary.shape[1]))
    column = pa.chunked_array(parts, type=schema.field(features.ENV_STATE).type)
    return table.append_column(features.ENV_STATE, column).select(schema.names).cast(schema)


def add_scene_summary(source: str | Path, output: str | Path) -> LeRobotDataset:
    """A copy of the dataset ``source`` in ``output`` with ``observation.environment_state``, the scene summary
    (``features.scene_summary``) of each frame's point cloud and grasps, and its statistics (``meta/stats.json``
    and each episode's, for LeRobot's merge).

    One data file at a time in Arrow (a dataset's point clouds need not fit in memory). Raises
    ``FileExistsError`` when ``output`` exists and ``ValueError`` when ``source`` already has the feature; a
    half-written copy is removed.
    """
    source, output = Path(source), Path(output)
    if output.exists():
        raise FileExistsError(f"{output} exists; remove it or choose another folder")
    if has_scene_summary(source):
        raise ValueError(f"{source} already has '{features.ENV_STATE}'")
    info = json.loads((source / "meta" / "info.json").read_text())
    max_grasps = features.rows_of(features.GRASPS, info["features"][features.GRASPS]["shape"])
    spec = dataset_features(1, max_grasps)[features.ENV_STATE]
    info["features"][features.ENV_STATE] = {**spec, "shape": list(spec["shape"])}
    # shapes as tuples, as LeRobot's load_info gives them (a (1,) feature is a scalar column)
    schema = get_hf_features_from_features(
        {k: {**v, "shape": tuple(v["shape"])} for k, v in info["features"].items()}).arrow_schema
    try:
        shutil.copytree(source, output, ignore=shutil.ignore_patterns("*.parquet", "*.lock"))
        for path in sorted((source / "meta").rglob("*.parquet")):
            shutil.copy2(path, output / path.relative_to(source))
        summaries, episode_of = [], []
        for path in tqdm(sorted((source / "data").glob("*/*.parquet")), desc="scene summary", unit="file"):
            table = _with_scene_summary(pq.read_table(path), schema)
            pq.write_table(table, output / path.relative_to(source))
            column = table.column(features.ENV_STATE).combine_chunks()
            summaries.append(column.flatten().to_numpy().reshape(len(table), -1))
            episode_of.append(table.column("episode_index").to_numpy())
            del table
        summaries, episode_of = np.concatenate(summaries), np.concatenate(episode_of)
        write_info(info, output)
        stats = {k: {s: np.asarray(v) for s, v in d.items()} for k, d in load_stats(source).items()}
        stats[features.ENV_STATE] = get_feature_stats(summaries, axis=0, keepdims=False)
        write_stats(stats, output)
        _add_episode_stats(output, summaries, episode_of)
    except BaseException:
        shutil.rmtree(output, ignore_errors=True)
        raise
    logging.info("%s: added '%s' to %d frames", output, features.ENV_STATE, len(summaries))
    return LeRobotDataset(REPO_ID, root=output)


def _stats(values: np.ndarray) -> dict[str, np.ndarray]:
    """LeRobot's per-feature statistics of ``values (frames, D)``: min, max, mean, std, count and its quantiles
    (exact here; LeRobot's running estimate is slow for a long vector and exact for an episode's few frames)."""
    out = dict(min=values.min(0), max=values.max(0), mean=values.mean(0), std=values.std(0),
               count=np.array([len(values)]))
    for q in DEFAULT_QUANTILES:
        out[f"q{int(round(q * 100)):02d}"] = np.quantile(values, q, axis=0)
    return out


def _add_episode_stats(root: Path, summaries: np.ndarray, episode_of: np.ndarray) -> None:
    """Each episode-metadata row gains the scene summary's ``stats/<key>/<stat>`` columns, as LeRobot writes them."""
    for path in sorted((root / "meta" / "episodes").glob("chunk-*/file-*.parquet")):
        table = pq.read_table(path)
        per_episode = [_stats(summaries[episode_of == e]) for e in table.column("episode_index").to_pylist()]
        for stat in per_episode[0]:
            values = np.stack([np.asarray(s[stat]).reshape(-1) for s in per_episode])  # (episodes, D)
            offsets = np.arange(0, values.size + 1, values.shape[1], dtype=np.int32)
            name = f"stats/{features.ENV_STATE}/{stat}"
            if name in table.column_names:  # left behind by a removal of the feature (lerobot remove_feature)
                table = table.drop_columns([name])
            table = table.append_column(name, pa.ListArray.from_arrays(offsets, values.reshape(-1)))
        # the Hugging Face schema note must list the new columns (as datasets writes it; building a
        # datasets.Dataset instead would hash the whole table, gigabytes for a large dataset)
        schema = datasets.Features.from_arrow_schema(table.schema.remove_metadata()).arrow_schema
        pq.write_table(table.cast(schema), path)


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
