"""Compact training cache: a LeRobot dataset cut down to what an RT-V3 training step reads.

A LeRobot row repeats the episode's scene context (point cloud and grasp candidates) and the
state history in every frame; the RT-V3 loss needs, per frame, only the episode's context, the
frame's state window and its future actions. This module stores each scene context once (episodes
of one scene share it), each episode's states and actions once, and the T - 1 states before each
episode's first frame (its stored history: the first state repeated for a planner demonstration,
the user's own motion before a DAgger relabel). The whole training set then fits in memory, or on
a GPU machine that has PyTorch but not LeRobot (``compact_training.py``): 4,095 episodes take
38 MiB in memory (33 MiB as a file) against 222 MB of the datasets' parquet files.

Layout of ``cache.npz`` (E episodes, F frames, C distinct contexts):

* ``states (F, 27)``, ``actions (F, 6)`` float32, episodes contiguous in dataset order;
* ``episode_length (E,)``, ``episode_context (E,)`` int64 (row of the context arrays),
  ``episode_target (E,)`` int64 (``target_grasp_index``, -1 when the dataset has none),
  ``history_prefix (E, T - 1, 27)`` float32;
* ``point_cloud (C, N, 6)`` float32, ``point_mask (C, N)`` bool, ``grasps (C, M, 9)`` float32,
  ``grasp_mask (C, M)`` bool (world frame, ``features.py``).

Windows come from :class:`TrainingCache` over the states with each episode's prefix placed in
front of it (prefix rows are never sampled), so the state history and the padded action windows
follow LeRobot's rule exactly; the export checks every frame's rebuilt history against the
dataset's stored ``observation.state_history``.
"""

from __future__ import annotations

import hashlib
import json
import logging
from dataclasses import dataclass, fields
from pathlib import Path

import numpy as np
import torch

from rtv3_maniskill import features
from rtv3_maniskill.policies.rtv3.batch import RTV3Inputs, SceneContext
from rtv3_maniskill.policies.rtv3.training_cache import TrainingCache

CACHE_FILE = "cache.npz"
CONFIG_FILE = "config.json"
"""The RT-V3 config the run trains (LeRobot's ``config.json`` of ``RTV3Config``)."""
INIT_WEIGHTS_FILE = "init_model.safetensors"
"""Optional starting weights (a checkpoint's ``model.safetensors``) for a fine-tune."""
SUMMARY_FILE = "summary.json"


