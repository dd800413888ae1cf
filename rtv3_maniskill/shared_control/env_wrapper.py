"""Shared control in ``GraspClutter-v1``: the user's twist goes in, an assistance method drives the robot.

:class:`SharedControlEnv` wraps one CPU ``GraspClutter-v1`` env (``pd_ee_twist``). Its action is
the USER body twist ``(6,)`` ``[v (m/s), w (rad/s)]`` in the TCP frame, or ``None`` / zeros for
"no input". Inside, an :class:`AssistanceMethod` turns it into the ROBOT twist sent to the env
(gripper held open):

* ``"direct"`` (:class:`DirectAssistance`): the user's twist, norm-clipped (paper's "Direct");
* ``"ho"`` (:class:`HOAssistance`): Hindsight Optimization over one goal per valid grasp
  candidate (its pre-grasp and the pi-about-z twin, one goal group);
* ``"rtv3"`` (:class:`RTV3Assistance`): the RT-V3 :class:`SharedController` around a learned prior.

``info`` gains ``user_twist (6,)``, ``robot_twist (6,)``, ``assistance_mode`` (``"shared"``,
``"autonomous"`` or ``"user_only"``) and ``assistance`` (the method's diagnostics: for RT-V3
class weights, entropy bounds, OOD flag; for HO the goal belief).

:func:`run_episode` plays one episode with a simulated user aiming at the episode's target
pre-grasp and returns an :class:`EpisodeResult`.
"""

from __future__ import annotations

import math
import time
from dataclasses import dataclass, field
from pathlib import Path
from typing import Any, Protocol, runtime_checkable

import gymnasium as gym
import numpy as np
import torch

from rtv3_maniskill import se3
from rtv3_maniskill.evaluation.planning import trial_outcome
from rtv3_maniskill.features import observation_from_env
from rtv3_maniskill.shared_control.direct import DirectTeleoperation
from rtv3_maniskill.shared_control.hindsight_optimization import VARIANTS as HO_VARIANTS
from rtv3_maniskill.shared_control.hindsight_optimization import HindsightOptimization
from rtv3_maniskill.shared_control.shared_controller import SharedControlConfig, SharedController
from rtv3_maniskill.shared_control.twist_utils import as_twist
from rtv3_maniskill.tasks.grasp_clutter import PREGRASP_DISTANCE, GraspClutterEnv
from rtv3_maniskill.tasks.grasp_sampler import canonicalize_symmetric

ENV_ID = "GraspClutter-v1"
CONTROL_MODE = "pd_ee_twist"
GRIPPER_OPEN = 1.0
"""Normalised gripper action of ``pd_ee_twist`` that holds the fingers open (0.04 m)."""
METHOD_NAMES = ("direct", "ho", "rtv3")
DEFAULT_POLICY_PATH = Path(__file__).resolve().parents[1] / "checkpoints" / "rtv3_grasp_clutter"
"""The shipped RT-V3 checkpoint (``config.json`` + ``model.safetensors``)."""


# ----------------------------------------------------------------------------- methods


@runtime_checkable
class AssistanceMethod(Protocol):
    """Turns the user's twist into the robot's twist, one control step at a time.

    ``reset(env)`` is called after every env reset (``env`` = the unwrapped ``GraspClutter-v1``);
    ``act(env, obs, user_twist)`` gets the current env observation (``state_dict`` layout, batch 1)
    and the user twist ``(6,)`` float64 or None (no input) and returns the robot body twist
    ``(6,)`` (TCP frame). ``last_diagnostics`` describes the last ``act``.
    """

    name: str
    last_diagnostics: dict[str, Any]

    def reset(self, env: Any) -> None: ...

    def act(self, env: Any, obs: dict, user_twist: torch.Tensor | None) -> torch.Tensor: ...


def _tcp_pose(env: Any) -> torch.Tensor:
    """``(4, 4)`` float64 TCP pose (world) of the single sub-scene."""
    return env.tcp_pose_matrix[0].detach().cpu().double()


def controller_speed_limits(env: Any) -> tuple[float, float]:
    """The ``pd_ee_twist`` controller's norm limits (m/s, rad/s): twists beyond them are scaled there."""
    config = env.agent.controller.controllers["arm"].config
    return float(config.max_linear_speed), float(config.max_angular_speed)


