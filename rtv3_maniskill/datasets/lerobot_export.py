"""Resumable export of demonstrations into a LeRobot v3 dataset.

Layout of an output folder ``DIR`` (the dataset root LeRobot loads):

* ``DIR/meta``, ``DIR/data``: the LeRobot dataset (written with LeRobot's own
  ``LeRobotDataset.create`` / ``add_frame`` / ``save_episode`` / ``finalize``);
* ``DIR/rtv3_staging/``: one ``.npz`` per finished episode, written atomically, and
  ``attempts.jsonl`` with one line per attempted (scene, grasp) and its outcome;
* ``DIR/rtv3_generation.json``: the generation settings, so a resumed run can refuse a
  folder that holds a different dataset.

Killing a run loses at most the episodes in progress: staging files appear only when
complete, and the LeRobot dataset is rebuilt from the staged episodes (in a temporary
folder, then moved in place) whenever a run finishes.
"""

from __future__ import annotations

import json
import os
import shutil
from pathlib import Path

import numpy as np

from rtv3_maniskill import features as F
from rtv3_maniskill.datasets.demonstrations import END_AT, HOLD_STEPS, Episode

STAGING = "rtv3_staging"
SETTINGS = "rtv3_generation.json"
ATTEMPTS = "attempts.jsonl"
REPO_ID = "local/rtv3_grasp_clutter"


def dataset_features(num_points: int, max_grasps: int) -> dict:
    """LeRobot feature spec of the RT-V3 dataset (see ``rtv3_maniskill.features``)."""
    state_names = (
        [f"ee_pos_{a}" for a in "xyz"]
        + [f"ee_quat_{a}" for a in "wxyz"]
        + [f"ee_twist_{a}" for a in ("vx", "vy", "vz", "wx", "wy", "wz")]
        + [f"q{i}" for i in range(1, 8)]
        + [f"dq{i}" for i in range(1, 8)]
    )
    return {
        F.STATE: {"dtype": "float32", "shape": (F.STATE_DIM,), "names": state_names},
        F.STATE_HISTORY: {"dtype": "float32", "shape": (F.HISTORY_STEPS, F.STATE_DIM), "names": ["step", "state"]},
        F.POINT_CLOUD: {"dtype": "float32", "shape": (num_points, 6), "names": ["point", "xyzrgb"]},
        F.POINT_CLOUD_MASK: {"dtype": "float32", "shape": (num_points,), "names": ["point"]},
        F.GRASPS: {"dtype": "float32", "shape": (max_grasps, F.GRASP_DIM), "names": ["grasp", "pos_quat_width_score"]},
        F.GRASPS_MASK: {"dtype": "float32", "shape": (max_grasps,), "names": ["grasp"]},
        F.ACTION: {"dtype": "float32", "shape": (6,), "names": ["vx", "vy", "vz", "wx", "wy", "wz"]},
        F.TARGET_GRASP: {"dtype": "int64", "shape": (1,), "names": None},
        "scene_seed": {"dtype": "int64", "shape": (1,), "names": None},
        "target_object": {"dtype": "int64", "shape": (1,), "names": None},
        "pregrasp_reached": {"dtype": "bool", "shape": (1,), "names": None},
    }


def state_histories(states: np.ndarray, steps: int = F.HISTORY_STEPS) -> np.ndarray:
    """``(S, 27)`` episode states -> ``(S, steps, 27)`` windows ending at each step, the first
    state repeated before the episode start (what LeRobot's windows and the policy queue do)."""
    padded = np.concatenate([np.repeat(states[:1], steps - 1, 0), states])
    return np.stack([padded[t : t + steps] for t in range(len(states))]).astype(np.float32)