@dataclass
class CompactCache:
    """A training set in memory; shapes in the module docstring."""

    states: torch.Tensor
    actions: torch.Tensor
    episode_length: torch.Tensor
    episode_context: torch.Tensor
    episode_target: torch.Tensor
    history_prefix: torch.Tensor
    point_cloud: torch.Tensor
    point_mask: torch.Tensor
    grasps: torch.Tensor
    grasp_mask: torch.Tensor

    def __post_init__(self) -> None:
        e, f = self.episode_length.shape[0], self.states.shape[0]
        checks = {
            "states": (self.states.ndim == 2 and self.states.shape[1] == features.STATE_DIM,
                       f"(F, {features.STATE_DIM})"),
            "actions": (tuple(self.actions.shape) == (f, 6), f"({f}, 6)"),
            "episode_length": (int(self.episode_length.sum()) == f and bool((self.episode_length > 0).all()),
                               f"positive lengths summing to the {f} frames"),
            "episode_context": (tuple(self.episode_context.shape) == (e,) and bool(
                ((self.episode_context >= 0) & (self.episode_context < self.point_cloud.shape[0])).all()),
                f"({e},) rows of the {self.point_cloud.shape[0]} contexts"),
            "episode_target": (tuple(self.episode_target.shape) == (e,), f"({e},)"),
            "history_prefix": (self.history_prefix.ndim == 3 and self.history_prefix.shape[0] == e
                               and self.history_prefix.shape[2] == features.STATE_DIM, f"({e}, T - 1, 27)"),
            "point_cloud": (self.point_cloud.ndim == 3 and self.point_cloud.shape[2] == 6, "(C, N, 6)"),
            "point_mask": (tuple(self.point_mask.shape) == tuple(self.point_cloud.shape[:2]), "(C, N)"),
            "grasps": (self.grasps.ndim == 3 and self.grasps.shape[2] == features.GRASP_DIM
                       and self.grasps.shape[0] == self.point_cloud.shape[0], "(C, M, 9)"),
            "grasp_mask": (tuple(self.grasp_mask.shape) == tuple(self.grasps.shape[:2]), "(C, M)"),
        }
        for name, (ok, want) in checks.items():
            if not ok:
                shape = tuple(getattr(self, name).shape)
                raise ValueError(f"compact cache: '{name}' has shape {shape}, expected {want}")
        for name in ("states", "actions", "history_prefix", "point_cloud", "grasps"):
            if not bool(torch.isfinite(getattr(self, name)).all()):
                raise ValueError(f"compact cache: '{name}' contains NaN or inf values")

    # ------------------------------------------------------------------ sizes

    @property
    def num_frames(self) -> int:
        return int(self.states.shape[0])

    @property
    def num_episodes(self) -> int:
        return int(self.episode_length.shape[0])

    @property
    def history_steps(self) -> int:
        """T, the history length the prefixes were cut for."""
        return int(self.history_prefix.shape[1]) + 1

    def nbytes(self) -> int:
        return sum(getattr(self, f.name).numel() * getattr(self, f.name).element_size() for f in fields(self))

    # ------------------------------------------------------------------ files

    def save(self, path: str | Path) -> None:
        arrays = {f.name: getattr(self, f.name).cpu().numpy() for f in fields(self)}
        np.savez_compressed(path, **arrays)

    @classmethod
    def load(cls, path: str | Path) -> CompactCache:
        path = Path(path)
        if not path.is_file():
            raise FileNotFoundError(f"no compact training cache at {path} (make one with `rtv3 compact-cache build`)")
        with np.load(path) as data:
            missing = [f.name for f in fields(cls) if f.name not in data.files]
            if missing:
                raise ValueError(f"{path} is not a compact training cache: it lacks {missing}")
            return cls(**{f.name: torch.from_numpy(data[f.name]) for f in fields(cls)})

    def select_episodes(self, keep: np.ndarray) -> CompactCache:
        """The cache restricted to episodes ``keep`` (sorted indices), contexts no longer used dropped."""
        keep = np.sort(np.asarray(keep, dtype=np.int64))
        starts = np.concatenate([[0], np.cumsum(self.episode_length.numpy())[:-1]])
        frames = np.concatenate([np.arange(starts[e], starts[e] + int(self.episode_length[e])) for e in keep])
        used, context = np.unique(self.episode_context.numpy()[keep], return_inverse=True)
        return CompactCache(
            self.states[frames], self.actions[frames], self.episode_length[keep], torch.from_numpy(context),
            self.episode_target[keep], self.history_prefix[keep], self.point_cloud[used], self.point_mask[used],
            self.grasps[used], self.grasp_mask[used])

    @classmethod
    def concatenate(cls, parts: list[CompactCache]) -> CompactCache:
        """Several caches as one (e.g. demonstrations and DAgger rounds, without merging the datasets)."""
        if not parts:
            raise ValueError("no caches to concatenate")
        shapes = {(p.history_steps, *p.point_cloud.shape[1:], *p.grasps.shape[1:]) for p in parts}
        if len(shapes) > 1:
            raise ValueError(f"caches with different history / points / grasps (T, N, 6, M, 9): {sorted(shapes)}")
        offsets = np.cumsum([0] + [p.point_cloud.shape[0] for p in parts[:-1]])
        cat = lambda name: torch.cat([getattr(p, name) for p in parts])  # noqa: E731
        return cls(cat("states"), cat("actions"), cat("episode_length"),
                   torch.cat([p.episode_context + int(o) for p, o in zip(parts, offsets)]), cat("episode_target"),
                   cat("history_prefix"), cat("point_cloud"), cat("point_mask"), cat("grasps"), cat("grasp_mask"))

    # ------------------------------------------------------------------ training batches

    def windows(self) -> WindowedCache:
        """The states with each episode's prefix in front, as a :class:`TrainingCache` (CPU)."""
        return WindowedCache.of(self)


