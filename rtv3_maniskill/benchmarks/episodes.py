"""Shared control in ``GraspClutter-v1``: the user's twist goes in, an assistance method drives the robot.

:class:`SharedControlEnv` wraps one CPU ``GraspClutter-v1`` env (``pd_ee_twist``). Its action is
the USER body twist ``(6,)`` ``[v (m/s), w (rad/s)]`` in the TCP frame, or ``None`` / zeros for
"no input". Inside, an assistance method of :mod:`rtv3_maniskill.shared_control` (Direct, HO or
the RT-V3 :class:`SharedController`, built by name with
:func:`rtv3_maniskill.shared_control.methods.make_method`) turns it into the ROBOT twist sent
to the env (gripper held open).

``info`` gains ``user_twist (6,)``, ``robot_twist (6,)``, ``assistance_mode`` (``"shared"``,
``"autonomous"`` or ``"user_only"``) and ``assistance`` (the method's ``describe()``: for RT-V3
class weights, entropy bounds, OOD flag; for HO the goal belief and the target's share of it).

:func:`run_episode` plays one episode with a simulated user aiming at the episode's target
pre-grasp and returns an :class:`EpisodeResult`.
"""

from __future__ import annotations

import time
from dataclasses import dataclass, field
from typing import Any

import gymnasium as gym
import numpy as np
import torch

from rtv3_maniskill import ENV_ID, features
from rtv3_maniskill.benchmarks.outcomes import describe_contact, trial_outcome
from rtv3_maniskill.robot.neo_qp import NeoSafetyFilter
from rtv3_maniskill.robot.twist_controller import attach_safety_filters, target_object_index
from rtv3_maniskill.shared_control.assistance import AssistanceMethod
from rtv3_maniskill.shared_control.direct import DirectTeleoperation
from rtv3_maniskill.shared_control.shared_controller import SharedController
from rtv3_maniskill.tasks.grasp_clutter import GraspClutterEnv
from rtv3_maniskill.tasks.grasp_sampler import canonicalize_symmetric

CONTROL_MODE = "pd_ee_twist"
QP_CONTROL_MODE = "pd_ee_twist_qp"
SAFETY_FILTERS = (None, "neoss")


def _tcp_pose(env: Any) -> torch.Tensor:
    """``(4, 4)`` float64 TCP pose (world) of the single sub-scene."""
    return env.tcp_pose_matrix[0].detach().cpu().double()


# ----------------------------------------------------------------------------- the controller and the policy


def controller_speed_limits(env: Any) -> tuple[float, float]:
    """The ``pd_ee_twist`` controller's norm limits (m/s, rad/s): twists beyond them are scaled there."""
    config = env.agent.controller.controllers["arm"].config
    return float(config.max_linear_speed), float(config.max_angular_speed)


def check_policy_fits_env(policy: Any, env: Any) -> None:
    """Raise ``ValueError`` when the env's cloud or grasp set has another size than the policy's inputs."""
    cfg = getattr(policy, "config", None)
    if cfg is None or not hasattr(cfg, "num_points"):
        return
    n, m = int(env.mesh_point_cloud.shape[1]), int(env.grasps.shape[1])
    if (n, m) != (int(cfg.num_points), int(cfg.max_grasps)):
        raise ValueError(
            f"the env gives N={n} points and M={m} grasps but the policy expects N={cfg.num_points}, "
            f"M={cfg.max_grasps}: make the env with num_points/max_grasps from the policy config")


# ----------------------------------------------------------------------------- the wrapper


