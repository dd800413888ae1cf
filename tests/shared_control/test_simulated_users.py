"""Simulated users (paper appendix "Simulated User", docs/PAPER_DETAILS.md)."""

from __future__ import annotations

import math

import numpy as np
import pytest
import torch

from rtv3_maniskill.se3 import se3_exp, se3_log
from rtv3_maniskill.shared_control.simulated_users import (
    IntermittentUser,
    LaggyUser,
    LowDoFUser,
    ModeSwitchingUser,
    NoisyUser,
    SingleDoFUser,
    make_user,
)

DT = 0.05
START = se3_exp(torch.tensor([0.3, 0.1, 0.4, 0.2, -0.1, 0.3], dtype=torch.float64))
GOAL = se3_exp(torch.tensor([0.5, -0.1, 0.2, -0.4, 0.3, 1.2], dtype=torch.float64))


def test_ideal_command_is_the_body_twist_to_the_goal_and_reaches_it():
    user = make_user("ideal")
    user.reset(GOAL)
    e = user(START)
    torch.testing.assert_close(e, se3_log(torch.linalg.inv(START) @ GOAL))
    torch.testing.assert_close(START @ se3_exp(e), GOAL)  # body twist, unscaled: one second reaches the goal
    # a pure body-frame offset gives exactly that offset
    offset = se3_exp(torch.tensor([0.1, 0.0, 0.0, 0.0, 0.0, 0.0], dtype=torch.float64))
    user.reset(START @ offset)
    torch.testing.assert_close(user(START), torch.tensor([0.1, 0, 0, 0, 0, 0], dtype=torch.float64))
    pose = START.clone()
    user.reset(GOAL)
    for _ in range(150):
        pose = pose @ se3_exp(user(pose) * DT)
    assert (se3_log(torch.linalg.inv(pose) @ GOAL)).abs().max() < 1e-3


def test_noisy_user_adds_zero_mean_noise_of_variance_005():
    user = make_user("noisy", seed=0)
    user.reset(GOAL)
    e = se3_log(torch.linalg.inv(START) @ GOAL)
    noise = torch.stack([user(START) - e for _ in range(4000)]).numpy()
    assert np.abs(noise.mean(0)).max() < 4 * math.sqrt(0.05 / 4000)
    np.testing.assert_allclose(noise.var(0), 0.05, rtol=0.1)
    assert abs(np.corrcoef(noise.T)[0, 1]) < 0.06  # independent axes


def test_users_are_reproducible_from_their_seed():
    def run(seed):
        user = make_user("noisy", seed=seed)
        user.reset(GOAL)
        return torch.stack([user(START) for _ in range(5)])

    assert torch.equal(run(3), run(3))
    assert not torch.equal(run(3), run(4))
    shared = np.random.default_rng(7)
    assert NoisyUser(rng=shared).rng is shared


def test_laggy_user_repeats_the_previous_command_with_probability_08():
    user = LaggyUser(seed=1)
    user.reset(GOAL)
    pose = START.clone()
    first = user(pose)
    torch.testing.assert_close(first, se3_log(torch.linalg.inv(pose) @ GOAL))
    previous, repeats, steps = first, 0, 3000
    drift = se3_exp(torch.tensor([0.001, 0.0, 0.0, 0.0, 0.0, 0.001], dtype=torch.float64))
    for _ in range(steps):
        pose = pose @ drift  # e changes every step, so a repeat is recognisable
        command = user(pose)
        if torch.equal(command, previous):
            repeats += 1
        else:
            torch.testing.assert_close(command, se3_log(torch.linalg.inv(pose) @ GOAL))
        previous = command
    assert repeats / steps == pytest.approx(0.8, abs=0.03)