def end_at_pregrasp(state: np.ndarray, action: np.ndarray, pregrasp_step: int, hold_steps: int = HOLD_STEPS) -> tuple[np.ndarray, np.ndarray]:
    """Cut a staged episode that goes on to the grasp at its pre-grasp and pad it with
    ``hold_steps`` copies of the pre-grasp state at rest (zero twist and joint velocities;
    NOTES.md: demonstrations are padded with copies of the final pose).

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
    at_rest[F.EE_TWIST] = 0.0
    at_rest[F.ARM_QVEL] = 0.0
    states = np.concatenate([state[: pregrasp_step + 1], np.repeat(at_rest[None], hold_steps, 0)])
    actions = np.concatenate([action[:pregrasp_step], np.zeros((hold_steps + 1, action.shape[1]), action.dtype)])
    return states.astype(np.float32), actions.astype(np.float32)


class StagingArea:
    """Finished episodes and attempt outcomes of a (possibly interrupted) generation run."""

    def __init__(self, root: Path):
        self.root = Path(root)
        self.dir = self.root / STAGING
        self.dir.mkdir(parents=True, exist_ok=True)
        self.attempts_file = self.dir / ATTEMPTS

    @staticmethod
    def key(scene_seed: int, grasp_index: int) -> str:
        return f"scene{scene_seed:08d}_grasp{grasp_index:03d}"

    def attempts(self) -> dict[str, dict]:
        """Outcome per attempted key; the last line wins; a torn last line is ignored."""
        out: dict[str, dict] = {}
        if self.attempts_file.exists():
            for line in self.attempts_file.read_text().splitlines():
                try:
                    record = json.loads(line)
                except json.JSONDecodeError:
                    continue
                out[record["key"]] = record
        # An episode counts as done only once its file exists.
        return {k: r for k, r in out.items() if r["outcome"] != "success" or (self.dir / f"{k}.npz").exists()}

    def save(self, episode: Episode) -> None:
        key = self.key(episode.scene_seed, episode.target_grasp_index)
        tmp = self.dir / f"{key}.tmp.npz"
        np.savez_compressed(
            tmp,
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

    def log_attempt(self, scene_seed: int, grasp_index: int, outcome: str, frames: int = 0) -> None:
        line = json.dumps(dict(key=self.key(scene_seed, grasp_index), scene=scene_seed, grasp=grasp_index, outcome=outcome, frames=frames))
        with open(self.attempts_file, "a") as f:
            f.write(line + "\n")
            f.flush()
            os.fsync(f.fileno())

    def episode_files(self) -> list[Path]:
        return sorted(p for p in self.dir.glob("scene*_grasp*.npz") if not p.name.endswith(".tmp.npz"))

    @staticmethod
    def load(path: Path) -> dict:
        with np.load(path) as data:
            out = {k: data[k] for k in data.files if k != "meta"}
            out["meta"] = json.loads(str(data["meta"]))
        return out


def check_or_write_settings(root: Path, settings: dict) -> None:
    """Refuse a folder that holds another dataset; record the settings of a new one."""
    root = Path(root)
    path = root / SETTINGS
    if path.exists():
        existing = json.loads(path.read_text())
        if existing != settings:
            diff = {k: (existing.get(k), settings.get(k)) for k in set(existing) | set(settings) if existing.get(k) != settings.get(k)}
            raise ValueError(
                f"{root} holds a dataset generated with other settings {diff} (existing, requested); "
                "use another --output folder or the same settings to resume"
            )
        return
    if (root / "meta").exists() or (root / "data").exists():
        raise ValueError(f"{root} already holds a dataset that rtv3 generate did not create; choose another --output folder")
    root.mkdir(parents=True, exist_ok=True)
    path.write_text(json.dumps(settings, indent=2))


def export_lerobot_dataset(root: Path, num_points: int, max_grasps: int, progress: bool = True, end_at: str = "pregrasp") -> int:
    """(Re)build the LeRobot dataset in ``root`` from the staged episodes; returns frames written.

    With ``end_at="pregrasp"`` episodes staged with the approach to the grasp (recorded with
    ``end_at="grasp"``) are cut at the pre-grasp (:func:`end_at_pregrasp`)."""
    if end_at not in END_AT:
        raise ValueError(f"end_at must be one of {END_AT}, got {end_at!r}")
    import datasets as hf_datasets
    from lerobot.datasets.lerobot_dataset import LeRobotDataset
    from tqdm import tqdm

    hf_datasets.disable_progress_bars()

    root = Path(root)
    staging = StagingArea(root)
    files = staging.episode_files()
    if not files:
        raise RuntimeError(f"no finished episodes in {staging.dir} to export")
    tmp_root = root / "rtv3_export_tmp"
    if tmp_root.exists():
        shutil.rmtree(tmp_root)
    dataset = LeRobotDataset.create(
        REPO_ID, fps=F.FPS, features=dataset_features(num_points, max_grasps), root=tmp_root, robot_type="panda", use_videos=False
    )
    frames = 0
    for path in tqdm(files, desc="export to LeRobot", disable=not progress, unit="episode"):
        ep = staging.load(path)
        meta = ep["meta"]
        if end_at == "pregrasp" and meta.get("info", {}).get("end_at", "grasp") == "grasp":
            ep["state"], ep["action"] = end_at_pregrasp(ep["state"], ep["action"], meta["pregrasp_step"])
        history = state_histories(ep["state"])
        for t in range(len(ep["state"])):
            dataset.add_frame(
                {
                    F.STATE: ep["state"][t],
                    F.STATE_HISTORY: history[t],
                    F.POINT_CLOUD: ep["point_cloud"],
                    F.POINT_CLOUD_MASK: ep["point_cloud_mask"],
                    F.GRASPS: ep["grasps"],
                    F.GRASPS_MASK: ep["grasps_mask"],
                    F.ACTION: ep["action"][t],
                    F.TARGET_GRASP: np.array([meta["target_grasp_index"]], dtype=np.int64),
                    "scene_seed": np.array([meta["scene_seed"]], dtype=np.int64),
                    "target_object": np.array([meta["target_object"]], dtype=np.int64),
                    "pregrasp_reached": np.array([t >= meta["pregrasp_step"]]),
                    "task": meta["task"],
                }
            )
            frames += 1
        dataset.save_episode()
    dataset.finalize()
    for name in ("meta", "data"):
        if (root / name).exists():
            shutil.rmtree(root / name)
        os.replace(tmp_root / name, root / name)
    shutil.rmtree(tmp_root, ignore_errors=True)
    return frames
