"""The diffusion copilot baseline: partial diffusion of the user's twist ("To the Noise and Back",
Yoneda et al., RSS 2023), with LeRobot's own ``DiffusionPolicy`` trained by ``lerobot-train``.

Each control step takes the user's body twist ``a_user``, holds it over the policy's action horizon,
normalises it with the policy's own statistics, noises it forward to a fraction ``gamma`` of the
diffusion schedule and runs the reverse (DDIM) steps from there, conditioned on the robot state and the
scene summary (``features.scene_summary``: every grasp candidate and the cloud's height map, never the
target)::

    x_k = sqrt(abar_k) a_user + sqrt(1 - abar_k) eps,   k = gamma K
    x_0 = reverse(x_k | state, scene),                   executed: x_0 at the current step

``gamma = 0`` returns the user's twist; ``gamma = 1`` starts from pure noise, so the user's twist is
ignored (the copilot alone, a reference). In between, the executed twist stays near the user's yet on
the demonstrations' manifold. The network, the noise scheduler and the normalisers are the checkpoint's
(``policy.diffusion.unet``, ``policy.diffusion.noise_scheduler``, the saved pre/post-processors).
"""

from __future__ import annotations

from collections import deque
from dataclasses import dataclass
from pathlib import Path
from typing import Any

import torch
from lerobot.policies.diffusion.modeling_diffusion import DiffusionPolicy
from lerobot.policies.factory import make_pre_post_processors

from rtv3_maniskill import features
from rtv3_maniskill.shared_control.twist_utils import check_speed_limits, clamp_twist_speed, step_inputs

DEFAULT_GAMMA = 0.1
"""The noising fraction ``rtv3 benchmark-shared`` and ``rtv3 teleop`` use unless told (chosen on the
validation block, see docs/RESULTS.md)."""
SHIPPED_COPILOT = Path(__file__).resolve().parents[1] / "checkpoints" / "copilot_diffusion"
"""The shipped copilot: ``rtv3 train-copilot`` on the planner demonstrations (its model card says which)."""


@dataclass(frozen=True)
class CopilotSettings:
    """Which copilot the ``copilot`` method runs.

    Attributes:
        path: the diffusion policy's ``pretrained_model`` folder (default: the shipped one).
        gamma: the noising fraction in [0, 1] (0: the user's twist; 1: the copilot alone).
        reverse_steps: DDIM steps of the whole schedule; None: the checkpoint's ``num_inference_steps``.
    """

    path: str = str(SHIPPED_COPILOT)
    gamma: float = DEFAULT_GAMMA
    reverse_steps: int | None = None

    def __post_init__(self):
        if not 0.0 <= float(self.gamma) <= 1.0:
            raise ValueError(f"copilot gamma must lie in [0, 1], got {self.gamma}")
        if self.reverse_steps is not None and int(self.reverse_steps) < 1:
            raise ValueError(f"copilot reverse_steps must be >= 1, got {self.reverse_steps}")


