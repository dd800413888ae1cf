"""Record interactive shared-control sessions as LeRobot v3 datasets (one episode per trial).

A session folder ``DIR`` is a LeRobot dataset root (``DIR/meta``, ``DIR/data``, written with
``LeRobotDataset.create`` / ``add_frame`` / ``save_episode`` / ``finalize``) with two files beside:
``DIR/sessions.csv`` (one row per trial: participant, method, scene, outcome, ...) and
``DIR/session.json`` (the session's settings).

Every frame holds the demonstrations' features (``lerobot_export.dataset_features``: state, state
history, point cloud, grasps, action = the TCP body twist realised over the step, so that
``lerobot-train --policy.type=rtv3`` accepts a session) and, per step:

* ``observation.user_twist (6,)``: the raw command of the input device, in its own frame;
* ``commanded_twist (6,)``: the twist the assistance method (or a scripted motion) sent;
* ``assist_mode (1,)`` int64: index into :data:`ASSIST_MODES`;
* ``class_weights (K,)``: RT-V3's class weights, zero-padded to K (HO: the goal belief; direct: zeros);
* ``button_events (4,)`` int64: 1 where a button was pressed this step (grasp, release, approach, lift);
* ``gripper (1,)``: the normalised gripper command (1 open, -1 closed);
* ``trial_outcome (1,)`` int64: index into :data:`OUTCOMES` (the whole episode has its trial's outcome).
"""

from __future__ import annotations

import json
import shutil
from pathlib import Path
from typing import Any

import numpy as np

from rtv3_maniskill import features
from rtv3_maniskill.datagen.lerobot_export import context_frame, dataset_features, state_histories
from rtv3_maniskill.features import REPO_ID
from rtv3_maniskill.records import RecordStore

ASSIST_MODES = ("none", "user_only", "shared", "autonomous", "scripted")
"""``assist_mode`` codes: the index of the mode name (``none``: no method output yet)."""
BUTTON_EVENTS = ("grasp", "release", "approach", "lift")
"""The paper's buttons A, B, Y, X in the order of ``button_events``."""
OUTCOMES = ("success", "timeout", "collision", "unmatched", "aborted")
"""Trial outcomes; the index is the ``trial_outcome`` code (``aborted``: the person quit the session)."""
USER_TWIST = "observation.user_twist"
SESSIONS_CSV = "sessions.csv"
SESSION_JSON = "session.json"
SESSION_FIELDS = ("trial", "episode_index", "participant", "method", "input", "scene_seed", "target_grasp_index",
                  "target_object", "task", "outcome", "steps", "duration_s", "contacts")
DEFAULT_NUM_CLASSES = 64


def assist_mode_code(mode: str) -> int:
    """Code of an assistance mode name (``""`` -> ``none``); raises ``ValueError`` on an unknown name."""
    name = mode or "none"
    if name not in ASSIST_MODES:
        raise ValueError(f"unknown assistance mode {mode!r}; known: {ASSIST_MODES}")
    return ASSIST_MODES.index(name)


def session_features(num_points: int, max_grasps: int, num_classes: int = DEFAULT_NUM_CLASSES) -> dict:
    """LeRobot feature spec of a session: the demonstrations' features plus the teleoperation ones."""
    spec = dataset_features(num_points, max_grasps)
    twist = ["vx", "vy", "vz", "wx", "wy", "wz"]
    spec.update({
        USER_TWIST: {"dtype": "float32", "shape": (6,), "names": twist},
        "commanded_twist": {"dtype": "float32", "shape": (6,), "names": twist},
        "assist_mode": {"dtype": "int64", "shape": (1,), "names": None},
        "class_weights": {"dtype": "float32", "shape": (num_classes,), "names": None},
        "button_events": {"dtype": "int64", "shape": (len(BUTTON_EVENTS),), "names": list(BUTTON_EVENTS)},
        "gripper": {"dtype": "float32", "shape": (1,), "names": None},
        "trial_outcome": {"dtype": "int64", "shape": (1,), "names": None},
    })
    return spec