def test_mode_switching_user_alternates_20_translation_and_20_rotation_steps():
    user = ModeSwitchingUser()
    user.reset(GOAL)
    e = se3_log(torch.linalg.inv(START) @ GOAL)
    for step in range(80):
        u = user(START)
        if (step // 20) % 2 == 0:
            torch.testing.assert_close(u[:3], e[:3])
            assert torch.equal(u[3:], torch.zeros(3, dtype=torch.float64)), step
        else:
            torch.testing.assert_close(u[3:], e[3:])
            assert torch.equal(u[:3], torch.zeros(3, dtype=torch.float64)), step
    user.reset(GOAL)
    assert user.translation_mode


def test_intermittent_user_rests_between_commanding_phases_and_pauses_the_inner_clock():
    user = make_user("mode_switching", pauses=(20, 10))
    assert isinstance(user, IntermittentUser)
    user.reset(GOAL)
    e = se3_log(torch.linalg.inv(START) @ GOAL)
    commands = [user(START) for _ in range(90)]
    for step, u in enumerate(commands):
        if step % 30 >= 20:  # resting: no command
            assert torch.equal(u, torch.zeros(6, dtype=torch.float64)), step
    # the mode-switching clock stops during rests: steps 0-19 translate, 30-49 rotate, 60-79 translate
    torch.testing.assert_close(commands[0][:3], e[:3])
    torch.testing.assert_close(commands[30][3:], e[3:])
    assert torch.equal(commands[30][:3], torch.zeros(3, dtype=torch.float64))
    torch.testing.assert_close(commands[60][:3], e[:3])
    user.reset(GOAL)
    assert not user.resting and torch.equal(user(START)[3:], torch.zeros(3, dtype=torch.float64))
    never = make_user("ideal", pauses=(5, 0))
    never.reset(GOAL)
    assert all(torch.linalg.norm(never(START)) > 0 for _ in range(12))
    with pytest.raises(ValueError, match="command_steps >= 1"):
        make_user("noisy", pauses=(0, 5))
    with pytest.raises(ValueError, match="pauses must be"):
        make_user("noisy", pauses=(5,))


def test_single_dof_user_holds_the_weighted_largest_dof_for_10_steps_with_gain_2():
    user = SingleDoFUser()
    # e: translation x = 0.05, rotation x = 0.3 -> weighted 0.03 < 0.05, so DoF 0 wins
    target_a = se3_exp(torch.tensor([0.05, 0.01, 0.0, 0.3, 0.0, 0.0], dtype=torch.float64))
    # later e: translation y dominates
    target_b = se3_exp(torch.tensor([0.0, 0.2, 0.0, 0.0, 0.0, 0.0], dtype=torch.float64))
    identity = torch.eye(4, dtype=torch.float64)
    user.reset(target_a)
    for step in range(10):
        if step == 5:
            user.goal_pose = target_b  # goal moves mid-period: the DoF is kept until step 10
        u = user(identity)
        e = se3_log(user.goal_pose)
        assert torch.count_nonzero(u) <= 1
        assert u[0] == pytest.approx(2 * float(e[0]))
    u = user(identity)
    assert user.active_dof == 1
    torch.testing.assert_close(u, torch.tensor([0.0, 0.4, 0.0, 0.0, 0.0, 0.0], dtype=torch.float64))


def test_low_dof_user_commands_translation_only():
    user = LowDoFUser()
    user.reset(GOAL)
    e = se3_log(torch.linalg.inv(START) @ GOAL)
    u = user(START)
    torch.testing.assert_close(u[:3], e[:3])
    assert torch.equal(u[3:], torch.zeros(3, dtype=torch.float64))


def test_velocity_clip_limits_command_norms():
    user = make_user("noisy", seed=0, max_linear_speed=0.05, max_angular_speed=0.1)
    user.reset(GOAL)
    for _ in range(20):
        u = user(START)
        assert u[:3].norm() <= 0.05 + 1e-12 and u[3:].norm() <= 0.1 + 1e-12


def test_registry_and_bad_inputs():
    assert isinstance(make_user("Mode-Switching"), ModeSwitchingUser)
    assert isinstance(make_user("single_dof"), SingleDoFUser)
    with pytest.raises(ValueError, match="unknown simulated user 'clumsy'.*laggy.*noisy"):
        make_user("clumsy")
    user = make_user("ideal")
    with pytest.raises(RuntimeError, match="reset"):
        user(START)
    user.reset(GOAL)
    with pytest.raises(ValueError, match=r"ee_pose must be a \(4, 4\)"):
        user(torch.zeros(3, 3))
    bad = START.clone()
    bad[0, 0] = math.nan
    with pytest.raises(ValueError, match="NaN"):
        user(bad)
    with pytest.raises(ValueError, match="repeat_probability"):
        LaggyUser(repeat_probability=1.5)
