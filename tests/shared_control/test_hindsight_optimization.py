"""Hindsight Optimization baseline (Javdani et al. 2018) and direct teleoperation."""

from __future__ import annotations

import math

import pytest
import torch

from rtv3_maniskill import features
from rtv3_maniskill.se3 import make_transform, matrix_to_pose, se3_exp, so3_exp, translate_along_z
from rtv3_maniskill.shared_control.direct import DirectTeleoperation
from rtv3_maniskill.shared_control.hindsight_optimization import HindsightOptimization, HOConstants, HuberCost
from rtv3_maniskill.shared_control.simulated_users import make_user

DT = 0.05
F64 = torch.float64


def pose_at(xyz, rotvec=(0.0, 0.0, 0.0)) -> torch.Tensor:
    return make_transform(so3_exp(torch.tensor(rotvec, dtype=F64)), torch.tensor(xyz, dtype=F64))


def observation_at(pose: torch.Tensor, grasp_poses: torch.Tensor | None = None, max_grasps: int = 8) -> dict:
    """A batch-1 feature dict: the TCP at ``pose``; optionally grasp candidates at ``grasp_poses (G, 4, 4)``."""
    state = torch.zeros(1, features.STATE_DIM)
    state[0, :7] = matrix_to_pose(pose).float()
    obs = {features.STATE: state}
    grasps, mask = torch.zeros(1, max_grasps, features.GRASP_DIM), torch.zeros(1, max_grasps)
    if grasp_poses is not None:
        grasps[0, : len(grasp_poses), :7] = matrix_to_pose(grasp_poses).float()
        mask[0, : len(grasp_poses)] = 1.0
    obs.update({features.GRASPS: grasps, features.GRASPS_MASK: mask})
    return obs


def drive(ho, user, pose: torch.Tensor, steps: int, grasp_poses: torch.Tensor | None = None) -> torch.Tensor:
    """Let ``user`` drive through ``ho`` for ``steps`` control steps; returns the final pose."""
    for _ in range(steps):
        twist = ho.step(observation_at(pose, grasp_poses), user(pose)[None].float())
        pose = pose @ se3_exp(twist[0].double() * DT)
    return pose


START = pose_at((0.0, 0.0, 0.3), (math.pi, 0.0, 0.0))  # gripper pointing down
GOALS = torch.stack(
    [
        pose_at((0.25, 0.0, 0.1), (math.pi, 0.0, 0.0)),
        pose_at((-0.2, 0.15, 0.1), (math.pi, 0.0, 0.0)),
        pose_at((0.0, -0.25, 0.12), (math.pi, 0.0, 0.0)),
    ]
)


def test_huber_cost_is_continuous_and_rate_is_its_derivative():
    cost = HuberCost(2.25, 0.07, 0.2)
    d = torch.tensor([0.07 - 1e-9, 0.07 + 1e-9], dtype=F64)
    v = cost.value(d)
    assert v[0] == pytest.approx(float(v[1]), abs=1e-7)
    assert float(cost.value(torch.tensor(0.07, dtype=F64))) == pytest.approx(0.5 * 2.25 * 0.07 + 0.2 * 0.07)
    for x in (0.01, 0.05, 0.2, 1.0):
        t = torch.tensor(x, dtype=F64)
        numeric = (cost.value(t + 1e-7) - cost.value(t - 1e-7)) / 2e-7
        assert float(cost.rate(t)) == pytest.approx(float(numeric), rel=1e-5)


def test_belief_converges_to_the_goal_a_noiseless_user_drives_to():
    ho = HindsightOptimization(None, None, goals=GOALS)
    ho.step(observation_at(START), None)
    torch.testing.assert_close(ho.episodes[0].belief, torch.full((3,), 1 / 3, dtype=F64))
    ho.reset()
    user = make_user("ideal")
    true_goal = 1
    user.reset(GOALS[true_goal])
    pose = drive(ho, user, START.clone(), 60)
    belief = ho.episodes[0].belief
    assert int(belief.argmax()) == true_goal
    assert belief[true_goal] > 0.9
    assert belief.max() <= HOConstants().max_goal_probability + 1e-9  # capped at 0.99
    assert belief.sum() == pytest.approx(1.0)
    assert (pose[:3, 3] - GOALS[true_goal, :3, 3]).norm() < 0.03


def test_goals_are_the_pre_grasps_of_the_observed_grasps_and_their_twins():
    grasps = translate_along_z(GOALS, features.PREGRASP_DISTANCE)  # grasps whose pre-grasps are GOALS
    ho = HindsightOptimization(None, None)
    user = make_user("ideal")
    user.reset(GOALS[2])
    drive(ho, user, START.clone(), 50, grasps)
    episode = ho.episodes[0]
    assert episode.goal_ids.tolist() == [0, 1, 2]  # one goal per grasp, twins share it
    assert episode.targets.shape == (6, 4, 4)
    torch.testing.assert_close(episode.targets[:3, :3, 3], GOALS[:, :3, 3], atol=1e-6, rtol=0)
    assert int(episode.belief.argmax()) == 2
    assert ho.describe(0)["most_likely_goal"] == 2
    with pytest.raises(ValueError, match="no valid grasp candidate"):
        HindsightOptimization().step(observation_at(START, GOALS[:0]), None)


