"""Resumable export of demonstrations into a LeRobot v3 dataset.

Layout of an output folder ``DIR`` (the dataset root LeRobot loads):

* ``DIR/meta``, ``DIR/data``: the LeRobot dataset (written with LeRobot's own
  ``LeRobotDataset.create`` / ``add_frame`` / ``save_episode`` / ``finalize``);
* ``DIR/rtv3_staging/``: one ``.npz`` per finished episode, written atomically, and
  ``attempts.csv`` (a ``rtv3_maniskill.records.RecordStore``) with one row per attempted
  (scene, grasp) and its outcome;
* ``DIR/rtv3_generation.json``: the generation settings, so a resumed run can refuse a
  folder that holds attempts made with other settings.

The 2-D features are stored flat (``features.STORED_FLAT``) so that LeRobot's dataset tools
(``lerobot-edit-dataset``: delete_episodes, split, merge, modify_tasks) can copy them. Note
that the CLI writes its output to ``--root/--new_repo_id``, inside this folder when
``--root`` is it, and a failed run leaves that folder half-made (LeRobot refuses to write
into it again until it is removed).

Killing a run loses at most the episodes in progress: staging files appear only when
complete, and the LeRobot dataset is rebuilt from the staged episodes (in a temporary
folder, then moved in place) whenever a run finishes.
"""

from __future__ import annotations

import json
import os
import shutil
import zipfile
import zlib
from dataclasses import replace
from pathlib import Path

import numpy as np
from tqdm import tqdm

from rtv3_maniskill import features
from rtv3_maniskill.datagen.demonstrations import END_AT, HOLD_STEPS, Episode
from rtv3_maniskill.datagen.episode_stats import fast_episode_writes
from rtv3_maniskill.records import RecordStore

STAGING = "rtv3_staging"
SETTINGS = "rtv3_generation.json"
ATTEMPTS = "attempts.csv"
ATTEMPT_FIELDS = ("key", "scene", "grasp", "outcome", "frames")
_EPISODE_ARRAYS = ("state", "action", "point_cloud", "point_cloud_mask", "grasps", "grasps_mask")
_OPTIONAL_ARRAYS = ("history_prefix",)
_EPISODE_META = ("target_grasp_index", "scene_seed", "object_names", "target_object", "task", "pregrasp_step", "info")


def dataset_features(num_points: int, max_grasps: int) -> dict:
    """LeRobot feature spec of the RT-V3 dataset (see ``rtv3_maniskill.features``)."""
    # The 2-D features are stored flat, row-major (features.STORED_FLAT: LeRobot's dataset
    # tools cannot copy 2-D columns); their names say the layout, and readers reshape them with
    # features.unflatten / unflatten_batch.
    flat = features.stored_shape
    steps = features.HISTORY_STEPS
    return {
        features.STATE: {"dtype": "float32", "shape": (features.STATE_DIM,), "names": list(features.STATE_NAMES)},
        features.STATE_HISTORY: {"dtype": "float32", "shape": flat(features.STATE_HISTORY, steps),
                                 "names": features.flat_names(features.STATE_HISTORY, steps)},
        features.POINT_CLOUD: {"dtype": "float32", "shape": flat(features.POINT_CLOUD, num_points),
                               "names": features.flat_names(features.POINT_CLOUD, num_points)},
        features.POINT_CLOUD_MASK: {"dtype": "float32", "shape": (num_points,), "names": ["point"]},
        features.GRASPS: {"dtype": "float32", "shape": flat(features.GRASPS, max_grasps),
                          "names": features.flat_names(features.GRASPS, max_grasps)},
        features.GRASPS_MASK: {"dtype": "float32", "shape": (max_grasps,), "names": ["grasp"]},
        features.ENV_STATE: {"dtype": "float32", "shape": (features.scene_summary_dim(max_grasps),),
                             "names": features.scene_summary_names(max_grasps)},
        features.ACTION: {"dtype": "float32", "shape": (6,), "names": ["vx", "vy", "vz", "wx", "wy", "wz"]},
        features.TARGET_GRASP: {"dtype": "int64", "shape": (1,), "names": None},
        "scene_seed": {"dtype": "int64", "shape": (1,), "names": None},
        "target_object": {"dtype": "int64", "shape": (1,), "names": None},
        "pregrasp_reached": {"dtype": "bool", "shape": (1,), "names": None},
    }


