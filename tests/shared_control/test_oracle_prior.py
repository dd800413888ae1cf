"""The oracle prior (a prior that knows the goals) and the recursive goal belief, without a simulator."""

from __future__ import annotations

import math

import numpy as np
import pytest
import torch

from rtv3_maniskill import features
from rtv3_maniskill.se3 import make_transform, matrix_to_pose, relative_transform, se3_exp, se3_log, so3_exp
from rtv3_maniskill.shared_control import SharedControlConfig, SharedController
from rtv3_maniskill.shared_control.oracle_prior import OraclePrior

F64 = torch.float64
DOWN = (math.pi, 0.0, 0.0)


def pose_at(xyz, rotvec=DOWN) -> torch.Tensor:
    return make_transform(so3_exp(torch.tensor(rotvec, dtype=F64)), torch.tensor(xyz, dtype=F64))


def observation_at(pose: torch.Tensor) -> dict:
    state = torch.zeros(1, features.STATE_DIM)
    state[0, :7] = matrix_to_pose(pose).float()
    return {features.STATE: state}


START = pose_at((0.0, 0.0, 0.30))
# Three pre-grasps 12 cm below and 10 cm apart: one step of a noisy command cannot tell them apart.
GOALS = torch.stack([pose_at((x, 0.0, 0.18)) for x in (-0.1, 0.0, 0.1)])


def test_each_class_is_the_clipped_straight_twist_to_its_goal_and_its_nearer_twin():
    prior = OraclePrior(GOALS, max_linear_speed=0.3, max_angular_speed=1.2)
    mixture = prior.predict_step0_mixture(observation_at(START))
    assert mixture.log_weights.shape == (1, 3)
    torch.testing.assert_close(mixture.weights, torch.full((1, 3), 1 / 3, dtype=F64))
    e = se3_log(relative_transform(START, GOALS[2]))
    torch.testing.assert_close(mixture.trans_mean[0, 2], e[:3], atol=1e-6, rtol=0)
    omega, gamma = mixture.rotation_given_translation(mixture.trans_mean)
    torch.testing.assert_close(gamma[0, 0], 0.1**2 * torch.eye(3, dtype=F64))
    torch.testing.assert_close(mixture.trans_cov[0, 0], 0.02**2 * torch.eye(3, dtype=F64))
    # A goal turned by pi about its z is reached through its twin: no half turn is commanded.
    turned = GOALS[1] @ pose_at((0.0, 0.0, 0.0), (0.0, 0.0, math.pi))
    far = OraclePrior(turned[None], max_linear_speed=None, max_angular_speed=None)
    assert far.predict_step0_mixture(observation_at(START)).rotation_given_translation(
        torch.zeros(1, 1, 3))[0].norm() < 1e-6
    # Far goals are clipped to the speed limits.
    fast = OraclePrior(pose_at((2.0, 0.0, 0.3))[None], max_linear_speed=0.3)
    assert float(fast.predict_step0_mixture(observation_at(START)).trans_mean.norm()) == pytest.approx(0.3)
    with pytest.raises(RuntimeError, match="set_goals"):
        OraclePrior().predict_step0_mixture(observation_at(START))
    with pytest.raises(ValueError, match="goals"):
        OraclePrior(torch.zeros(0, 4, 4))


def _drive(memory: float, steps: int = 40) -> torch.Tensor:
    """A user who aims at goal 1 with noisy but consistent commands; returns the class weights."""
    ctrl = SharedController(OraclePrior(GOALS), SharedControlConfig(
        belief_memory=memory, ood_covariance="predictive", ood_alpha=0.99, user_cov_decay=1.0,
        max_linear_speed=0.3, max_angular_speed=1.2, prior_covariance_scale=1.0))  # the oracle's own covariances
    ctrl.reset()
    rng = np.random.default_rng(0)
    pose = START.clone()
    for _ in range(steps):
        e = se3_log(relative_transform(pose, GOALS[1]))
        command = (e + torch.from_numpy(rng.normal(0.0, 0.05, 6))).float()[None]
        twist = ctrl.step(observation_at(pose), command)
        pose = pose @ se3_exp(0.2 * twist[0].double() * 0.05)  # slow: the goals stay ambiguous per step
    return ctrl.last_diagnostics.class_weights[0]


def test_recursive_belief_concentrates_on_the_goal_consistent_commands_point_to():
    forgetful = _drive(0.0)
    recursive = _drive(1.0)
    assert int(recursive.argmax()) == 1 and recursive[1] > 0.95
    assert recursive[1] > forgetful[1] + 0.2  # the paper's forgetful posterior stays unsure
    with pytest.raises(ValueError, match="belief_memory"):
        SharedControlConfig(belief_memory=1.5)


class MaskRecordingPrior:
    """Test double of the learned prior: a fixed one-class mixture; records the grasp masks it is shown."""

    def __init__(self):
        self.masks, self.resets = [], 0

    def predict_step0_mixture(self, observation):
        from rtv3_maniskill.twist_mixture import TwistMixture

        self.masks.append(torch.as_tensor(observation[features.GRASPS_MASK]).clone())
        b = self.masks[-1].shape[0]

        def rotation_given_translation(v):
            return torch.zeros(*v.shape[:-1], 3, dtype=v.dtype), 0.01 * torch.eye(3, dtype=v.dtype).expand(
                *v.shape[:-1], 3, 3)

        return TwistMixture(torch.zeros(b, 1), torch.zeros(b, 1, 3), 0.01 * torch.eye(3).expand(b, 1, 3, 3).clone(),
                            rotation_given_translation)

    def reset(self):
        self.resets += 1


def test_rtv3_goal_shows_its_learned_prior_only_the_target_grasp():
    """``rtv3-goal``: RT-V3's controller with the policy's grasp mask reduced to the trial's target
    (a ceiling on reading the goal); no belief over the candidates; a target that is not among the
    candidates is a named error."""
    from rtv3_maniskill.shared_control.methods import make_method

    policy = MaskRecordingPrior()
    method = make_method("rtv3-goal", (0.3, 1.2), policy=policy, config=SharedControlConfig())
    assert method.config.goal_belief_margin is None and method.config.max_linear_speed == 0.3
    observation = {**observation_at(START), features.GRASPS: torch.zeros(1, 4, features.GRASP_DIM),
                   features.GRASPS_MASK: torch.tensor([[1.0, 1.0, 1.0, 0.0]])}
    with pytest.raises(RuntimeError, match="set_target"):
        method.step(observation, torch.zeros(1, 6))
    method.policy.set_target(1)
    method.reset()
    method.step(observation, torch.tensor([[0.1, 0.0, 0.0, 0.0, 0.0, 0.0]]))
    torch.testing.assert_close(policy.masks[-1], torch.tensor([[0.0, 1.0, 0.0, 0.0]]))
    assert policy.resets == 1
    for missing in (3, 7):  # padding, out of range
        method.policy.set_target(missing)
        with pytest.raises(ValueError, match="not among the observation's 4 grasp candidates"):
            method.step(observation, torch.zeros(1, 6))
    with pytest.raises(ValueError, match="needs a policy"):
        make_method("rtv3-goal", (0.3, 1.2))