def test_assistance_points_towards_the_believed_goal():
    ho = HindsightOptimization(None, None, goals=GOALS)
    user = make_user("ideal")
    user.reset(GOALS[0])
    pose = drive(ho, user, START.clone(), 40)
    episode = ho.episodes[0]
    assert int(episode.belief.argmax()) == 0
    assist_world = pose[:3, :3] @ episode.last_assistance[:3]
    to_goal = GOALS[0, :3, 3] - pose[:3, 3]
    cosine = float(assist_world @ to_goal / (assist_world.norm() * to_goal.norm()))
    assert cosine > 0.8
    # the output is the user's command plus the assistance
    u = user(pose)[None].float()
    out = ho.step(observation_at(pose), u)
    assert out.dtype == torch.float32 and out.shape == (1, 6)
    torch.testing.assert_close(out, u + episode.last_assistance.float()[None])


def test_the_output_rotation_is_the_users_own():
    """The cost is on the translation alone: at the goal's position, turned away from its
    orientation, HO adds nothing and the user's rotation passes through."""
    goal = pose_at((0.0, 0.0, 0.3), (math.pi, 0.0, 0.0)) @ pose_at((0.0, 0.0, 0.0), (0.0, 0.0, 0.5))
    ho = HindsightOptimization(None, None, goals=goal[None])
    torch.testing.assert_close(ho.step(observation_at(START), None), torch.zeros(1, 6), atol=1e-6, rtol=0)
    assert ho.episodes[0].belief.tolist() == [1.0]
    user = torch.tensor([[0.0, 0.0, 0.0, 0.1, 0.0, 0.0]])
    torch.testing.assert_close(ho.step(observation_at(START), user)[0, 3:], user[0, 3:])


def test_translation_assistance_magnitude_and_near_goal_scaling():
    """Huber cost m = 1.5, delta = 0.1, c = 0.1: far from the goal the rate is m + c, divided by 40;
    within 2 cm it is also scaled down linearly."""
    far_goal = pose_at((0.5, 0.0, 0.3), (math.pi, 0.0, 0.0))
    ho = HindsightOptimization(None, None, goals=far_goal[None])
    out = ho.step(observation_at(START), None)[0]
    assert float(out[:3].norm()) == pytest.approx((1.5 + 0.1) / 40.0, rel=1e-5)
    near_goal = pose_at((0.01, 0.0, 0.3), (math.pi, 0.0, 0.0))
    ho = HindsightOptimization(None, None, goals=near_goal[None])
    near = ho.step(observation_at(START), None)[0]
    expected = ((1.5 / 0.1) * 0.01 + 0.1) / 40.0 * (0.01 / 0.02)
    assert float(near[:3].norm()) == pytest.approx(expected, rel=1e-4)


def test_target_groups_share_one_belief_entry():
    ho = HindsightOptimization(None, None, goals=GOALS, target_groups=[7, 7, 9])
    user = make_user("ideal")
    user.reset(GOALS[1])
    drive(ho, user, START.clone(), 40)
    assert ho.episodes[0].num_goals == 2 and ho.episodes[0].goal_ids.tolist() == [7, 9]
    assert ho.episodes[0].belief[0] > 0.9
    ho.reset()
    ho.step(observation_at(START), None)
    torch.testing.assert_close(ho.episodes[0].belief, torch.tensor([0.5, 0.5], dtype=F64))


def test_bad_inputs():
    with pytest.raises(ValueError, match="goals is empty"):
        HindsightOptimization(goals=torch.zeros(0, 4, 4))
    with pytest.raises(ValueError, match="one id per goal pose"):
        HindsightOptimization(goals=GOALS, target_groups=[0, 1]).step(observation_at(START), None)
    ho = HindsightOptimization(goals=GOALS)
    with pytest.raises(ValueError, match="user_twist contains NaN"):
        ho.step(observation_at(START), torch.tensor([[math.nan, 0, 0, 0, 0, 0]]))
    with pytest.raises(ValueError, match=r"user_twist must have shape \(1, 6\)"):
        ho.step(observation_at(START), torch.zeros(3))
    with pytest.raises(ValueError, match="observation.state"):
        ho.step({features.STATE: torch.zeros(1, 7)}, None)
    with pytest.raises(ValueError, match="observation.grasps"):
        HindsightOptimization().step({features.STATE: observation_at(START)[features.STATE]}, None)


def test_direct_teleoperation_passes_the_twist_through_with_limits():
    direct = DirectTeleoperation(max_linear_speed=0.1, max_angular_speed=0.5)
    obs = observation_at(START)
    u = torch.tensor([[0.05, 0.0, 0.0, 0.0, 0.2, 0.0]])
    torch.testing.assert_close(direct.step(obs, u), u)
    fast = direct.step(obs, torch.tensor([[0.3, 0.4, 0.0, 0.0, 0.0, 2.0]]))[0]
    assert float(fast[:3].norm()) == pytest.approx(0.1)
    torch.testing.assert_close(fast[:3] / fast[:3].norm(), torch.tensor([0.6, 0.8, 0.0]))
    assert float(fast[5]) == pytest.approx(0.5)
    assert torch.equal(direct.step(obs, None), torch.zeros(1, 6))
    assert direct.describe(0) == {"mode": "user_only"}
    with pytest.raises(ValueError, match="NaN"):
        direct.step(obs, torch.tensor([[0, 0, math.inf, 0, 0, 0]]))
    with pytest.raises(ValueError, match="torch tensor or numpy array"):
        direct.step(obs, [[0, 0, 0, 0, 0, 0]])