class SharedControlEnv(gym.Wrapper):
    """``GraspClutter-v1`` whose action is the user's twist; ``method`` decides the robot's twist.

    Args:
        env: a ``GraspClutter-v1`` env (one env, CPU, ``pd_ee_twist``, ``state_dict`` or ``pointcloud``
            obs); None makes one from ``make_kwargs`` (``reconfiguration_freq=0``: the wrapper
            reconfigures itself when the scene seed changes).
        method: the :class:`AssistanceMethod` (settable later via ``.method``); None = direct.
        rendered_context: in ``state_dict`` mode, replace the mesh-sampled cloud by a depth-camera
            cloud rendered once per scene (as ``rtv3 generate --context rendered`` stores it).
        safety_filter: ``"neoss"`` puts the NEO collision damper (:class:`~rtv3_maniskill.robot.neo_qp.
            NeoSafetyFilter`, the paper's "w. NeoSS") in front of the method: the robot's twist is
            tracked by the QP controller ``pd_ee_twist_qp``, whose damper keeps the links and hand out
            of the table and objects (the fingers may touch the target); None = no filter.
        make_kwargs: passed to ``gym.make`` (e.g. ``num_points``, ``render_mode``, ``scene_type``).

    Action: user twist ``(6,)`` (or ``(1, 6)``), or None / zeros = no input. Scenes: ``reset(seed=s)``
    loads the scene of seed ``s`` (rebuilt only when ``s`` differs from the loaded one); ``seed=None``
    draws a new scene.
    """

    def __init__(self, env: gym.Env | None = None, method: AssistanceMethod | None = None,
                 rendered_context: bool = False, safety_filter: str | None = None, **make_kwargs: Any) -> None:
        if safety_filter not in SAFETY_FILTERS:
            raise ValueError(f"unknown safety filter {safety_filter!r}; known: {', '.join(map(str, SAFETY_FILTERS))}")
        if env is None:
            mode = QP_CONTROL_MODE if safety_filter else CONTROL_MODE
            kwargs = dict(obs_mode="state_dict", control_mode=mode, reconfiguration_freq=0)
            kwargs.update(make_kwargs)
            env = gym.make(ENV_ID, **kwargs)
        elif make_kwargs:
            raise ValueError(f"pass either an env or make kwargs, not both (got {sorted(make_kwargs)})")
        super().__init__(env)
        base = env.unwrapped
        if not isinstance(base, GraspClutterEnv):
            raise ValueError(f"SharedControlEnv needs a {ENV_ID} env, got {type(base).__name__}")
        wanted = QP_CONTROL_MODE if safety_filter else CONTROL_MODE
        if base.control_mode not in (CONTROL_MODE, QP_CONTROL_MODE) or (safety_filter and base.control_mode != wanted):
            raise ValueError(f"SharedControlEnv{' with a safety filter' if safety_filter else ''} needs "
                             f"control_mode={wanted!r}, got {base.control_mode!r}")
        if base.num_envs != 1:
            raise ValueError(f"SharedControlEnv drives one env, got num_envs={base.num_envs}")
        if base.obs_mode not in ("state_dict", "pointcloud"):
            raise ValueError(f"SharedControlEnv needs obs_mode 'state_dict' or 'pointcloud', got {base.obs_mode!r}")
        self.method: AssistanceMethod = method if method is not None else DirectTeleoperation(
            *controller_speed_limits(base))
        self.rendered_context = rendered_context and base.obs_mode == "state_dict"
        self.action_space = gym.spaces.Box(-np.inf, np.inf, shape=(6,), dtype=np.float32)
        self._scene_seed: int | None = None
        self._context: tuple[torch.Tensor, torch.Tensor] | None = None
        self._obs: dict | None = None
        self.safety_filter = safety_filter
        self._filter = None
        if safety_filter == "neoss":
            self._filter = NeoSafetyFilter()
        self.gripper = features.GRIPPER_OPEN
        """Normalised gripper action sent with every step (1 = open, -1 = closed); stays open unless set."""

    @property
    def qp_infeasible_steps(self) -> int:
        """Steps the safety filter stopped the arm because its QP had no solution (0 without a filter)."""
        return 0 if self._filter is None else int(self._filter.infeasible_count)

    @property
    def base(self) -> Any:
        """The unwrapped ``GraspClutterEnv``."""
        return self.env.unwrapped

    @property
    def rendered_point_cloud(self) -> tuple[torch.Tensor, torch.Tensor] | None:
        """The loaded scene's depth-camera cloud ``(1, N, 6)`` and mask ``(1, N)`` that replaces the
        observation's (``rendered_context``), or None."""
        return self._context

    def _with_context(self, obs: dict) -> dict:
        if self._context is not None:
            extra = dict(obs["extra"])
            extra["point_cloud"], extra["point_cloud_mask"] = self._context[0].clone(), self._context[1].clone()
            obs = {**obs, "extra": extra}
        return obs

    def reset(self, *, seed: int | None = None, options: dict | None = None):
        options = dict(options or {})
        reload = seed is None or seed != self._scene_seed or bool(options.get("reconfigure", False))
        options["reconfigure"] = reload
        obs, info = self.env.reset(seed=seed, options=options)
        if reload:
            self._scene_seed = seed
            self._context = self.base.capture_point_cloud() if self.rendered_context else None
        obs = self._with_context(obs)
        self._obs = obs
        if self._filter is not None:  # a reset rebuilds the controllers: attach again every time
            self._filter.reset(self.base.layouts[0], target_object=target_object_index(self.env))
            attach_safety_filters(self.env, [self._filter])
        if isinstance(self.method, SharedController):
            check_policy_fits_env(self.method.policy, self.base)
        self.method.reset()
        return obs, info

    def user_goal(self) -> torch.Tensor:
        """``(4, 4)`` float64 the episode's target pre-grasp (world), as the twin of the pair
        {pre-grasp, pre-grasp rotated pi about z} closer to the current TCP orientation (a person
        would not turn the hand half a turn for the same parallel-jaw grasp)."""
        target = self.base.target_pregrasp_pose[0].detach().cpu().double().numpy()
        return torch.from_numpy(canonicalize_symmetric(target[None], _tcp_pose(self.base).numpy())[0])

    def step(self, action: Any):
        if self._obs is None:
            raise RuntimeError("call reset() before step()")
        observation = features.observation_from_env(self._obs)
        user: torch.Tensor | None = None
        if action is not None:  # checked once, by the method; zeros = no input
            user = torch.as_tensor(np.asarray(action) if not isinstance(action, torch.Tensor) else action)
            user = user.reshape(1, -1) if user.ndim == 1 else user
            if tuple(user.shape) == (1, 6) and user.is_floating_point() and float(user.abs().sum()) == 0.0:
                user = None
        robot = self.method.step(observation, user)[0].double()
        command = torch.cat([robot.float(), torch.tensor([float(self.gripper)])])[None]
        obs, reward, terminated, truncated, info = self.env.step(command)
        obs = self._with_context(obs)
        self._obs = obs
        diagnostics = self.method.describe(0)
        if "belief" in diagnostics:  # HO: the target's share of the belief
            target = np.flatnonzero(diagnostics["goal_ids"] == int(self.base.target_grasp_index[0]))
            diagnostics["target_belief"] = float(diagnostics["belief"][target[0]]) if len(target) else float("nan")
        info["user_twist"] = torch.zeros(6, dtype=torch.float64) if user is None else user[0].double()
        info["robot_twist"] = robot
        info["assistance_mode"] = diagnostics.get("mode", "")
        info["assistance"] = diagnostics
        return obs, reward, terminated, truncated, info

    def step_scripted(self, robot_twist: Any, mode: str = "scripted", user_twist: Any = None):
        """One step with ``robot_twist`` (6,) (TCP body frame) sent as it is, bypassing the method (a
        scripted grasp motion, or the user alone while holding an object); gripper :attr:`gripper`.
        ``info`` as in :meth:`step`, with ``assistance_mode = mode`` and ``assistance = {"mode": mode}``."""
        if self._obs is None:
            raise RuntimeError("call reset() before step_scripted()")
        robot = torch.as_tensor(np.asarray(robot_twist), dtype=torch.float64).reshape(-1)
        if robot.shape != (6,) or not torch.isfinite(robot).all():
            raise ValueError(f"robot_twist must be 6 finite numbers, got {robot.tolist()}")
        command = torch.cat([robot.float(), torch.tensor([float(self.gripper)])])[None]
        obs, reward, terminated, truncated, info = self.env.step(command)
        obs = self._with_context(obs)
        self._obs = obs
        user = torch.zeros(6, dtype=torch.float64) if user_twist is None else torch.as_tensor(
            np.asarray(user_twist), dtype=torch.float64).reshape(6)
        info.update(user_twist=user, robot_twist=robot, assistance_mode=mode, assistance={"mode": mode})
        return obs, reward, terminated, truncated, info