class DiffusionCopilot:
    """An :class:`~rtv3_maniskill.shared_control.assistance.AssistanceMethod` around a LeRobot diffusion policy.

    Args:
        policy: a ``DiffusionPolicy`` whose inputs are ``observation.state`` and ``observation.environment_state``
            (the scene summary) and whose action is the 6-D body twist.
        preprocessor, postprocessor: its saved LeRobot processors (normalisation with its dataset statistics).
        gamma: the noising fraction in [0, 1].
        reverse_steps: DDIM steps of the whole schedule (``gamma`` of them run each control step, at least one
            when ``gamma > 0``); None: the policy's ``num_inference_steps``.
        max_linear_speed, max_angular_speed: norm limits (m/s, rad/s) of the output.
        seed: seed of the noise, reset with every episode (paired trials see the same noise).
    """

    name = "copilot"

    def __init__(self, policy: DiffusionPolicy, preprocessor: Any, postprocessor: Any, gamma: float = DEFAULT_GAMMA,
                 reverse_steps: int | None = None, max_linear_speed: float | None = 0.3,
                 max_angular_speed: float | None = 1.2, seed: int = 0) -> None:
        check_speed_limits(max_linear_speed, max_angular_speed)
        if not 0.0 <= float(gamma) <= 1.0:
            raise ValueError(f"copilot gamma must lie in [0, 1], got {gamma}")
        config = policy.config
        missing = [k for k in (features.STATE, features.ENV_STATE) if k not in config.input_features]
        if missing or tuple(config.action_feature.shape) != (6,):
            raise ValueError(f"the copilot needs a diffusion policy with inputs {features.STATE} and "
                             f"{features.ENV_STATE} and a (6,) action; this one lacks {missing or 'the (6,) action'}")
        self.policy = policy.eval()
        self.preprocessor, self.postprocessor = preprocessor, postprocessor
        self.gamma = float(gamma)
        self.reverse_steps = int(reverse_steps or policy.diffusion.num_inference_steps or 10)
        if self.reverse_steps < 1:
            raise ValueError(f"reverse_steps must be >= 1, got {reverse_steps}")
        self.max_linear_speed, self.max_angular_speed = max_linear_speed, max_angular_speed
        self.seed = seed
        self.summary_dim = int(config.env_state_feature.shape[0])
        self.max_grasps = (self.summary_dim - features.HEIGHT_MAP_CELLS ** 2) // len(features.SUMMARY_GRASP_CHANNELS)
        self._history: deque[dict[str, torch.Tensor]] = deque(maxlen=config.n_obs_steps)
        self._generator = torch.Generator().manual_seed(seed)
        self._last: dict[str, Any] = {"mode": "shared", "gamma": self.gamma}

    @classmethod
    def from_pretrained(cls, path: str | Path, **kwargs: Any) -> DiffusionCopilot:
        """The copilot of a ``lerobot-train --policy.type=diffusion`` checkpoint (its ``pretrained_model`` folder).

        Raises ``FileNotFoundError`` when the folder holds no LeRobot policy."""
        path = Path(path)
        if not (path / "config.json").is_file() or not (path / "model.safetensors").is_file():
            raise FileNotFoundError(f"{path} holds no LeRobot policy (config.json and model.safetensors)")
        policy = DiffusionPolicy.from_pretrained(path)
        policy.config.device = "cpu"
        pre, post = make_pre_post_processors(policy.config, pretrained_path=str(path),
                                             preprocessor_overrides={"device_processor": {"device": "cpu"}},
                                             postprocessor_overrides={"device_processor": {"device": "cpu"}})
        return cls(policy.to("cpu"), pre, post, **kwargs)

    def reset(self) -> None:
        """Forget the observation history and restart the noise stream."""
        self._history.clear()
        self._generator = torch.Generator().manual_seed(self.seed)

    def _observe(self, observation: dict[str, Any], batch: int) -> dict[str, torch.Tensor]:
        """The policy's inputs ``(B, n_obs_steps, D)``: state and scene summary, the first repeated at the start."""
        summary = observation.get(features.ENV_STATE)
        if summary is None or summary.shape[-1] != self.summary_dim:
            summary = features.scene_summary(observation[features.POINT_CLOUD], observation[features.POINT_CLOUD_MASK],
                                             observation[features.GRASPS], observation[features.GRASPS_MASK])
        summary = torch.as_tensor(summary, dtype=torch.float32).reshape(batch, -1)
        if summary.shape[-1] != self.summary_dim:
            raise ValueError(f"the scene summary has {summary.shape[-1]} values, the copilot was trained on "
                             f"{self.summary_dim} (another max_grasps)")
        frame = {features.STATE: torch.as_tensor(observation[features.STATE], dtype=torch.float32).reshape(batch, -1),
                 features.ENV_STATE: summary}
        if not self._history or self._history[-1][features.STATE].shape[0] != batch:
            self._history.clear()
            self._history.extend([frame] * self._history.maxlen)
        else:
            self._history.append(frame)
        return {k: torch.stack([f[k] for f in self._history], 1) for k in frame}

    @torch.no_grad()
    def denoise(self, observation: dict[str, Any], user: torch.Tensor) -> torch.Tensor:
        """Partial diffusion of ``user (B, 6)`` to ``gamma`` and back -> the executed twist ``(B, 6)`` (unclipped)."""
        if self.gamma == 0.0:
            return user
        config, diffusion = self.policy.config, self.policy.diffusion
        horizon = config.horizon
        inputs = self._observe(observation, user.shape[0])
        held = user[:, None, :].expand(-1, horizon, -1)
        normalized = self.preprocessor({**inputs, features.ACTION: held})
        cond = diffusion._prepare_global_conditioning(
            {features.STATE: normalized[features.STATE], features.ENV_STATE: normalized[features.ENV_STATE]})
        scheduler = diffusion.noise_scheduler
        scheduler.set_timesteps(self.reverse_steps)
        steps = max(1, round(self.gamma * self.reverse_steps))
        timesteps = scheduler.timesteps[-steps:]
        noise = torch.randn(held.shape, generator=self._generator)
        if self.gamma >= 1.0:
            sample = noise
        else:
            sample = scheduler.add_noise(normalized[features.ACTION], noise, timesteps[:1])
        for t in timesteps:
            eps = diffusion.unet(sample, torch.full((sample.shape[0],), int(t), dtype=torch.long), global_cond=cond)
            sample = scheduler.step(eps, t, sample, generator=self._generator).prev_sample
        current = sample[:, config.n_obs_steps - 1]
        return self.postprocessor(current).to(torch.float32)

    def step(self, observation: dict[str, Any], user_twist: Any) -> torch.Tensor:
        """``observation`` (state, point cloud and grasps, batched), ``user_twist (B, 6)`` or None -> ``(B, 6)``.

        No input (None) is the user's command to hold still: a zero twist, denoised like any other."""
        state, user = step_inputs(observation, user_twist)
        out = clamp_twist_speed(self.denoise({**observation, features.STATE: state}, user), self.max_linear_speed,
                                self.max_angular_speed)
        self._last = {"mode": "shared", "gamma": self.gamma,
                      "distance_from_user": float((out - user).norm(dim=-1).mean())}
        return out

    def describe(self, index: int = 0) -> dict[str, Any]:
        """The last step: ``mode`` ``"shared"``, ``gamma`` and the twist's mean distance from the user's."""
        return dict(self._last)


__all__ = ["DEFAULT_GAMMA", "SHIPPED_COPILOT", "CopilotSettings", "DiffusionCopilot"]