@dataclass
class WindowedCache:
    """A :class:`CompactCache` laid out for LeRobot's window rule.

    Attributes:
        cache: the :class:`TrainingCache` over ``prefix + frames`` of every episode (prefix rows not loaded).
        frame_rows: ``(F,)`` row of each real frame in that layout; frame_episode: ``(F,)`` its episode.
    """

    compact: CompactCache
    cache: TrainingCache
    frame_rows: torch.Tensor
    frame_episode: torch.Tensor

    @classmethod
    def of(cls, compact: CompactCache) -> WindowedCache:
        lengths = compact.episode_length.long()
        pad = compact.history_steps - 1
        total = lengths + pad
        block_start = torch.cumsum(total, 0) - total
        rows = int(total.sum())
        frame_episode = torch.repeat_interleave(torch.arange(compact.num_episodes), lengths)
        first_frame = torch.cumsum(lengths, 0) - lengths
        frame_offset = torch.arange(compact.num_frames) - torch.repeat_interleave(first_frame, lengths)
        frame_rows = block_start[frame_episode] + pad + frame_offset
        states = torch.zeros(rows, features.STATE_DIM)
        actions = torch.zeros(rows, 6)
        states[frame_rows] = compact.states.float()
        actions[frame_rows] = compact.actions.float()
        prefix_rows = (block_start[:, None] + torch.arange(pad)[None]).reshape(-1)
        states[prefix_rows] = compact.history_prefix.float().reshape(-1, features.STATE_DIM)
        episode_start = torch.repeat_interleave(block_start, total)
        episode_end = torch.repeat_interleave(block_start + total, total)
        loaded = torch.zeros(rows, dtype=torch.bool)
        loaded[frame_rows] = True
        cache = TrainingCache(actions, states, episode_start, episode_end, loaded)
        return cls(compact, cache, frame_rows, frame_episode)

    def batch(self, frames: torch.Tensor, horizon: int, device: torch.device | str = "cpu"
              ) -> tuple[RTV3Inputs, torch.Tensor, torch.Tensor, torch.Tensor]:
        """One training batch for frames ``(B,)`` (indices 0..F-1 of the compact cache).

        Returns:
            inputs: states ``(B, T, 27)`` and the scene context (world frame); actions ``(B, H, 6)``;
            valid ``(B, H)`` bool (False: past the episode end); target ``(B,)`` target grasp index.
        """
        frames = frames.cpu()
        rows = self.frame_rows[frames]
        c = self.compact
        states = self.cache.state_windows(rows, c.history_steps)
        actions, pad = self.cache.action_windows(rows, horizon)
        episode = self.frame_episode[frames]
        ctx = c.episode_context[episode].to(c.point_cloud.device)  # the contexts may live on the GPU (contexts_to)
        to = lambda t: t.to(device, non_blocking=True)  # noqa: E731
        context = SceneContext(to(c.point_cloud[ctx].float()), to(c.point_mask[ctx].bool()),
                               to(c.grasps[ctx].float()), to(c.grasp_mask[ctx].bool()))
        return RTV3Inputs(to(states), context), to(actions), to(~pad), to(c.episode_target[episode].long())

    def contexts_to(self, device: torch.device | str) -> None:
        """Keep the scene contexts (most of the cache's bytes) on ``device``: batches gather them there."""
        c = self.compact
        c.point_cloud, c.point_mask = c.point_cloud.to(device), c.point_mask.to(device)
        c.grasps, c.grasp_mask = c.grasps.to(device), c.grasp_mask.to(device)


