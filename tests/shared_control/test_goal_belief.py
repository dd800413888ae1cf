"""The recursive belief over grasp candidates, and the candidates the shared controller hands its prior."""

from __future__ import annotations

import math

import numpy as np
import pytest
import torch

from rtv3_maniskill import features
from rtv3_maniskill.se3 import make_transform, matrix_to_pose, relative_transform, se3_exp, se3_log, so3_exp
from rtv3_maniskill.shared_control import SharedControlConfig, SharedController
from rtv3_maniskill.shared_control.goal_belief import GoalBelief
from rtv3_maniskill.shared_control.oracle_prior import OraclePrior

F64 = torch.float64
DOWN = (math.pi, 0.0, 0.0)
MAX_GRASPS = 5  # three candidates and two padding slots


def pose_at(xyz, rotvec=DOWN) -> torch.Tensor:
    return make_transform(so3_exp(torch.tensor(rotvec, dtype=F64)), torch.tensor(xyz, dtype=F64))


START = pose_at((0.0, 0.0, 0.30))
# Three top-down grasps 10 cm apart along x; their pre-grasps lie 5 cm above them.
GRASP_POSES = torch.stack([pose_at((x, 0.0, 0.13)) for x in (-0.1, 0.0, 0.1)])
PREGRASPS = features.pregrasp_poses(GRASP_POSES)


def observation_at(pose: torch.Tensor) -> dict:
    state = torch.zeros(1, features.STATE_DIM)
    state[0, :7] = matrix_to_pose(pose).float()
    grasps = torch.zeros(1, MAX_GRASPS, features.GRASP_DIM)
    grasps[0, :3, :7] = matrix_to_pose(GRASP_POSES).float()
    mask = torch.zeros(1, MAX_GRASPS)
    mask[0, :3] = 1.0
    return {features.STATE: state, features.GRASPS: grasps.flatten(1), features.GRASPS_MASK: mask}


def _command_to(pose: torch.Tensor, goal: int, rng: np.random.Generator, noise: float = 0.05) -> torch.Tensor:
    e = se3_log(relative_transform(pose, PREGRASPS[goal]))
    return (e + torch.from_numpy(rng.normal(0.0, noise, 6)))[None]


def _update(belief: GoalBelief, pose: torch.Tensor, command: torch.Tensor, observed: torch.Tensor | None = None):
    cov = 0.01 * torch.eye(3, dtype=F64)[None]
    observed = torch.ones(1, 6, dtype=torch.bool) if observed is None else observed
    belief.update(observation_at(pose), command, torch.ones(1, dtype=torch.bool), observed, cov, cov)


def test_consistent_commands_leave_only_their_goal_and_padding_stays_out():
    belief = GoalBelief(margin=3.0, covariance_scale=1.0)
    rng = np.random.default_rng(0)
    mask = observation_at(START)[features.GRASPS_MASK]
    torch.testing.assert_close(belief.kept(mask), mask)  # no command yet: every candidate
    for _ in range(20):
        _update(belief, START, _command_to(START, 2, rng))
    assert belief.kept(mask).tolist() == [[0.0, 0.0, 1.0, 0.0, 0.0]]
    assert float(belief.evidence[0, 2]) == 0.0 and float(belief.evidence[0, :2].max()) < -3.0
    belief.reset()
    torch.testing.assert_close(belief.kept(mask), mask)


def test_only_the_observed_axes_count():
    """A command straight down alone (every candidate, and its twin turned about that axis, lies as
    far down) rules nothing out; the same command with x and y observed as zero (hold still) points
    to the middle candidate, the one straight below."""
    belief = GoalBelief(margin=1.0, covariance_scale=1.0)
    command = torch.tensor([[0.0, 0.0, 0.12, 0.0, 0.0, 0.0]], dtype=F64)  # body z points down
    only_z = torch.tensor([[False, False, True, False, False, False]])
    for _ in range(10):
        _update(belief, START, command, only_z)
    torch.testing.assert_close(belief.evidence[0, :3], torch.zeros(3, dtype=F64))
    for _ in range(10):
        _update(belief, START, command, only_z | torch.tensor([[True, True, False, False, False, False]]))
    assert belief.kept(observation_at(START)[features.GRASPS_MASK]).tolist() == [[0.0, 1.0, 0.0, 0.0, 0.0]]


