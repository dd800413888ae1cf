"""Held-out test windows for the prediction benchmark: episodes of a LeRobot dataset chosen by scene seed,
cut into ``T + H`` windows and batched for the policy.

A window is ``T + H`` consecutive frames of one episode (20 = 8 + 12); the current step is the
T-th frame (index T - 1): the policy reads the T states up to and including it plus the
episode's static scene context; the ground truth is the recorded TCP poses of the H following
frames. Only full windows are used (no padding at either end of an episode). Held-out episodes
are chosen by scene seed (the dataset's ``scene_seed`` column): a range ``A:B`` (A <= seed < B),
the last fraction of the dataset's scenes, or all of them.
"""

from __future__ import annotations

import math
from collections.abc import Sequence
from dataclasses import dataclass
from pathlib import Path
from typing import Any

import numpy as np
import torch

from rtv3_maniskill import features, se3


@dataclass
class EpisodeData:
    """One dataset episode: ``states (S, 27)`` and its static context (see ``features.py``)."""

    episode_index: int
    scene_seed: int
    states: np.ndarray
    point_cloud: np.ndarray
    point_cloud_mask: np.ndarray
    grasps: np.ndarray
    grasps_mask: np.ndarray


def parse_seed_range(text: str) -> tuple[int, int]:
    """``"A:B"`` -> ``(A, B)``: the scene seeds ``A <= s < B``."""
    parts = str(text).split(":")
    try:
        low, high = (int(p) for p in parts)
    except ValueError:
        raise ValueError(f"scene-seed range must look like A:B with integers (A <= seed < B), got {text!r}") from None
    if high <= low:
        raise ValueError(f"scene-seed range {text!r} is empty: need A < B (A <= seed < B)")
    return low, high


def select_scene_seeds(
    available: Sequence[int],
    seed_range: tuple[int, int] | None = None,
    last_fraction: float | None = None,
    all_scenes: bool = False,
) -> list[int]:
    """The held-out scene seeds among ``available`` (exactly one rule must be given).

    ``seed_range``: ``A <= s < B``; ``last_fraction``: the largest ``ceil(f * n)`` of the n
    distinct seeds (``rtv3 generate`` numbers scenes in order, so these are the last scenes
    made); ``all_scenes``: every seed.
    """
    rules = sum([seed_range is not None, last_fraction is not None, bool(all_scenes)])
    if rules != 1:
        raise ValueError("choose the held-out episodes with exactly one of: "
                         "scene-seed range, last fraction, all scenes")
    seeds = sorted({int(s) for s in available})
    if seed_range is not None:
        low, high = seed_range
        chosen = [s for s in seeds if low <= s < high]
        if not chosen:
            raise ValueError(
                f"no episode has a scene seed in [{low}, {high}); the dataset's seeds span {seeds[0]}..{seeds[-1]}"
                if seeds else "the dataset has no episodes"
            )
        return chosen
    if last_fraction is not None:
        if not (0.0 < last_fraction <= 1.0) or not math.isfinite(last_fraction):
            raise ValueError(f"last fraction must be in (0, 1], got {last_fraction}")
        if not seeds:
            raise ValueError("the dataset has no episodes")
        return seeds[len(seeds) - max(1, math.ceil(last_fraction * len(seeds))):]
    return seeds