def context_frame(point_cloud: np.ndarray, point_cloud_mask: np.ndarray, grasps: np.ndarray,
                  grasps_mask: np.ndarray) -> dict[str, np.ndarray]:
    """A frame's scene features as the dataset stores them: the point cloud ``(N, 6)`` and grasps ``(M, 9)``
    flat, their masks, and the derived scene summary ``observation.environment_state`` (``features.scene_summary``)."""
    summary = features.scene_summary(point_cloud, point_cloud_mask, grasps, grasps_mask).numpy()
    return {
        features.POINT_CLOUD: np.asarray(point_cloud, dtype=np.float32).reshape(-1),
        features.POINT_CLOUD_MASK: np.asarray(point_cloud_mask, dtype=np.float32),
        features.GRASPS: np.asarray(grasps, dtype=np.float32).reshape(-1),
        features.GRASPS_MASK: np.asarray(grasps_mask, dtype=np.float32),
        features.ENV_STATE: summary,
    }


def state_histories(states: np.ndarray, steps: int = features.HISTORY_STEPS,
                    prefix: np.ndarray | None = None) -> np.ndarray:
    """``(S, 27)`` episode states -> ``(S, steps, 27)`` windows ending at each step, the first
    state repeated before the episode start (what LeRobot's windows and the policy queue do).
    ``prefix`` ``(P, 27)``: states visited before ``states[0]`` (``Episode.history_prefix``), which
    the windows of the first frames hold before the repeated first state."""
    before = np.zeros((0, states.shape[1]), np.float32) if prefix is None else np.asarray(prefix, np.float32)
    before = before[-(steps - 1):] if steps > 1 else before[:0]
    start = before[:1] if len(before) else states[:1]
    padded = np.concatenate([np.repeat(start, steps - 1 - len(before), 0), before, states])
    return np.stack([padded[t : t + steps] for t in range(len(states))]).astype(np.float32)


def end_at_pregrasp(state: np.ndarray, action: np.ndarray, pregrasp_step: int,
                    hold_steps: int = HOLD_STEPS) -> tuple[np.ndarray, np.ndarray]:
    """Cut a staged episode that goes on to the grasp at its pre-grasp and pad it with
    ``hold_steps`` copies of the pre-grasp state at rest (zero twist and joint velocities;
    docs/PAPER_DETAILS.md: demonstrations are padded with copies of the final pose).

    Args:
        state: ``(S, 27)`` staged states; action: ``(S, 6)`` realised twists.
        pregrasp_step: index of the first state at the pre-grasp.
    Returns:
        ``(pregrasp_step + 1 + hold_steps, 27)`` states and ``(..., 6)`` actions; the action
        leaving the pre-grasp and every padded action are zero.
    """
    if not 0 <= pregrasp_step < len(state):
        raise ValueError(f"pregrasp_step {pregrasp_step} outside an episode of {len(state)} steps")
    at_rest = state[pregrasp_step].copy()
    at_rest[features.EE_TWIST] = 0.0
    at_rest[features.ARM_QVEL] = 0.0
    states = np.concatenate([state[: pregrasp_step + 1], np.repeat(at_rest[None], hold_steps, 0)])
    actions = np.concatenate([action[:pregrasp_step], np.zeros((hold_steps + 1, action.shape[1]), action.dtype)])
    return states.astype(np.float32), actions.astype(np.float32)


class StagedEpisodeError(RuntimeError):
    """A staged episode file cannot be read (truncated or corrupt); the message names it."""


class StagedScene:
    """One scene's episodes and attempt outcomes, made by a scene worker and written by the run's
    process (:meth:`StagingArea.write`): the same calls as a :class:`StagingArea`, held in memory.
    (A one-process run writes straight into its :class:`StagingArea`, each target as it finishes.)"""

    def __init__(self) -> None:
        self.entries: list[tuple[Episode | None, int, int, str, int, str]] = []

    def save_success(self, episode: Episode, variant: str = "") -> None:
        """A finished episode and its ``success`` attempt."""
        self.entries.append((episode, episode.scene_seed, episode.target_grasp_index, "success", len(episode.state),
                             variant))

    def log_attempt(self, scene_seed: int, grasp_index: int, outcome: str, frames: int = 0,
                    variant: str = "") -> None:
        self.entries.append((None, scene_seed, grasp_index, outcome, frames, variant))