# ----------------------------------------------------------------------------- episodes


@dataclass
class EpisodeResult:
    """One simulated-user episode.

    Attributes:
        success: the env's ``info["success"]`` was reached (pre-grasp within the pose-distance threshold).
        collision: any robot contact at any step.
        steps: control steps taken (stops at success, at ``max_steps`` or, with ``stop_on_contact``, at
            the first contact).
        trajectory: ``(steps + 1, 4, 4)`` TCP poses (world), the start included.
        diagnostics: per step the method's diagnostics plus ``user_twist``, ``robot_twist`` (6,),
            ``pregrasp_distance`` and ``collision``.
        frames: ``env.render()`` images ``(H, W, 3)`` uint8 (start + one per step) if recorded.
        final_distance: pose distance to the pre-grasp at the end.
        wall_time: seconds the episode took.
        qp_infeasible_steps: steps a safety filter stopped the arm (its QP had no solution).
        contact: what the robot touched at its first contact (``"table"``, ``"object"``, ``"self"``,
            "+"-joined when several; ``""`` without a contact).
    """

    success: bool
    collision: bool
    steps: int
    trajectory: np.ndarray
    diagnostics: list[dict[str, Any]]
    frames: list[np.ndarray] = field(default_factory=list)
    final_distance: float = float("nan")
    wall_time: float = 0.0
    qp_infeasible_steps: int = 0
    contact: str = ""

    @property
    def outcome(self) -> str:
        """``"collision"`` (any contact, even if the pre-grasp was reached), else ``"success"`` or
        ``"timeout"``: the paper's exclusive outcomes (SR + CR + TOR = 100 %)."""
        return trial_outcome(collision=self.collision, success=self.success) or "timeout"

    @property
    def twist_deviation(self) -> float:
        """Mean over the steps of ``||robot_twist - user_twist||`` (6-D, m/s and rad/s as numbers; 0 without steps)."""
        if not self.diagnostics:
            return 0.0
        return float(np.mean([np.linalg.norm(d["robot_twist"] - d["user_twist"]) for d in self.diagnostics]))

    @property
    def mode_counts(self) -> dict[str, int]:
        """Steps per assistance mode."""
        counts: dict[str, int] = {}
        for d in self.diagnostics:
            counts[d.get("mode", "")] = counts.get(d.get("mode", ""), 0) + 1
        return counts


