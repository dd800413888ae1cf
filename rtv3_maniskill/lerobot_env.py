"""``GraspClutter-v1`` for ``lerobot-eval``: EnvConfig ``rtv3_clutter`` and a numpy gym view.

``lerobot-eval`` keeps only a few observation keys of a gym env (``agent_pos`` ->
``observation.state``, ``environment_state`` -> ``observation.environment_state``, ...), so
this view hands over the 27-D state as ``agent_pos`` and the static scene as ``environment_state``:
by default the whole packed context (point cloud + grasp set, ``features.pack_context``), which RT-V3
reads; with ``environment_state="summary"`` the fixed-size scene summary the datasets store
(``features.scene_summary``), which stock LeRobot policies trained on them read. The action is the
6-D TCP body twist (the gripper stays open); ``info["is_success"]`` is the task's success:
reaching the episode's target pre-grasp. So by default (``context="target"``, the planning
benchmark's protocol) the policy is shown only that target among the candidates; with
``context="all"`` it sees every candidate and cannot know which one the success counts.

    lerobot-eval --policy.path=CKPT --env.type=rtv3_clutter --eval.n_episodes=10 --eval.batch_size=1
    lerobot-eval --policy.path=DIFFUSION_CKPT --env.type=rtv3_clutter --env.environment_state=summary ...
"""

from __future__ import annotations

from dataclasses import dataclass, field

import gymnasium as gym
import numpy as np
import torch
from lerobot.configs.types import FeatureType, PolicyFeature
from lerobot.envs.configs import EnvConfig

from rtv3_maniskill import ENV_ID, features  # the package registers GraspClutter-v1 with gymnasium

GYM_ID = "rtv3/GraspClutterLeRobot-v1"
ENVIRONMENT_STATES = ("packed", "summary")
"""What ``environment_state`` holds: the packed context (RT-V3) or the datasets' scene summary (stock policies)."""


class GraspClutterLeRobotEnv(gym.Env):
    """Single ``GraspClutter-v1`` env (CPU) with numpy observations for LeRobot."""

    metadata = {"render_modes": ["rgb_array"], "render_fps": features.FPS}

    def __init__(self, render_mode: str | None = "rgb_array", max_episode_steps: int = 150, context: str = "target",
                 environment_state: str = "packed", **task_kwargs):
        if context not in features.CONTEXT_MODES:
            raise ValueError(f"unknown context {context!r}; expected one of {features.CONTEXT_MODES}")
        if environment_state not in ENVIRONMENT_STATES:
            raise ValueError(f"unknown environment_state {environment_state!r}; expected one of {ENVIRONMENT_STATES}")
        self.context, self.environment_state = context, environment_state

        self.render_mode = render_mode
        self._env = gym.make(
            ENV_ID,
            obs_mode="state_dict",
            control_mode="pd_ee_twist",
            render_mode=render_mode,
            max_episode_steps=max_episode_steps,
            **task_kwargs,
        )
        base = self._env.unwrapped
        self.num_points, self.max_grasps = base.num_points, base.max_grasps
        self._max_episode_steps = max_episode_steps
        context_dim = environment_state_dim(environment_state, self.num_points, self.max_grasps)
        self.observation_space = gym.spaces.Dict(
            {
                "agent_pos": gym.spaces.Box(-np.inf, np.inf, (features.STATE_DIM,), np.float32),
                "environment_state": gym.spaces.Box(-np.inf, np.inf, (context_dim,), np.float32),
            }
        )
        limit = np.array([0.3] * 3 + [1.2] * 3, dtype=np.float32)
        self.action_space = gym.spaces.Box(-limit, limit, dtype=np.float32)

    def _convert(self, obs: dict) -> dict[str, np.ndarray]:
        inputs = features.observation_from_env(obs)
        target = int(self._env.unwrapped.target_grasp_index[0])
        grasps_mask = features.context_mask(inputs[features.GRASPS_MASK], target, self.context)
        scene = features.pack_context if self.environment_state == "packed" else features.scene_summary
        state = scene(inputs[features.POINT_CLOUD], inputs[features.POINT_CLOUD_MASK], inputs[features.GRASPS],
                      grasps_mask)
        return {"agent_pos": inputs[features.STATE][0].cpu().numpy(), "environment_state": state[0].cpu().numpy()}

    @staticmethod
    def _info(info: dict) -> dict:
        return {
            "is_success": bool(info["success"][0]),
            "collision": bool(info["collision"][0]),
            "pregrasp_distance": float(info["pregrasp_distance"][0]),
        }

    def reset(self, *, seed: int | None = None, options: dict | None = None):
        super().reset(seed=seed)
        obs, info = self._env.reset(seed=seed, options=options)
        return self._convert(obs), self._info(info)

    def step(self, action):
        action = np.asarray(action, dtype=np.float32).reshape(-1)
        if action.shape != (6,):
            raise ValueError(f"action must be a (6,) TCP body twist [v, w], got shape {action.shape}")
        full = torch.from_numpy(np.concatenate([action, [0.04]]).astype(np.float32))[None]
        obs, reward, terminated, truncated, info = self._env.step(full)
        out_info = self._info(info)
        return (self._convert(obs), float(reward[0]), bool(terminated[0]) or out_info["is_success"],
                bool(truncated[0]), out_info)

    def render(self):
        return self._env.render()[0].cpu().numpy()

    def close(self):
        self._env.close()