class RecordingPrior(OraclePrior):
    """The oracle prior over the three pre-grasps that also records the grasp mask it was shown."""

    def __init__(self) -> None:
        super().__init__(PREGRASPS)
        self.masks: list[torch.Tensor] = []

    def predict_step0_mixture(self, observation):
        self.masks.append(torch.as_tensor(observation[features.GRASPS_MASK]).clone())
        return super().predict_step0_mixture(observation)


@pytest.mark.parametrize("margin", [None, 3.0])
def test_the_controller_hands_its_prior_the_candidates_the_belief_keeps(margin):
    prior = RecordingPrior()
    ctrl = SharedController(prior, SharedControlConfig(goal_belief_margin=margin, prior_covariance_scale=1.0,
                                                       user_cov_decay=1.0))
    ctrl.reset()
    rng = np.random.default_rng(1)
    pose = START.clone()
    for _ in range(30):
        twist = ctrl.step(observation_at(pose), _command_to(pose, 0, rng).float())
        pose = pose @ se3_exp(0.2 * twist[0].double() * 0.05)
    full = observation_at(START)[features.GRASPS_MASK]
    torch.testing.assert_close(prior.masks[0], full)  # the first command cannot rule anything out yet
    expected = full if margin is None else torch.tensor([[1.0, 0.0, 0.0, 0.0, 0.0]])
    torch.testing.assert_close(prior.masks[-1], expected)
    shown = ctrl.describe(0)  # what the teleoperation panel shows
    assert shown["shown_grasps"].tolist() == ([0, 1, 2] if margin is None else [0])
    assert shown["grasp_candidates"] == 3
    ctrl.reset()
    ctrl.step(observation_at(START), torch.zeros(1, 6))  # a new episode starts from every candidate again
    torch.testing.assert_close(prior.masks[-1], full)


def test_bad_settings_are_named():
    with pytest.raises(ValueError, match="goal_belief_margin"):
        SharedControlConfig(goal_belief_margin=0.0)
    with pytest.raises(ValueError, match="margin"):
        GoalBelief(margin=-1.0)
    belief = GoalBelief(margin=1.0)
    with pytest.raises(ValueError, match="observation.grasps"):
        belief.update({features.STATE: torch.zeros(1, features.STATE_DIM)}, torch.zeros(1, 6),
                      torch.ones(1, dtype=torch.bool), torch.ones(1, 6, dtype=torch.bool),
                      torch.eye(3)[None], torch.eye(3)[None])


def test_benchmark_shared_turns_the_goal_belief_off_or_sets_its_margin(tmp_path):
    import argparse

    from rtv3_maniskill.benchmarks.shared_config import BenchmarkConfig
    from rtv3_maniskill.cli.benchmark_shared import add_arguments, config_settings, shared_control_overrides

    parser = argparse.ArgumentParser()
    add_arguments(parser)

    def margin(*argv: str) -> float | None:
        args = parser.parse_args(list(argv))
        config = BenchmarkConfig(output=tmp_path, methods=["rtv3"], users=["noisy"],
                                 fusion=config_settings(args)["fusion"], shared_control=shared_control_overrides(args))
        return config.shared_control_config(0.3, 1.2).goal_belief_margin

    assert margin() == 1.0  # tuned
    assert margin("--goal-belief-margin", "off") is None
    assert margin("--goal-belief-margin", "2.5") == 2.5
    assert margin("--fusion", "paper") is None
    for bad in ("0", "-1", "many"):
        with pytest.raises(SystemExit):
            parser.parse_args(["--goal-belief-margin", bad])
