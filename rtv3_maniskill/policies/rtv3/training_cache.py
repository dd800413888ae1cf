"""In-memory training cache: a dataset's actions and states, read once, windows cut by frame index.

``lerobot-train`` loads every sample with ``LeRobotDataset.__getitem__``. With an ``action``
window of H = 12 frames LeRobot reads 1 + 12 full dataset rows per sample, each with its
point cloud and grasps (the episode's static scene context, repeated in every frame): ~13x
the data of one row, and most of a training step on CPU. So ``RTV3Config`` asks LeRobot for
no window at all (one row per sample) and the policy cuts the windows from this cache
instead, by the batch's absolute frame ``index`` (which LeRobot's processor pipeline keeps).
The cache holds only the ``action`` and ``observation.state`` columns (33 floats per frame:
~1 MB for 8k frames), read once with pyarrow from the dataset's parquet files, and each
frame's episode bounds from the dataset metadata.

Windows are exactly LeRobot's (``LeRobotDataset._get_query_indices``): frame indices clamped
to the episode, ``*_is_pad`` True outside it.
"""

from __future__ import annotations

import logging
from dataclasses import dataclass
from pathlib import Path

import numpy as np
import torch

from rtv3_maniskill import features


@dataclass
class TrainingCache:
    """Columns of a LeRobot dataset by absolute frame index (the dataset's ``index`` column).

    Attributes:
        actions: ``(F, 6)``; states: ``(F, 27)``; episode_start / episode_end: ``(F,)`` int64,
            the first and one-past-the-last absolute index of each frame's episode.
        loaded: ``(F,)`` bool, False for indices no data file held.
    """

    actions: torch.Tensor
    states: torch.Tensor
    episode_start: torch.Tensor
    episode_end: torch.Tensor
    loaded: torch.Tensor

    @classmethod
    def from_dataset_meta(cls, meta) -> TrainingCache | None:
        """Read the cache of the dataset described by ``meta`` (a ``LeRobotDatasetMetadata``);
        ``None`` when its data files are not on disk (e.g. metadata of a dataset not yet written)."""
        import pyarrow.parquet as pq

        root = Path(meta.root)
        if meta.episodes is None and (root / "meta" / "episodes").is_dir():
            # the metadata of a dataset written in this process (LeRobotDataset.create) holds no episode table
            from lerobot.datasets.lerobot_dataset import LeRobotDatasetMetadata

            meta = LeRobotDatasetMetadata(meta.repo_id, root=root)
        episodes = meta.episodes
        if episodes is None or len(episodes) == 0:
            return None
        paths = sorted({root / meta.get_data_file_path(i) for i in range(len(episodes))})
        if not paths or not all(p.is_file() for p in paths):
            return None
        columns = ["index", features.ACTION, features.STATE]
        tables = [pq.read_table(p, columns=columns) for p in paths]
        index = np.concatenate([t.column("index").to_numpy() for t in tables]).astype(np.int64)
        size = int(index.max()) + 1 if index.size else 0

        def column(name: str, width: int) -> torch.Tensor:
            flat = np.concatenate([t.column(name).combine_chunks().flatten().to_numpy() for t in tables])
            out = torch.zeros(size, width, dtype=torch.float32)
            out[torch.from_numpy(index)] = torch.from_numpy(flat.astype(np.float32).reshape(-1, width))
            return out

        ep = episodes.select_columns(["dataset_from_index", "dataset_to_index"]).with_format("numpy")[:]
        starts = np.asarray(ep["dataset_from_index"], dtype=np.int64)
        ends = np.asarray(ep["dataset_to_index"], dtype=np.int64)
        episode_start = torch.zeros(size, dtype=torch.long)
        episode_end = torch.zeros(size, dtype=torch.long)
        for start, end in zip(starts.tolist(), ends.tolist()):
            episode_start[start:end] = start
            episode_end[start:end] = end
        loaded = torch.zeros(size, dtype=torch.bool)
        loaded[torch.from_numpy(index)] = True
        cache = cls(column(features.ACTION, 6), column(features.STATE, features.STATE_DIM), episode_start,
                    episode_end, loaded)
        logging.info("rtv3 training cache: %d frames of %s (actions + states, %.1f MB)", int(loaded.sum()), root,
                     (cache.actions.numel() + cache.states.numel()) * 4 / 2**20)
        return cache

    def _frames(self, index: torch.Tensor) -> torch.Tensor:
        index = index.reshape(-1).long().cpu()
        if index.numel() and (int(index.min()) < 0 or int(index.max()) >= self.loaded.numel()
                              or not bool(self.loaded[index].all())):
            raise IndexError("batch 'index' holds frames the rtv3 training cache does not have: the batch is not "
                             "from the dataset the policy was made with (make_policy(cfg, ds_meta=dataset.meta))")
        return index

    def _window(self, index: torch.Tensor, deltas: range) -> tuple[torch.Tensor, torch.Tensor]:
        """Clamped absolute indices ``(B, len(deltas))`` and their padding flags (LeRobot's rule)."""
        query = index[:, None] + torch.tensor(list(deltas), dtype=torch.long)[None]
        start, end = self.episode_start[index][:, None], self.episode_end[index][:, None]
        pad = (query < start) | (query >= end)
        return torch.minimum(torch.maximum(query, start), end - 1), pad

    def action_windows(self, index: torch.Tensor, horizon: int) -> tuple[torch.Tensor, torch.Tensor]:
        """``a_0 .. a_{H-1}`` of each frame: ``(B, H, 6)`` and ``action_is_pad (B, H)`` bool."""
        query, pad = self._window(self._frames(index), range(horizon))
        return self.actions[query], pad

    def state_windows(self, index: torch.Tensor, steps: int) -> torch.Tensor:
        """States ``s_{-T+1} .. s_0`` of each frame ``(B, T, 27)``, the first state repeated before
        the episode start (what LeRobot's windows, the stored history and the inference queue give)."""
        query, _ = self._window(self._frames(index), range(-steps + 1, 1))
        return self.states[query]