def environment_state_dim(environment_state: str, num_points: int, max_grasps: int) -> int:
    """Length of ``environment_state`` for :data:`ENVIRONMENT_STATES` ``environment_state``."""
    if environment_state == "packed":
        return features.environment_state_dim(num_points, max_grasps)
    return features.scene_summary_dim(max_grasps)


if GYM_ID not in gym.registry:
    gym.register(id=GYM_ID, entry_point=GraspClutterLeRobotEnv, max_episode_steps=150)


@EnvConfig.register_subclass("rtv3_clutter")
@dataclass
class RTV3ClutterEnvConfig(EnvConfig):
    """``--env.type=rtv3_clutter``: ``GraspClutter-v1`` with state + packed scene context."""

    task: str | None = "GraspClutter-v1"
    fps: int = features.FPS
    episode_length: int = 150
    scene_type: str = "mixed"
    object_source: str = "procedural"
    num_points: int = 512
    """Must equal the policy's ``num_points`` (the shipped checkpoint and `rtv3 generate` use 512)."""
    max_grasps: int = features.DEFAULT_MAX_GRASPS
    context: str = "target"
    """Grasp candidates the policy sees: ``"target"`` (the episode's target, whose pre-grasp the success
    counts) or ``"all"``."""
    environment_state: str = "packed"
    """``"packed"``: the whole point cloud and grasp set (RT-V3); ``"summary"``: the datasets' scene summary
    (``features.scene_summary``), for policies trained with ``--policy.type=diffusion`` or ``act``."""
    features: dict[str, PolicyFeature] = field(default_factory=dict)
    features_map: dict[str, str] = field(
        default_factory=lambda: {
            features.ACTION: features.ACTION,
            "agent_pos": features.STATE,
            "environment_state": "observation.environment_state",
        }
    )

    def __post_init__(self):
        if self.context not in features.CONTEXT_MODES:
            raise ValueError(f"--env.context {self.context!r}: expected one of {features.CONTEXT_MODES}")
        if self.environment_state not in ENVIRONMENT_STATES:
            raise ValueError(f"--env.environment_state {self.environment_state!r}: expected one of "
                             f"{ENVIRONMENT_STATES}")
        self.features = {
            features.ACTION: PolicyFeature(type=FeatureType.ACTION, shape=(6,)),
            "agent_pos": PolicyFeature(type=FeatureType.STATE, shape=(features.STATE_DIM,)),
            "environment_state": PolicyFeature(
                type=FeatureType.ENV,
                shape=(environment_state_dim(self.environment_state, self.num_points, self.max_grasps),),
            ),
        }

    @property
    def package_name(self) -> str:
        return "rtv3_maniskill.lerobot_env"

    @property
    def gym_id(self) -> str:
        return GYM_ID

    @property
    def gym_kwargs(self) -> dict:
        return dict(
            max_episode_steps=self.episode_length,
            scene_type=self.scene_type,
            object_source=self.object_source,
            num_points=self.num_points,
            max_grasps=self.max_grasps,
            context=self.context,
            environment_state=self.environment_state,
        )