def load_episodes(
    dataset_root: str | Path,
    seed_range: tuple[int, int] | None = None,
    last_fraction: float | None = None,
    all_scenes: bool = False,
) -> tuple[list[EpisodeData], dict[str, Any]]:
    """Held-out episodes of the LeRobot dataset at ``dataset_root`` and a description of the choice."""
    from lerobot.datasets.lerobot_dataset import LeRobotDataset  # lerobot loads in a few seconds: only here

    root = Path(dataset_root).expanduser()
    if not (root / "meta" / "info.json").is_file():
        raise FileNotFoundError(f"no LeRobot dataset at {root} (missing meta/info.json); make one with `rtv3 generate`")
    dataset = LeRobotDataset(features.REPO_ID, root=root)
    hf = dataset.hf_dataset
    needed = [features.STATE, "episode_index", "index", "scene_seed", features.POINT_CLOUD, features.GRASPS]
    missing = [k for k in needed if k not in hf.column_names]
    if missing:
        raise ValueError(f"dataset at {root} lacks the columns {missing} (not an `rtv3 generate` dataset?)")
    table = hf.select_columns([features.STATE, "episode_index", "scene_seed", "index"]).with_format("numpy")[:]
    episode_of = np.asarray(table["episode_index"]).reshape(-1)
    scene_of = np.asarray(table["scene_seed"]).reshape(-1)
    states = np.asarray(table[features.STATE], dtype=np.float64)
    chosen = set(select_scene_seeds(scene_of.tolist(), seed_range, last_fraction, all_scenes))
    context_keys = [features.POINT_CLOUD, features.POINT_CLOUD_MASK, features.GRASPS, features.GRASPS_MASK]
    context_columns = hf.select_columns(context_keys).with_format("numpy")
    episodes = []
    order = np.lexsort((np.asarray(table["index"]).reshape(-1), episode_of))  # grouped by episode, in frame order
    ids, starts = np.unique(episode_of[order], return_index=True)
    for ep, rows in zip(ids, np.split(order, starts[1:])):
        scene = int(scene_of[rows[0]])
        if scene not in chosen:
            continue
        context = context_columns[int(rows[0])]
        episodes.append(
            EpisodeData(
                episode_index=int(ep),
                scene_seed=scene,
                states=states[rows],
                point_cloud=features.unflatten(features.POINT_CLOUD,
                                               np.asarray(context[features.POINT_CLOUD], dtype=np.float32)),
                point_cloud_mask=np.asarray(context[features.POINT_CLOUD_MASK], dtype=np.float32),
                grasps=features.unflatten(features.GRASPS, np.asarray(context[features.GRASPS], dtype=np.float32)),
                grasps_mask=np.asarray(context[features.GRASPS_MASK], dtype=np.float32),
            )
        )
    if seed_range is not None:
        rule = f"scene seeds in [{seed_range[0]}, {seed_range[1]})"
    elif last_fraction is not None:
        rule = f"last {last_fraction:g} of the dataset's {len(set(scene_of.tolist()))} scenes (by seed)"
    else:
        rule = "all scenes of the dataset"
    return episodes, dict(rule=rule, scene_seeds=sorted(chosen), dataset_episodes=int(dataset.num_episodes))


def make_windows(episodes: Sequence[EpisodeData], history: int, horizon: int) -> list[tuple[int, int]]:
    """Every full window as ``(episode position in the list, current step)``:
    ``history - 1 <= t <= S - 1 - horizon``."""
    if history < 1 or horizon < 1:
        raise ValueError(f"history and horizon must be >= 1, got {history}, {horizon}")
    return [(i, t) for i, ep in enumerate(episodes) for t in range(history - 1, len(ep.states) - horizon)]


def _state_poses(states: np.ndarray) -> torch.Tensor:
    s = torch.as_tensor(states, dtype=torch.float64)
    return se3.pose_to_matrix(s[..., features.EE_POS], s[..., features.EE_QUAT])


def window_batch(
    episodes: Sequence[EpisodeData], windows: Sequence[tuple[int, int]], history: int, horizon: int
) -> tuple[dict[str, torch.Tensor], torch.Tensor, torch.Tensor]:
    """Policy batch, current poses ``(B, 4, 4)`` and recorded future poses ``(B, H, 4, 4)`` (float64, world)."""
    states, clouds, cloud_masks, grasps, grasp_masks, futures = [], [], [], [], [], []
    for i, t in windows:
        ep = episodes[i]
        states.append(ep.states[t - history + 1 : t + 1])
        futures.append(ep.states[t : t + horizon + 1])
        clouds.append(ep.point_cloud)
        cloud_masks.append(ep.point_cloud_mask)
        grasps.append(ep.grasps)
        grasp_masks.append(ep.grasps_mask)
    batch = {
        features.STATE: torch.as_tensor(np.stack(states), dtype=torch.float32),
        features.POINT_CLOUD: torch.as_tensor(np.stack(clouds)),
        features.POINT_CLOUD_MASK: torch.as_tensor(np.stack(cloud_masks)),
        features.GRASPS: torch.as_tensor(np.stack(grasps)),
        features.GRASPS_MASK: torch.as_tensor(np.stack(grasp_masks)),
    }
    poses = _state_poses(np.stack(futures))  # (B, H + 1, 4, 4)
    return batch, poses[:, 0], poses[:, 1:]