class StagingArea:
    """Finished episodes and attempt outcomes of a (possibly interrupted) generation run.

    The outcomes are a :class:`rtv3_maniskill.records.RecordStore` (``attempts.csv``, one row
    per attempted (scene, grasp), fsync'd, torn rows cut). Opened with ``settings`` (the
    generating process) it guards them: a folder that already holds attempts made with other
    settings is refused, while a folder whose earlier run failed before its first attempt
    (settings written, nothing recorded) is not. Workers open it without ``settings``.
    A staged episode counts only once its attempt is recorded: an ``.npz`` without a success
    row (a kill between the two writes) is re-attempted, and deleted when opened with settings.
    """

    def __init__(self, root: Path, settings: dict | None = None):
        self.root = Path(root)
        self.dir = self.root / STAGING
        self.attempts_file = self.dir / ATTEMPTS
        if settings is not None and not (self.root / SETTINGS).exists() and not self.dir.exists():
            if (self.root / "meta").exists() or (self.root / "data").exists():
                raise ValueError(f"{self.root} already holds a dataset that rtv3 generate did not create; "
                                 "choose another --output folder")
        self.dir.mkdir(parents=True, exist_ok=True)
        self._import_legacy_attempts()
        self.records = RecordStore(self.attempts_file, ATTEMPT_FIELDS, key=("key",), settings=settings,
                                   settings_path=self.root / SETTINGS)
        if settings is not None:
            recorded = self.attempts()
            for path in self.episode_files():
                if path.stem not in recorded:
                    path.unlink()

    def close(self) -> None:
        self.records.close()

    def __enter__(self) -> StagingArea:
        return self

    def __exit__(self, *exc) -> None:
        self.close()

    @staticmethod
    def key(scene_seed: int, grasp_index: int, variant: str = "") -> str:
        """``scene00000003_grasp007``, or with a ``variant`` (several episodes of one target, e.g. DAgger
        relabels) ``scene00000003_grasp007_VARIANT``."""
        base = f"scene{scene_seed:08d}_grasp{grasp_index:03d}"
        return f"{base}_{variant}" if variant else base

    @staticmethod
    def scene_prefix(scene_seed: int) -> str:
        """The start of every key of ``scene_seed``."""
        return StagingArea.key(scene_seed, 0).split("_")[0] + "_"

    def attempts(self) -> dict[str, dict]:
        """Outcome per attempted key (the last row wins), rows as ``dict(key, scene, grasp,
        outcome, frames)``. A success counts only while its episode file exists (delete a file to
        have its grasp attempted again)."""
        rows = RecordStore.read(self.attempts_file, ATTEMPT_FIELDS) if self.attempts_file.exists() else []
        out = {r["key"]: dict(r, scene=int(r["scene"]), grasp=int(r["grasp"]), frames=int(r["frames"])) for r in rows}
        return {k: r for k, r in out.items() if r["outcome"] != "success" or (self.dir / f"{k}.npz").exists()}

    def save(self, episode: Episode, variant: str = "") -> None:
        key = self.key(episode.scene_seed, episode.target_grasp_index, variant)
        tmp = self.dir / f"{key}.tmp.npz"
        optional = {k: getattr(episode, k) for k in _OPTIONAL_ARRAYS if getattr(episode, k) is not None}
        np.savez_compressed(
            tmp,
            **optional,
            state=episode.state,
            action=episode.action,
            point_cloud=episode.point_cloud,
            point_cloud_mask=episode.point_cloud_mask,
            grasps=episode.grasps,
            grasps_mask=episode.grasps_mask,
            meta=json.dumps(
                dict(
                    target_grasp_index=episode.target_grasp_index,
                    scene_seed=episode.scene_seed,
                    object_names=episode.object_names,
                    target_object=episode.target_object,
                    task=episode.task,
                    pregrasp_step=episode.pregrasp_step,
                    info=episode.info,
                )
            ),
        )
        os.replace(tmp, self.dir / f"{key}.npz")

    def log_attempt(self, scene_seed: int, grasp_index: int, outcome: str, frames: int = 0,
                    variant: str = "") -> None:
        self.records.append(dict(key=self.key(scene_seed, grasp_index, variant), scene=scene_seed,
                                 grasp=grasp_index, outcome=outcome, frames=frames))

    def save_success(self, episode: Episode, variant: str = "") -> None:
        """A finished episode, then its ``success`` attempt (as :meth:`StagedScene.save_success`)."""
        self.save(episode, variant=variant)
        self.log_attempt(episode.scene_seed, episode.target_grasp_index, "success", len(episode.state),
                         variant=variant)

    def write(self, staged: StagedScene) -> None:
        """Write what a scene worker staged (:class:`StagedScene`), in its order: each episode before
        its attempt row, so a kill in between leaves an episode that is attempted again."""
        for episode, scene_seed, grasp_index, outcome, frames, variant in staged.entries:
            if episode is not None:
                self.save(episode, variant=variant)
            self.log_attempt(scene_seed, grasp_index, outcome, frames, variant=variant)

    def episode_files(self) -> list[Path]:
        return sorted(p for p in self.dir.glob("scene*_grasp*.npz") if not p.name.endswith(".tmp.npz"))

    @staticmethod
    def load(path: Path) -> Episode:
        """The staged episode in ``path``.

        Raises:
            StagedEpisodeError: the file is truncated or corrupt (names it and what to do).
        """
        path = Path(path)
        try:
            with np.load(path) as data:
                arrays = {k: data[k] for k in _EPISODE_ARRAYS}
                arrays.update({k: data[k] for k in _OPTIONAL_ARRAYS if k in data.files})
                meta = json.loads(str(data["meta"]))
            return Episode(**arrays, **{k: meta[k] for k in _EPISODE_META})
        except (zipfile.BadZipFile, zlib.error, EOFError, OSError, KeyError, ValueError, TypeError) as err:
            raise StagedEpisodeError(
                f"the staged episode {path} cannot be read ({type(err).__name__}: {err}); it is truncated or "
                f"corrupt (a full disk or a copy cut short?). Delete it and rerun the same `rtv3 generate` "
                f"command: generation resumes and records that demonstration again"
            ) from err

    def _import_legacy_attempts(self) -> None:
        """Folders staged before the record store kept ``attempts.jsonl``: copy it over once."""
        legacy = self.dir / "attempts.jsonl"
        if not legacy.exists() or self.attempts_file.exists():
            return
        with RecordStore(self.attempts_file, ATTEMPT_FIELDS, key=("key",)) as store:
            for line in legacy.read_text().splitlines():
                try:
                    record = json.loads(line)
                except json.JSONDecodeError:
                    continue  # a torn last line
                store.append({k: record[k] for k in ATTEMPT_FIELDS})


