"""Hindsight Optimization baseline (Javdani et al. 2018) and direct teleoperation."""

from __future__ import annotations

import math

import pytest
import torch

from rtv3_maniskill.se3 import make_transform, se3_exp, so3_exp
from rtv3_maniskill.shared_control.direct import DirectTeleoperation
from rtv3_maniskill.shared_control.hindsight_optimization import VARIANTS, HindsightOptimization, HuberCost
from rtv3_maniskill.shared_control.simulated_users import make_user

DT = 0.05
F64 = torch.float64


def pose_at(xyz, rotvec=(0.0, 0.0, 0.0)) -> torch.Tensor:
    return make_transform(so3_exp(torch.tensor(rotvec, dtype=F64)), torch.tensor(xyz, dtype=F64))


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


@pytest.mark.parametrize("variant", ["javdani2018", "rtv3_authors"])
def test_belief_converges_to_the_goal_a_noiseless_user_drives_to(variant):
    ho = HindsightOptimization(GOALS, variant=variant, dt=DT)
    torch.testing.assert_close(ho.belief, torch.full((3,), 1 / 3, dtype=F64))
    user = make_user("ideal")
    true_goal = 1
    user.reset(GOALS[true_goal])
    pose = START.clone()
    for _ in range(60):
        twist = ho.step(pose, user(pose))
        pose = pose @ se3_exp(twist * DT)
    assert int(ho.belief.argmax()) == true_goal
    assert ho.belief[true_goal] > 0.9
    assert ho.belief.max() <= VARIANTS[variant].max_goal_probability + 1e-9  # capped at 0.99
    assert ho.belief.sum() == pytest.approx(1.0)
    assert (pose[:3, 3] - GOALS[true_goal, :3, 3]).norm() < 0.03


def test_assistance_points_towards_the_believed_goal():
    ho = HindsightOptimization(GOALS, variant="javdani2018")
    user = make_user("ideal")
    user.reset(GOALS[0])
    pose = START.clone()
    for _ in range(15):
        pose = pose @ se3_exp(ho.step(pose, user(pose)) * DT)
    assert int(ho.belief.argmax()) == 0
    assist_world = pose[:3, :3] @ ho.last_assistance[:3]
    to_goal = GOALS[0, :3, 3] - pose[:3, 3]
    cosine = float(assist_world @ to_goal / (assist_world.norm() * to_goal.norm()))
    assert cosine > 0.8
    # the output is the user's command plus the assistance
    u = user(pose)
    out = ho.step(pose, u)
    torch.testing.assert_close(out, u + ho.last_assistance)


def test_single_goal_assistance_with_rotation_turns_towards_the_goal_orientation():
    goal = pose_at((0.0, 0.0, 0.3), (math.pi, 0.0, 0.0)) @ pose_at((0.0, 0.0, 0.0), (0.0, 0.0, 0.5))
    ho = HindsightOptimization(goal[None], variant="javdani2018")
    out = ho.step(START, torch.zeros(6))
    assert ho.belief.tolist() == [1.0]
    assert out[:3].norm() < 1e-9  # already at the goal position
    assert out[5] > 0 and out[3:5].abs().max() < 1e-9  # body rotation about +z, the goal's direction
    # Javdani scaling far from the goal: 0.07 * (0.2 + 0.01) / 0.05 rad/s
    assert float(out[5]) == pytest.approx(0.07 * 0.21 / 0.05, rel=1e-6)
    # the RT-V3 authors' variant has no rotation cost: the output rotation is the user's
    ho2 = HindsightOptimization(goal[None], variant="rtv3_authors")
    user = torch.tensor([0.0, 0.0, 0.0, 0.1, 0.0, 0.0], dtype=F64)
    torch.testing.assert_close(ho2.step(START, user)[3:], user[3:])


def test_translation_assistance_magnitude_and_near_goal_scaling():
    far_goal = pose_at((0.5, 0.0, 0.3), (math.pi, 0.0, 0.0))
    ho = HindsightOptimization(far_goal[None], variant="javdani2018")
    out = ho.step(START, torch.zeros(6))
    assert float(out[:3].norm()) == pytest.approx((2.25 + 0.2) / 40.0, rel=1e-6)
    near_goal = pose_at((0.01, 0.0, 0.3), (math.pi, 0.0, 0.0))
    ho = HindsightOptimization(near_goal[None], variant="javdani2018")
    near = ho.step(START, torch.zeros(6))
    expected = ((2.25 / 0.07) * 0.01 + 0.2) / 40.0 * (0.01 / 0.02)
    assert float(near[:3].norm()) == pytest.approx(expected, rel=1e-6)


def test_target_groups_share_one_belief_entry():
    ho = HindsightOptimization(GOALS, target_groups=[7, 7, 9])
    assert ho.num_goals == 2 and ho.goal_ids.tolist() == [7, 9]
    user = make_user("ideal")
    user.reset(GOALS[1])
    pose = START.clone()
    for _ in range(40):
        pose = pose @ se3_exp(ho.step(pose, user(pose)) * DT)
    assert ho.belief[0] > 0.9
    ho.reset()
    torch.testing.assert_close(ho.belief, torch.tensor([0.5, 0.5], dtype=F64))


def test_bad_inputs():
    with pytest.raises(ValueError, match="goals is empty"):
        HindsightOptimization(torch.zeros(0, 4, 4))
    with pytest.raises(ValueError, match="unknown HO variant"):
        HindsightOptimization(GOALS, variant="javdani")
    with pytest.raises(ValueError, match="one id per goal pose"):
        HindsightOptimization(GOALS, target_groups=[0, 1])
    ho = HindsightOptimization(GOALS)
    with pytest.raises(ValueError, match="user_twist contains NaN"):
        ho.step(START, torch.tensor([math.nan, 0, 0, 0, 0, 0]))
    with pytest.raises(ValueError, match=r"user_twist must have shape \(6,\)"):
        ho.step(START, torch.zeros(3))
    with pytest.raises(ValueError, match="ee_pose"):
        ho.step(torch.eye(3), torch.zeros(6))


def test_direct_teleoperation_passes_the_twist_through_with_limits():
    direct = DirectTeleoperation(max_linear_speed=0.1, max_angular_speed=0.5)
    u = torch.tensor([0.05, 0.0, 0.0, 0.0, 0.2, 0.0])
    torch.testing.assert_close(direct.step(START, u), u.double())
    fast = direct.step(None, torch.tensor([0.3, 0.4, 0.0, 0.0, 0.0, 2.0]))
    assert float(fast[:3].norm()) == pytest.approx(0.1)
    torch.testing.assert_close(fast[:3] / fast[:3].norm(), torch.tensor([0.6, 0.8, 0.0], dtype=F64))
    assert float(fast[5]) == pytest.approx(0.5)
    with pytest.raises(ValueError, match="NaN"):
        direct.step(None, [0, 0, math.inf, 0, 0, 0])