def render_frame(env: gym.Env) -> np.ndarray:
    """``env.render()`` of a single env as ``(H, W, 3)`` uint8 numpy."""
    image = env.render()
    image = image.cpu().numpy() if isinstance(image, torch.Tensor) else np.asarray(image)
    return image[0] if image.ndim == 4 else image


def run_episode(env: SharedControlEnv, method: AssistanceMethod | None, user: Any, max_steps: int = 150,
                record_frames: bool = False, *, seed: int | None = None, options: dict | None = None,
                stop_on_contact: bool = False) -> EpisodeResult:
    """Reset ``env`` (scene ``seed``, ``options`` e.g. ``target_grasp_index``) and let ``user`` drive.

    The user (``rtv3_maniskill.shared_control.simulated_users``) is reset towards the target
    pre-grasp (:meth:`SharedControlEnv.user_goal`) and called with the TCP pose ``(4, 4)`` every
    step; ``method`` (None keeps ``env.method``) assists. Stops at success, after ``max_steps`` or,
    with ``stop_on_contact`` (the paper's protocol: a contact fails the trial), at the first robot
    contact.
    """
    if not isinstance(env, SharedControlEnv):
        raise TypeError(f"run_episode needs a SharedControlEnv, got {type(env).__name__}")
    if max_steps < 1:
        raise ValueError(f"max_steps must be >= 1, got {max_steps}")
    if not callable(user) or not callable(getattr(user, "reset", None)):
        raise TypeError(f"user must be a simulated user (make_user(name, seed)), got {type(user).__name__}")
    if method is not None:
        env.method = method
    start = time.perf_counter()
    infeasible_before = env.qp_infeasible_steps
    _, info = env.reset(seed=seed, options=options)
    base = env.base
    user.reset(env.user_goal())
    poses = [_tcp_pose(base).numpy()]
    frames = [render_frame(env)] if record_frames else []
    diagnostics: list[dict[str, Any]] = []
    success = bool(info["success"][0])
    collision = False
    contact = ""
    steps = 0
    distance = float(info["pregrasp_distance"][0])
    while not success and steps < max_steps and not (stop_on_contact and collision):
        command = user(_tcp_pose(base))
        _, _, _, _, info = env.step(command)
        steps += 1
        success = bool(info["success"][0])
        hit = bool(info["collision"][0])
        if hit and not collision:
            contact = describe_contact(base)
        collision = collision or hit
        distance = float(info["pregrasp_distance"][0])
        diagnostics.append({
            **info["assistance"],
            "user_twist": info["user_twist"].numpy().copy(),
            "robot_twist": info["robot_twist"].numpy().copy(),
            "pregrasp_distance": distance,
            "collision": hit,
        })
        poses.append(_tcp_pose(base).numpy())
        if record_frames:
            frames.append(render_frame(env))
    return EpisodeResult(
        success=success, collision=collision, steps=steps, trajectory=np.stack(poses), diagnostics=diagnostics,
        frames=frames, final_distance=distance, wall_time=time.perf_counter() - start,
        qp_infeasible_steps=env.qp_infeasible_steps - infeasible_before, contact=contact,
    )