def export_lerobot_dataset(root: Path, num_points: int, max_grasps: int, progress: bool = True,
                           end_at: str = "pregrasp") -> int:
    """(Re)build the LeRobot dataset in ``root`` from the staged episodes; returns frames written.

    With ``end_at="pregrasp"`` episodes staged with the approach to the grasp (recorded with
    ``end_at="grasp"``) are cut at the pre-grasp (:func:`end_at_pregrasp`)."""
    if end_at not in END_AT:
        raise ValueError(f"end_at must be one of {END_AT}, got {end_at!r}")
    # Lazy: LeRobot takes seconds to load, and the scene workers that stage episodes never export.
    import datasets as hf_datasets
    from lerobot.datasets.lerobot_dataset import LeRobotDataset

    hf_datasets.disable_progress_bars()

    root = Path(root)
    with StagingArea(root) as staging:
        files = staging.episode_files()
    if not files:
        raise RuntimeError(f"no finished episodes in {staging.dir} to export")
    tmp_root = root / "rtv3_export_tmp"
    if tmp_root.exists():
        shutil.rmtree(tmp_root)
    dataset = LeRobotDataset.create(
        features.REPO_ID, fps=features.FPS, features=dataset_features(num_points, max_grasps), root=tmp_root,
        robot_type="panda",
        use_videos=False,
    )
    with fast_episode_writes(dataset):
        frames = _add_episodes(dataset, staging, files, end_at, progress)
    dataset.finalize()
    for name in ("meta", "data"):
        if (root / name).exists():
            shutil.rmtree(root / name)
        os.replace(tmp_root / name, root / name)
    shutil.rmtree(tmp_root, ignore_errors=True)
    return frames


def _add_episodes(dataset, staging: StagingArea, files: list[Path], end_at: str, progress: bool) -> int:
    """Append the staged episodes ``files`` to ``dataset`` (one LeRobot episode each); returns frames."""
    frames = 0
    for path in tqdm(files, desc="export to LeRobot", disable=not progress, unit="episode"):
        ep = staging.load(path)
        if end_at == "pregrasp" and ep.info.get("end_at", "grasp") == "grasp":
            state, action = end_at_pregrasp(ep.state, ep.action, ep.pregrasp_step)
            ep = replace(ep, state=state, action=action)
        history = state_histories(ep.state, prefix=ep.history_prefix)
        scene = context_frame(ep.point_cloud, ep.point_cloud_mask, ep.grasps, ep.grasps_mask)
        for t in range(len(ep.state)):
            dataset.add_frame(
                {
                    features.STATE: ep.state[t],
                    features.STATE_HISTORY: history[t].reshape(-1),
                    **scene,
                    features.ACTION: ep.action[t],
                    features.TARGET_GRASP: np.array([ep.target_grasp_index], dtype=np.int64),
                    "scene_seed": np.array([ep.scene_seed], dtype=np.int64),
                    "target_object": np.array([ep.target_object], dtype=np.int64),
                    "pregrasp_reached": np.array([t >= ep.pregrasp_step]),
                    "task": ep.task,
                }
            )
            frames += 1
        dataset.save_episode()
    return frames