# ---------------------------------------------------------------------- export from a LeRobot dataset


def _context_key(arrays: tuple[np.ndarray, ...]) -> bytes:
    digest = hashlib.sha1()
    for a in arrays:
        digest.update(np.ascontiguousarray(a).tobytes())
    return digest.digest()


def from_lerobot_dataset(root: str | Path, history_steps: int = features.HISTORY_STEPS,
                         num_points: int | None = None, max_grasps: int | None = None) -> CompactCache:
    """Read a LeRobot dataset written by ``rtv3 generate`` / ``rtv3 dagger`` / the merge script.

    Raises ``ValueError`` naming the problem when a feature is missing, the scene context changes
    within an episode, or a stored ``observation.state_history`` differs from the rebuilt one.
    """
    import pyarrow.parquet as pq

    root = Path(root)
    info_path = root / "meta" / "info.json"
    if not info_path.is_file():
        raise FileNotFoundError(f"no LeRobot dataset at {root} (missing meta/info.json)")
    info = json.loads(info_path.read_text())
    feats = info["features"]
    needed = [features.STATE, features.ACTION, features.POINT_CLOUD, features.POINT_CLOUD_MASK, features.GRASPS,
              features.GRASPS_MASK]
    missing = [k for k in needed if k not in feats]
    if missing:
        raise ValueError(f"dataset {root} lacks {missing}: the compact cache needs the separate context keys")
    n = features.rows_of(features.POINT_CLOUD, feats[features.POINT_CLOUD]["shape"])
    m = features.rows_of(features.GRASPS, feats[features.GRASPS]["shape"])
    for name, want, got in (("num_points", num_points, n), ("max_grasps", max_grasps, m)):
        if want is not None and want != got:
            raise ValueError(f"dataset {root} has {name}={got} but the config asks for {want}")
    has_history = features.STATE_HISTORY in feats
    has_target = features.TARGET_GRASP in feats
    paths = sorted((root / "data").rglob("*.parquet"))
    if not paths:
        raise FileNotFoundError(f"dataset {root} has no parquet files under data/")

    def flat(table, name: str, width: int, dtype=np.float32) -> np.ndarray:
        values = table.column(name).combine_chunks()
        while hasattr(values, "flatten"):  # list columns, nested for 2-D features
            values = values.flatten()
        return values.to_numpy(zero_copy_only=False).astype(dtype).reshape(-1, width)

    columns = ["index", "episode_index", *needed] + ([features.STATE_HISTORY] if has_history else []) + (
        [features.TARGET_GRASP] if has_target else [])
    parts: dict[str, list[np.ndarray]] = {k: [] for k in ("index", "episode", "states", "actions", "history")}
    contexts: dict[bytes, int] = {}
    context_rows: list[tuple[np.ndarray, ...]] = []
    episode_context: dict[int, int] = {}
    episode_target: dict[int, int] = {}
    for path in paths:
        table = pq.read_table(path, columns=columns)
        episode = table.column("episode_index").to_numpy().astype(np.int64)
        parts["index"].append(table.column("index").to_numpy().astype(np.int64))
        parts["episode"].append(episode)
        parts["states"].append(flat(table, features.STATE, features.STATE_DIM))
        parts["actions"].append(flat(table, features.ACTION, 6))
        if has_history:
            parts["history"].append(flat(table, features.STATE_HISTORY, history_steps * features.STATE_DIM))
        pc = flat(table, features.POINT_CLOUD, n * 6).reshape(-1, n, 6)
        pm = flat(table, features.POINT_CLOUD_MASK, n) > 0.5
        gr = flat(table, features.GRASPS, m * features.GRASP_DIM).reshape(-1, m, features.GRASP_DIM)
        gm = flat(table, features.GRASPS_MASK, m) > 0.5
        target = flat(table, features.TARGET_GRASP, 1, np.int64)[:, 0] if has_target else None
        first = np.flatnonzero(np.r_[True, episode[1:] != episode[:-1]])
        owner = np.repeat(first, np.diff(np.r_[first, episode.size]))
        for arr in (pc, pm, gr, gm):  # the scene is static within an episode
            if not np.array_equal(arr, arr[owner]):
                raise ValueError(f"{path}: the scene context changes within an episode; the compact cache stores "
                                 "one per episode")
        for i in first.tolist():
            e = int(episode[i])
            row = (pc[i], pm[i], gr[i], gm[i])
            key = _context_key(row)
            if key not in contexts:
                contexts[key] = len(context_rows)
                context_rows.append(row)
            if e in episode_context and episode_context[e] != contexts[key]:
                raise ValueError(f"episode {e} has two scene contexts")
            episode_context[e] = contexts[key]
            episode_target[e] = int(target[i]) if target is not None else -1
    index = np.concatenate(parts["index"])
    order = np.argsort(index, kind="stable")
    episode = np.concatenate(parts["episode"])[order]
    if np.any(np.diff(episode) < 0) or len(np.unique(episode)) != int(np.sum(np.r_[True, episode[1:] != episode[:-1]])):
        raise ValueError(f"dataset {root}: episodes are not contiguous in frame index order")
    states = np.concatenate(parts["states"])[order]
    ids, lengths = np.unique(episode, return_counts=True)
    starts = np.cumsum(lengths) - lengths
    pad = history_steps - 1
    if has_history:
        history = np.concatenate(parts["history"])[order].reshape(-1, history_steps, features.STATE_DIM)
        prefix = history[starts, :pad]
    else:
        prefix = np.repeat(states[starts][:, None], pad, 1)
    compact = CompactCache(
        torch.from_numpy(states), torch.from_numpy(np.concatenate(parts["actions"])[order]),
        torch.from_numpy(lengths.astype(np.int64)), torch.tensor([episode_context[int(e)] for e in ids]),
        torch.tensor([episode_target[int(e)] for e in ids], dtype=torch.long), torch.from_numpy(prefix.copy()),
        *(torch.from_numpy(np.stack([row[i] for row in context_rows])) for i in range(4)),
    )
    if has_history:  # the rebuilt history must be the stored one, frame by frame
        windowed = compact.windows()
        for lo in range(0, compact.num_frames, 65536):
            frames = torch.arange(lo, min(lo + 65536, compact.num_frames))
            rebuilt = windowed.cache.state_windows(windowed.frame_rows[frames], history_steps).numpy()
            bad = np.flatnonzero(~np.isclose(rebuilt, history[lo:lo + len(frames)], atol=1e-6).all((1, 2)))
            if bad.size:
                raise ValueError(
                    f"dataset {root}: frame {int(index[order][lo + bad[0]])}'s stored '{features.STATE_HISTORY}' is "
                    f"not its episode's prefix followed by its states ({bad.size} such frames)")
    logging.info("compact cache of %s: %d episodes, %d frames, %d scene contexts, %.1f MiB", root,
                 compact.num_episodes, compact.num_frames, compact.point_cloud.shape[0], compact.nbytes() / 2**20)
    return compact


def fit_budget(compact: CompactCache, max_bytes: int, seed: int = 0) -> CompactCache:
    """``compact`` itself when its in-memory size is within ``max_bytes``; else a seeded random subset
    of whole episodes that is (the file, compressed, is smaller still)."""
    if compact.nbytes() <= max_bytes:
        return compact
    order = np.random.default_rng(seed).permutation(compact.num_episodes)
    lo, hi = 1, compact.num_episodes  # largest prefix of the permutation that fits
    while lo < hi:
        mid = (lo + hi + 1) // 2
        if compact.select_episodes(order[:mid]).nbytes() <= max_bytes:
            lo = mid
        else:
            hi = mid - 1
    subset = compact.select_episodes(order[:lo])
    if subset.nbytes() > max_bytes:
        raise ValueError(f"not even one episode fits in {max_bytes / 2**20:.1f} MiB")
    return subset
