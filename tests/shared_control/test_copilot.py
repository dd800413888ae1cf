"""The diffusion copilot: partial diffusion of the user's twist through LeRobot's DiffusionPolicy."""

from __future__ import annotations

from pathlib import Path

import numpy as np
import pytest
import torch
from lerobot.configs.types import FeatureType, PolicyFeature
from lerobot.policies.diffusion.configuration_diffusion import DiffusionConfig
from lerobot.policies.diffusion.modeling_diffusion import DiffusionPolicy
from lerobot.policies.factory import make_pre_post_processors

from rtv3_maniskill import features
from rtv3_maniskill.shared_control.copilot import CopilotSettings, DiffusionCopilot
from rtv3_maniskill.shared_control.methods import UNINFORMED_METHODS, make_method, method_spec

MAX_GRASPS = 4


def _stats(dim: int, low: float, high: float) -> dict[str, np.ndarray]:
    return dict(min=np.full(dim, low, np.float32), max=np.full(dim, high, np.float32),
                mean=np.zeros(dim, np.float32), std=np.ones(dim, np.float32))


@pytest.fixture(scope="module")
def checkpoint(tmp_path_factory) -> Path:
    """A small (untrained) diffusion policy saved as lerobot-train saves one: weights, config, processors."""
    torch.manual_seed(0)
    summary = features.scene_summary_dim(MAX_GRASPS)
    config = DiffusionConfig(
        n_obs_steps=1, horizon=8, n_action_steps=4, down_dims=(16, 32), diffusion_step_embed_dim=16,
        noise_scheduler_type="DDIM", num_inference_steps=10, device="cpu",
        input_features={features.STATE: PolicyFeature(FeatureType.STATE, (features.STATE_DIM,)),
                        features.ENV_STATE: PolicyFeature(FeatureType.ENV, (summary,))},
        output_features={features.ACTION: PolicyFeature(FeatureType.ACTION, (6,))})
    stats = {features.STATE: _stats(features.STATE_DIM, -2, 2), features.ENV_STATE: _stats(summary, -1, 1),
             features.ACTION: _stats(6, -1, 1)}
    policy = DiffusionPolicy(config)
    pre, post = make_pre_post_processors(config, dataset_stats=stats)
    folder = tmp_path_factory.mktemp("copilot") / "pretrained_model"
    policy.save_pretrained(folder)
    pre.save_pretrained(folder)
    post.save_pretrained(folder)
    return folder


def _observation(batch: int = 2) -> dict[str, torch.Tensor]:
    g = torch.zeros(batch, MAX_GRASPS, features.GRASP_DIM)
    g[:, :2, :3] = torch.tensor([0.0, 0.05, 0.08])
    g[:, :2, 3] = 1.0
    mask = torch.zeros(batch, MAX_GRASPS)
    mask[:, :2] = 1.0
    state = torch.zeros(batch, features.STATE_DIM)
    state[:, features.EE_QUAT] = torch.tensor([0.0, 1.0, 0.0, 0.0])
    cloud = torch.rand(batch, 16, 6, generator=torch.Generator().manual_seed(1)) * 0.1
    return {features.STATE: state, features.POINT_CLOUD: cloud,
            features.POINT_CLOUD_MASK: torch.ones(batch, 16), features.GRASPS: g, features.GRASPS_MASK: mask}


USER_A = torch.tensor([[0.1, 0.0, 0.0, 0.0, 0.0, 0.0], [0.0, 0.0, -0.05, 0.0, 0.0, 0.2]])
USER_B = torch.tensor([[0.0, -0.1, 0.05, 0.0, 0.3, 0.0], [0.05, 0.05, 0.0, 0.1, 0.0, 0.0]])


def _step(copilot: DiffusionCopilot, user: torch.Tensor) -> torch.Tensor:
    copilot.reset()
    return copilot.step(_observation(), user)


def test_gamma_zero_returns_the_users_twist(checkpoint):
    copilot = DiffusionCopilot.from_pretrained(checkpoint, gamma=0.0)
    assert torch.equal(_step(copilot, USER_A), USER_A)
    assert copilot.describe()["distance_from_user"] == 0.0


def test_gamma_one_ignores_the_users_twist(checkpoint):
    copilot = DiffusionCopilot.from_pretrained(checkpoint, gamma=1.0, max_linear_speed=None, max_angular_speed=None)
    a, b = _step(copilot, USER_A), _step(copilot, USER_B)
    assert torch.allclose(a, b, atol=1e-6) and not torch.allclose(a, USER_A, atol=1e-3)


def test_partial_diffusion_depends_on_the_user_and_is_repeatable(checkpoint):
    copilot = DiffusionCopilot.from_pretrained(checkpoint, gamma=0.3, max_linear_speed=None, max_angular_speed=None)
    a, again, b = _step(copilot, USER_A), _step(copilot, USER_A), _step(copilot, USER_B)
    assert torch.equal(a, again), "reset restarts the noise: paired trials see the same noise"
    assert not torch.allclose(a, b, atol=1e-4)
    assert a.shape == (2, 6) and a.dtype == torch.float32 and torch.isfinite(a).all()
    # no input is the command to hold still
    copilot.reset()
    assert torch.isfinite(copilot.step(_observation(), None)).all()


def test_output_respects_the_speed_limits(checkpoint):
    copilot = DiffusionCopilot.from_pretrained(checkpoint, gamma=1.0, max_linear_speed=0.01, max_angular_speed=0.02)
    out = _step(copilot, USER_A)
    assert (out[:, :3].norm(dim=-1) <= 0.01 + 1e-6).all() and (out[:, 3:].norm(dim=-1) <= 0.02 + 1e-6).all()


def test_bad_settings_and_folders_are_named(checkpoint, tmp_path):
    with pytest.raises(ValueError, match="gamma"):
        DiffusionCopilot.from_pretrained(checkpoint, gamma=1.5)
    with pytest.raises(ValueError, match="gamma"):
        CopilotSettings(gamma=-0.1)
    with pytest.raises(FileNotFoundError, match="no LeRobot policy"):
        DiffusionCopilot.from_pretrained(tmp_path)
    copilot = DiffusionCopilot.from_pretrained(checkpoint)
    wrong = {**_observation(), features.GRASPS: torch.zeros(2, MAX_GRASPS + 1, 9),
             features.GRASPS_MASK: torch.zeros(2, MAX_GRASPS + 1)}
    with pytest.raises(ValueError, match="max_grasps"):
        copilot.step(wrong, USER_A)


def test_the_copilot_is_a_registered_method_a_person_can_use(checkpoint):
    spec = method_spec("diffusion-copilot")
    assert spec.name == "copilot" and not spec.needs_policy and "copilot" in UNINFORMED_METHODS
    method = make_method("copilot", (0.3, 1.2), copilot=CopilotSettings(path=str(checkpoint), gamma=0.4))
    assert isinstance(method, DiffusionCopilot) and method.gamma == 0.4
    assert method.max_linear_speed == 0.3 and method.max_angular_speed == 1.2