class SessionRecorder:
    """Buffers one trial's frames and writes it as a LeRobot episode when the trial ends.

    Every finished trial is durable: its episode is written and the dataset finalized (parquet
    footers, episode metadata) before its ``sessions.csv`` row, so a session killed at any moment
    keeps every finished trial in a form ``LeRobotDataset`` loads, and ``resume=True`` continues it
    (the dataset is reopened as LeRobot resumes a recording: each later trial goes to new files).

    Args:
        root: the session folder; must not exist yet (LeRobot creates it), unless ``resume``.
        num_points, max_grasps: N and M of the env's cloud and grasp set.
        num_classes: K, the class-weight width (longer weight vectors are refused).
        settings: the session's settings, written to ``session.json`` (a resumed session must have the
            same; ``ValueError`` names the first that differs).
        resume: continue the session recorded in ``root``; :attr:`trials` is then the number of
            finished trials (a trial cut by the kill is recorded again).
    """

    def __init__(self, root: str | Path, num_points: int, max_grasps: int, num_classes: int = DEFAULT_NUM_CLASSES,
                 settings: dict[str, Any] | None = None, resume: bool = False) -> None:
        # Lazy, as LeRobot below: the study and the grasp actions import this module for its constants only.
        import datasets as hf_datasets

        self.root = Path(root)
        settings = json.loads(json.dumps(settings or {}, default=str))
        hf_datasets.disable_progress_bars()
        self.num_classes = num_classes
        if resume:
            self._check_resumable(settings)
            if not (self.root / "meta" / "episodes").is_dir():  # killed before its first trial ended: start again
                shutil.rmtree(self.root)
                resume = False
            else:
                self.dataset = self._open()
        if not resume:
            from lerobot.datasets.lerobot_dataset import LeRobotDataset  # loads LeRobot (seconds)

            if self.root.exists():
                raise FileExistsError(f"the session folder {self.root} already exists; record each session into a new "
                                      "one, or continue it with --resume")
            spec = session_features(num_points, max_grasps, num_classes)
            self.dataset = LeRobotDataset.create(REPO_ID, fps=features.FPS, features=spec, root=self.root,
                                                 robot_type="panda", use_videos=False)
            self.dataset.meta.metadata_buffer_size = 1  # each episode's metadata is written with it
            (self.root / SESSION_JSON).write_text(json.dumps(settings, indent=2))
        self.records = RecordStore(self.root / SESSIONS_CSV, SESSION_FIELDS, key=("trial",))
        self.trials = len(self.records.rows)
        self._frames: list[dict[str, Any]] = []
        self._trial: dict[str, Any] | None = None
        self._closed = False

    def start_trial(self, context: dict[str, np.ndarray], task: str, **meta: Any) -> None:
        """Begin a trial. ``context``: ``point_cloud (N, 6)``, ``point_cloud_mask (N,)``, ``grasps (M, 9)``,
        ``grasps_mask (M,)``; ``meta``: participant, method, input, scene_seed, target_grasp_index, target_object."""
        arrays = {k: np.asarray(v, dtype=np.float32) for k, v in context.items()}
        self._trial = dict(context=arrays, task=task, meta=meta)
        self._frames = []

    def add_step(self, state: np.ndarray, user_twist: np.ndarray, commanded_twist: np.ndarray, assist_mode: str,
                 class_weights: np.ndarray | None, buttons: np.ndarray, gripper: float, pregrasp_reached: bool) -> None:
        """One control step: ``state (27,)`` before the step and what happened during it."""
        if self._trial is None:
            raise RuntimeError("start_trial() before add_step()")
        weights = np.zeros(self.num_classes, dtype=np.float32)
        if class_weights is not None:
            w = np.asarray(class_weights, dtype=np.float32).reshape(-1)
            if len(w) > self.num_classes:
                raise ValueError(f"{len(w)} class weights do not fit the recorded width K={self.num_classes}")
            weights[: len(w)] = w
        self._frames.append(dict(
            state=np.asarray(state, dtype=np.float32).reshape(features.STATE_DIM),
            user=np.asarray(user_twist, dtype=np.float32).reshape(6),
            commanded=np.asarray(commanded_twist, dtype=np.float32).reshape(6),
            mode=assist_mode_code(assist_mode), weights=weights,
            buttons=np.asarray(buttons, dtype=np.int64).reshape(-1), gripper=float(gripper),
            reached=bool(pregrasp_reached),
        ))

    def end_trial(self, outcome: str, final_state: np.ndarray, duration_s: float, contacts: int) -> int:
        """Write the trial as one episode; ``final_state (27,)`` is the state after the last step (its
        realised twist is the last action). Returns the episode index."""
        if self._trial is None or not self._frames:
            raise RuntimeError("end_trial() needs a started trial with at least one step")
        if outcome not in OUTCOMES:
            raise ValueError(f"unknown outcome {outcome!r}; known: {OUTCOMES}")
        trial, frames = self._trial, self._frames
        states = np.stack([f["state"] for f in frames])
        after = np.concatenate([states[1:], np.asarray(final_state, dtype=np.float32).reshape(1, -1)])
        actions = after[:, features.EE_TWIST]  # body twist realised over each step
        history = state_histories(states)
        ctx, meta = trial["context"], trial["meta"]
        code = np.array([OUTCOMES.index(outcome)], dtype=np.int64)
        scene = context_frame(ctx["point_cloud"], ctx["point_cloud_mask"], ctx["grasps"], ctx["grasps_mask"])
        for t, f in enumerate(frames):
            self.dataset.add_frame({
                features.STATE: f["state"],
                features.STATE_HISTORY: history[t].reshape(-1),
                **scene,
                features.ACTION: actions[t],
                features.TARGET_GRASP: np.array([meta.get("target_grasp_index", -1)], dtype=np.int64),
                "scene_seed": np.array([meta.get("scene_seed", -1)], dtype=np.int64),
                "target_object": np.array([meta.get("target_object", -1)], dtype=np.int64),
                "pregrasp_reached": np.array([f["reached"]]),
                USER_TWIST: f["user"],
                "commanded_twist": f["commanded"],
                "assist_mode": np.array([f["mode"]], dtype=np.int64),
                "class_weights": f["weights"],
                "button_events": f["buttons"],
                "gripper": np.array([f["gripper"]], dtype=np.float32),
                "trial_outcome": code,
                "task": trial["task"],
            })
        self.dataset.save_episode()
        episode = self.dataset.meta.total_episodes - 1
        self.dataset.finalize()  # durable now: footers and the episode's metadata on disk
        self.dataset = self._open()  # the next trial resumes the recording in new files
        self.records.append(dict(trial=self.trials, episode_index=episode, task=trial["task"], outcome=outcome,
                                 steps=len(frames), duration_s=f"{duration_s:.2f}", contacts=contacts,
                                 **{k: meta.get(k, "") for k in SESSION_FIELDS[2:8]}))
        self.trials += 1
        self._trial, self._frames = None, []
        return episode

    def close(self) -> None:
        """Finalize the dataset (its parquet footers) and close ``sessions.csv``; idempotent."""
        if self._closed:
            return
        self._closed = True
        self.dataset.finalize()
        self.records.close()

    def _open(self) -> Any:
        """The recorded dataset, opened to record more episodes after its last one."""
        from lerobot.datasets.lerobot_dataset import LeRobotDataset  # loads LeRobot (seconds)

        dataset = LeRobotDataset(REPO_ID, root=self.root)
        dataset.meta.metadata_buffer_size = 1
        dataset.episode_buffer = dataset.create_episode_buffer()
        return dataset

    def _check_resumable(self, settings: dict[str, Any]) -> None:
        if not (self.root / SESSION_JSON).is_file() or not (self.root / "meta" / "info.json").is_file():
            raise FileNotFoundError(f"{self.root} holds no recorded session to resume (no {SESSION_JSON} and "
                                    "meta/info.json); start it without --resume")
        recorded = json.loads((self.root / SESSION_JSON).read_text())
        for key in sorted(set(recorded) | set(settings)):
            if recorded.get(key) != settings.get(key):
                raise ValueError(f"{self.root} was recorded with {key}={recorded.get(key)!r}, not "
                                 f"{settings.get(key)!r}: resume it with the same options")
        stored = json.loads((self.root / "meta" / "info.json").read_text())["features"]
        if features.ENV_STATE not in stored:
            raise ValueError(f"{self.root} was recorded before sessions stored '{features.ENV_STATE}': "
                             "record a new session (`rtv3 merge` converts the old one for training)")
        if not (self.root / "meta" / "episodes").is_dir() and (self.root / SESSIONS_CSV).is_file():
            if RecordStore.read(self.root / SESSIONS_CSV, SESSION_FIELDS):
                raise ValueError(f"{self.root}: sessions.csv lists trials but the dataset holds no episode")


__all__ = ["ASSIST_MODES", "BUTTON_EVENTS", "OUTCOMES", "SESSION_FIELDS", "SESSIONS_CSV", "SessionRecorder",
           "USER_TWIST", "assist_mode_code", "session_features"]