class DirectAssistance:
    """Direct teleoperation: the user's twist, clipped to the controller's speed limits."""

    name = "direct"

    def __init__(self, max_linear_speed: float | None = None, max_angular_speed: float | None = None) -> None:
        self._limits = (max_linear_speed, max_angular_speed)
        self.teleop: DirectTeleoperation | None = None
        self.last_diagnostics: dict[str, Any] = {}

    def reset(self, env: Any) -> None:
        if self.teleop is None:
            lin, ang = controller_speed_limits(env)
            self.teleop = DirectTeleoperation(self._limits[0] or lin, self._limits[1] or ang)
        self.teleop.reset()
        self.last_diagnostics = {}

    def act(self, env: Any, obs: dict, user_twist: torch.Tensor | None) -> torch.Tensor:
        if self.teleop is None:
            raise RuntimeError("DirectAssistance.act before reset(env)")
        user = torch.zeros(6, dtype=torch.float64) if user_twist is None else user_twist
        self.last_diagnostics = {"mode": "user_only"}
        return self.teleop.step(_tcp_pose(env), user)


def pregrasp_goals(env: Any) -> tuple[torch.Tensor, torch.Tensor]:
    """HO goals of the loaded scene: every valid grasp's pre-grasp and its pi-about-z twin.

    Returns ``goals (2G, 4, 4)`` (world) and ``groups (2G,)``: the grasp index, shared by a
    pre-grasp and its twin (one goal with two target poses, NOTES.md HO).
    """
    mask = env.grasps_mask[0].detach().cpu() > 0.5
    index = torch.nonzero(mask).flatten()
    if len(index) == 0:
        raise ValueError("the scene has no valid grasp candidate: HO needs at least one goal")
    grasps = env.grasp_poses[0, index].detach().cpu().double()
    pre = se3.translate_along_z(grasps, -PREGRASP_DISTANCE)
    twins = se3.rotate_about_z(pre, math.pi)
    return torch.cat([pre, twins]), torch.cat([index, index])


class HOAssistance:
    """Hindsight Optimization over the scene's grasp candidates (goals rebuilt at every reset).

    Args:
        variant: ``"rtv3_authors"`` (the RT-V3 paper's baseline: translation-only cost,
            default) or ``"javdani2018"`` (original constants incl. rotation).
    """

    name = "ho"

    def __init__(self, variant: str = "rtv3_authors", max_linear_speed: float | None = None,
                 max_angular_speed: float | None = None) -> None:
        if variant not in HO_VARIANTS:
            raise ValueError(f"unknown HO variant {variant!r}; known: {', '.join(HO_VARIANTS)}")
        self.variant = variant
        self._limits = (max_linear_speed, max_angular_speed)
        self.ho: HindsightOptimization | None = None
        self._target_group = -1
        self.last_diagnostics: dict[str, Any] = {}

    def reset(self, env: Any) -> None:
        goals, groups = pregrasp_goals(env)
        lin, ang = controller_speed_limits(env)
        self.ho = HindsightOptimization(
            goals, self.variant, dt=1.0 / env.control_freq, target_groups=groups.tolist(),
            max_linear_speed=self._limits[0] or lin, max_angular_speed=self._limits[1] or ang,
        )
        self._target_group = int(env.target_grasp_index[0])
        self.last_diagnostics = {}

    def act(self, env: Any, obs: dict, user_twist: torch.Tensor | None) -> torch.Tensor:
        if self.ho is None:
            raise RuntimeError("HOAssistance.act before reset(env)")
        user = torch.zeros(6, dtype=torch.float64) if user_twist is None else user_twist
        twist = self.ho.step(_tcp_pose(env), user)
        belief = self.ho.belief
        target = torch.nonzero(self.ho.goal_ids == self._target_group).flatten()
        self.last_diagnostics = {
            "mode": "shared",
            "belief": belief.numpy().copy(),
            "goal_ids": self.ho.goal_ids.numpy().copy(),
            "most_likely_goal": int(self.ho.goal_ids[int(belief.argmax())]),
            "target_belief": float(belief[target[0]]) if len(target) else float("nan"),
            "assistance": self.ho.last_assistance.numpy().copy(),
        }
        return twist


