"""The teleop window's frames, rendered in a process of their own so that the control loop keeps 20 Hz.

Rendering a frame of ``GraspClutter-v1`` costs about 34 ms on a CPU (lavapipe), a control step with
RT-V3 about 20 ms: in one loop they do not fit into 50 ms. :class:`RenderProcess` holds a second,
render-only copy of the scene (same make arguments, same scene seed, so the same layout) in a spawned
process. The control loop sends it the robot's joint positions and the objects' poses after each
step and never waits: the process renders the newest state it has when it is free, and the loop
shows a finished frame when there is one. The display therefore runs at the rate rendering allows,
on the other core, with a frame at most one render old.
"""

from __future__ import annotations

import multiprocessing as mp
import os
import time
from collections.abc import Callable
from typing import Any

import numpy as np

from rtv3_maniskill import ENV_ID

RENDER_NICENESS = 10
"""The render process yields the CPU to the control loop (``os.nice``)."""
START_TIMEOUT_S = 120.0
"""How long the first trial waits for the render process to start and send its first frame."""


def _serve(connection: Any, make_kwargs: dict[str, Any]) -> None:
    # Leave the control loop its core: one rasterizer thread (Mesa's lavapipe reads LP_NUM_THREADS
    # when SAPIEN creates its device) and a lower scheduling priority.
    os.environ.setdefault("LP_NUM_THREADS", "1")
    os.nice(RENDER_NICENESS)
    # Imported here, in the spawned render process only: the simulator loads after the settings above,
    # and the control process that imports this module pays nothing for them.
    import gymnasium as gym
    import torch

    torch.set_num_threads(1)
    env = gym.make(ENV_ID, obs_mode="state_dict", render_mode="rgb_array", reconfiguration_freq=0, **make_kwargs)
    base = env.unwrapped
    connection.send(("ready", None))
    try:
        while True:  # the client keeps at most one state in flight: every message is handled in order
            kind, payload = connection.recv()
            if kind == "close":
                break
            if kind == "scene":
                env.reset(seed=int(payload), options=dict(reconfigure=True))
                continue
            qpos, poses = payload
            base.agent.robot.set_qpos(torch.as_tensor(qpos, dtype=torch.float32)[None])
            for actor, pose in zip(base.objects[0], poses):
                actor.set_pose(_pose(pose))
            image = env.render()
            image = image.cpu().numpy() if hasattr(image, "cpu") else np.asarray(image)
            connection.send(("frame", np.ascontiguousarray(image[0] if image.ndim == 4 else image)))
    finally:
        env.close()


def _pose(raw: np.ndarray) -> Any:
    import sapien  # the render process's, loaded by its env (see _serve)

    return sapien.Pose(p=raw[:3].tolist(), q=raw[3:7].tolist())


class RenderProcess:
    """Frames of the scene ``make_kwargs`` describes, rendered in a spawned process.

    Args:
        make_kwargs: ``gym.make`` keyword arguments of the scene (scene type, objects, camera size, ...).
    """

    def __init__(self, make_kwargs: dict[str, Any]) -> None:
        context = mp.get_context("spawn")
        self._connection, child = context.Pipe()
        self._process = context.Process(target=_serve, args=(child, dict(make_kwargs)), daemon=True)
        self._process.start()  # it builds its env while the caller builds its own
        self._busy = False
        self._ready = False
        self._pending: Any = None

    def set_scene(self, scene_seed: int, idle: Callable[[], Any] | None = None) -> None:
        """Load the scene of ``scene_seed`` (as the control loop's env did); waits for the process to have
        started (the first time, calling ``idle`` every 0.1 s meanwhile) and for a frame in flight."""
        if not self._ready:
            if not self._wait(START_TIMEOUT_S, idle) or self._connection.recv()[0] != "ready":
                raise RuntimeError("the teleop render process did not start")
            self._ready = True
        self._drain()
        self._connection.send(("scene", int(scene_seed)))

    def first_frame(self, qpos: np.ndarray, object_poses: np.ndarray,
                    idle: Callable[[], Any] | None = None) -> np.ndarray:
        """Render this state of the newly set scene and wait for it (``idle`` every 0.1 s): the trial's first
        frame ``(H, W, 3)`` uint8, shown before the trial's clock starts."""
        self.show(qpos, object_poses)
        deadline = time.monotonic() + START_TIMEOUT_S
        while time.monotonic() < deadline:
            self._wait(deadline - time.monotonic(), idle)
            frame = self.frame()
            if frame is not None:
                return frame
        raise RuntimeError("the teleop render process sent no frame of the trial's scene")

    def _wait(self, timeout: float, idle: Callable[[], Any] | None) -> bool:
        """Whether a message came within ``timeout`` seconds, calling ``idle`` between 0.1 s polls."""
        deadline = time.monotonic() + timeout
        while not self._connection.poll(0.1):
            if idle is not None:
                idle()
            if time.monotonic() >= deadline:
                return False
        return True

    def show(self, qpos: np.ndarray, object_poses: np.ndarray) -> None:
        """Render this state when the process is free: ``qpos (9,)``, ``object_poses (n, 7)`` (p, q wxyz)."""
        state = (np.asarray(qpos, dtype=np.float32).reshape(-1), np.asarray(object_poses, dtype=np.float64))
        if self._busy:
            self._pending = state
        else:
            self._connection.send(("state", state))
            self._busy = True

    def frame(self) -> np.ndarray | None:
        """The newest finished frame ``(H, W, 3)`` uint8, or None when none finished since the last call."""
        newest = None
        while self._connection.poll():
            kind, payload = self._connection.recv()
            if kind == "frame":
                newest = payload
                self._busy = False
        if not self._busy and self._pending is not None:
            self._connection.send(("state", self._pending))
            self._pending, self._busy = None, True
        return newest

    def _drain(self) -> None:
        while self._busy:
            if self._connection.poll(5.0):
                kind, _ = self._connection.recv()
                self._busy = kind != "frame"
            else:
                break
        self._busy, self._pending = False, None

    def close(self) -> None:
        try:
            self._connection.send(("close", None))
        except (BrokenPipeError, OSError):
            pass
        self._process.join(timeout=10)
        if self._process.is_alive():
            self._process.terminate()


def scene_state(base: Any) -> tuple[np.ndarray, np.ndarray]:
    """The state :meth:`RenderProcess.show` takes from a ``GraspClutter-v1`` env: ``qpos (9,)``, object poses."""
    qpos = base.agent.robot.get_qpos()[0].detach().cpu().numpy()
    poses = np.stack([actor.pose.raw_pose[0].detach().cpu().numpy() for actor in base.objects[0]])
    return qpos, poses


__all__ = ["RenderProcess", "scene_state"]