class RTV3Assistance:
    """RT-V3 shared control (:class:`SharedController`) around an ``RTV3Policy`` prior.

    Args:
        policy: an ``RTV3Policy`` (or anything with ``predict_step0_mixture(obs, update_history)``,
            ``predict_action_chunk(obs, update_history)``, ``reset()`` and a ``config`` with
            ``num_points`` / ``max_grasps``).
        config: controller settings; the speed limits default to the env controller's.
    """

    name = "rtv3"

    def __init__(self, policy: Any, config: SharedControlConfig | None = None) -> None:
        self.policy = policy
        self._config = config
        self._prior = policy
        self.controller: SharedController | None = None
        self.last_diagnostics: dict[str, Any] = {}

    def reset(self, env: Any) -> None:
        cfg = getattr(self.policy, "config", None)
        if cfg is not None and hasattr(cfg, "num_points"):
            n, m = int(env.mesh_point_cloud.shape[1]), int(env.grasps.shape[1])
            if (n, m) != (int(cfg.num_points), int(cfg.max_grasps)):
                raise ValueError(
                    f"the env gives N={n} points and M={m} grasps but the policy expects "
                    f"N={cfg.num_points}, M={cfg.max_grasps}: make the env with num_points/max_grasps from the policy config"
                )
        if self.controller is None:
            config = self._config
            if config is None:
                lin, ang = controller_speed_limits(env)
                config = SharedControlConfig(max_linear_speed=lin, max_angular_speed=ang)
            self.controller = SharedController(self._prior, config)
        self.controller.reset()
        self.last_diagnostics = {}

    def act(self, env: Any, obs: dict, user_twist: torch.Tensor | None) -> torch.Tensor:
        if self.controller is None:
            raise RuntimeError("RTV3Assistance.act before reset(env)")
        observation = observation_from_env(obs)
        user = None if user_twist is None else user_twist[None]
        twist = self.controller.step(observation, user)[0].double()
        d = self.controller.last_diagnostics
        assert d is not None
        self.last_diagnostics = {
            "mode": d.modes[0],
            "class_weights": d.class_weights[0].numpy().copy(),
            "prior_class_weights": d.prior_class_weights[0].numpy().copy(),
            "trans_entropy_lower": float(d.trans_entropy_lower[0]),
            "trans_entropy_upper": float(d.trans_entropy_upper[0]),
            "rot_entropy_lower": float(d.rot_entropy_lower[0]),
            "rot_entropy_upper": float(d.rot_entropy_upper[0]),
            "ood": bool(d.ood[0]),
            "surface_distance": float(d.surface_distance[0]),
        }
        return twist


def load_rtv3_policy(path: str | Path | None = None):
    """Load an ``RTV3Policy`` checkpoint folder (``config.json`` + ``model.safetensors``) for CPU inference.

    Raises:
        FileNotFoundError: no checkpoint there (the message says how to get one).
    """
    folder = Path(path) if path is not None else DEFAULT_POLICY_PATH
    missing = [name for name in ("config.json", "model.safetensors") if not (folder / name).is_file()]
    if missing:
        where = "the shipped checkpoint" if path is None else "--policy.path"
        raise FileNotFoundError(
            f"no RT-V3 checkpoint at {folder} ({where}; missing {', '.join(missing)}). Train one with "
            f"`lerobot-train --policy.type=rtv3 ...` (see README) and pass its pretrained_model folder "
            f"with --policy.path DIR, or place it at {DEFAULT_POLICY_PATH}."
        )
    from rtv3_maniskill.policies.rtv3.modeling_rtv3 import RTV3Policy  # lerobot import: ~6 s

    policy = RTV3Policy.from_pretrained(str(folder))
    policy.config.device = "cpu"
    return policy.to("cpu").eval()


def make_method(name: str, policy: Any = None, ho_variant: str = "rtv3_authors",
                config: SharedControlConfig | None = None) -> AssistanceMethod:
    """Assistance method by name: ``"direct"``, ``"ho"`` or ``"rtv3"`` (needs ``policy``).

    Raises:
        ValueError: unknown name, or ``"rtv3"`` without a policy.
    """
    key = str(name).strip().lower().replace("-", "_")
    if key == "direct":
        return DirectAssistance()
    if key == "ho":
        return HOAssistance(ho_variant)
    if key in ("rtv3", "rt_v3"):
        if policy is None:
            raise ValueError("method 'rtv3' needs a policy (load one with load_rtv3_policy)")
        return RTV3Assistance(policy, config)
    raise ValueError(f"unknown assistance method {name!r}; known methods: {', '.join(METHOD_NAMES)}")


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
        make_kwargs: passed to ``gym.make`` (e.g. ``num_points``, ``render_mode``, ``scene_type``).

    Action: user twist ``(6,)`` (or ``(1, 6)``), or None / zeros = no input. Scenes: ``reset(seed=s)``
    loads the scene of seed ``s`` (rebuilt only when ``s`` differs from the loaded one); ``seed=None``
    draws a new scene.
    """

    def __init__(self, env: gym.Env | None = None, method: AssistanceMethod | None = None,
                 rendered_context: bool = False, **make_kwargs: Any) -> None:
        if env is None:
            kwargs = dict(obs_mode="state_dict", control_mode=CONTROL_MODE, reconfiguration_freq=0)
            kwargs.update(make_kwargs)
            env = gym.make(ENV_ID, **kwargs)
        elif make_kwargs:
            raise ValueError(f"pass either an env or make kwargs, not both (got {sorted(make_kwargs)})")
        super().__init__(env)
        base = env.unwrapped
        if not isinstance(base, GraspClutterEnv):
            raise ValueError(f"SharedControlEnv needs a {ENV_ID} env, got {type(base).__name__}")
        if base.control_mode != CONTROL_MODE:
            raise ValueError(f"SharedControlEnv needs control_mode={CONTROL_MODE!r}, got {base.control_mode!r}")
        if base.num_envs != 1:
            raise ValueError(f"SharedControlEnv drives one env, got num_envs={base.num_envs}")
        if base.obs_mode not in ("state_dict", "pointcloud"):
            raise ValueError(f"SharedControlEnv needs obs_mode 'state_dict' or 'pointcloud', got {base.obs_mode!r}")
        self.method: AssistanceMethod = method if method is not None else DirectAssistance()
        self.rendered_context = rendered_context and base.obs_mode == "state_dict"
        self.action_space = gym.spaces.Box(-np.inf, np.inf, shape=(6,), dtype=np.float32)
        self._scene_seed: int | None = None
        self._context: tuple[torch.Tensor, torch.Tensor] | None = None
        self._obs: dict | None = None

    @property
    def base(self) -> Any:
        """The unwrapped ``GraspClutterEnv``."""
        return self.env.unwrapped

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
        self.method.reset(self.base)
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
        user: torch.Tensor | None
        if action is None:
            user = None
        else:
            value = action[0] if getattr(action, "shape", None) is not None and tuple(action.shape) == (1, 6) else action
            user = as_twist(value, "user twist (the action of SharedControlEnv)")
            if float(user.norm()) == 0.0:
                user = None
        robot = torch.as_tensor(self.method.act(self.base, self._obs, user)).double().reshape(-1)
        if robot.shape != (6,) or not torch.isfinite(robot).all():
            raise FloatingPointError(f"assistance method {self.method.name!r} returned {robot.tolist()}, expected 6 finite numbers")
        command = torch.cat([robot.float(), torch.tensor([GRIPPER_OPEN])])[None]
        obs, reward, terminated, truncated, info = self.env.step(command)
        obs = self._with_context(obs)
        self._obs = obs
        diagnostics = dict(self.method.last_diagnostics)
        info["user_twist"] = torch.zeros(6, dtype=torch.float64) if user is None else user
        info["robot_twist"] = robot
        info["assistance_mode"] = diagnostics.get("mode", "")
        info["assistance"] = diagnostics
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
    """

    success: bool
    collision: bool
    steps: int
    trajectory: np.ndarray
    diagnostics: list[dict[str, Any]]
    frames: list[np.ndarray] = field(default_factory=list)
    final_distance: float = float("nan")
    wall_time: float = 0.0

    @property
    def outcome(self) -> str:
        """``"collision"`` (any contact, even if the pre-grasp was reached), else ``"success"`` or
        ``"timeout"``: the paper's exclusive outcomes (SR + CR + TOR = 100 %)."""
        return trial_outcome(collision=self.collision, success=self.success) or "timeout"

    @property
    def mode_counts(self) -> dict[str, int]:
        """Steps per assistance mode."""
        counts: dict[str, int] = {}
        for d in self.diagnostics:
            counts[d.get("mode", "")] = counts.get(d.get("mode", ""), 0) + 1
        return counts


def _frame(env: gym.Env) -> np.ndarray:
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
    _, info = env.reset(seed=seed, options=options)
    base = env.base
    user.reset(env.user_goal())
    poses = [_tcp_pose(base).numpy()]
    frames = [_frame(env)] if record_frames else []
    diagnostics: list[dict[str, Any]] = []
    success = bool(info["success"][0])
    collision = False
    steps = 0
    distance = float(info["pregrasp_distance"][0])
    while not success and steps < max_steps and not (stop_on_contact and collision):
        command = user(_tcp_pose(base))
        _, _, _, _, info = env.step(command)
        steps += 1
        success = bool(info["success"][0])
        hit = bool(info["collision"][0])
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
            frames.append(_frame(env))
    return EpisodeResult(
        success=success, collision=collision, steps=steps, trajectory=np.stack(poses), diagnostics=diagnostics,
        frames=frames, final_distance=distance, wall_time=time.perf_counter() - start,
    )
