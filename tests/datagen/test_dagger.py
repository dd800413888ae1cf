"""DAgger with the planner as the expert: rollouts, relabels from visited states, the stored histories."""

from __future__ import annotations

import argparse
import json

import numpy as np
import pytest

from rtv3_maniskill import features
from rtv3_maniskill.cli.dagger import add_arguments, dagger_config
from rtv3_maniskill.datagen.dagger import Rollout, relabel_steps
from rtv3_maniskill.datagen.dagger_config import FAILURE_WINDOW_STEPS, DaggerConfig, parse_driver
from rtv3_maniskill.datagen.lerobot_export import state_histories


def test_state_histories_hold_the_prefix_before_the_first_frame():
    states = np.arange(4 * 27, dtype=np.float32).reshape(4, 27)
    prefix = -np.arange(1, 4)[:, None].repeat(27, 1).astype(np.float32)[::-1]  # rows -3, -2, -1
    hist = state_histories(states, steps=8, prefix=prefix)
    assert hist.shape == (4, 8, 27)
    # frame 0: the earliest prefix state repeated, the prefix, then the frame itself
    np.testing.assert_array_equal(hist[0, :, 0], [-3, -3, -3, -3, -3, -2, -1, states[0, 0]])
    np.testing.assert_array_equal(hist[2, -3:], states[:3])
    # without a prefix: the first state repeated (LeRobot's padding), as before
    np.testing.assert_array_equal(state_histories(states, steps=8)[0], np.repeat(states[:1], 8, 0))
    # a prefix longer than T - 1 keeps its last T - 1 states
    long = np.full((20, 27), 7.0, np.float32)
    long[-7:] = 5.0
    np.testing.assert_array_equal(state_histories(states, steps=8, prefix=long)[0, :7, 0], [5.0] * 7)


def test_relabel_steps_spread_over_the_rollout_and_skip_the_contact_state():
    rollout = Rollout(np.zeros((61, 27)), np.zeros((61, 7)), "collision", steps=60)
    steps = relabel_steps(rollout, 3, 2, np.random.default_rng(0))
    assert len(steps) == 3 and steps == sorted(steps)
    assert steps[0] <= 21 and steps[-1] >= 40 and max(steps) <= 59  # one per third; step 60 touched something
    short = Rollout(np.zeros((3, 27)), np.zeros((3, 7)), "success", steps=2)
    assert relabel_steps(short, 3, 2, np.random.default_rng(0)) == [2]


def test_failure_relabels_come_from_the_last_second_of_a_failed_rollout():
    failed = Rollout(np.zeros((101, 27)), np.zeros((101, 7)), "collision", steps=100)
    steps = relabel_steps(failed, 1, 2, np.random.default_rng(0), failure_count=5)
    assert len(steps) == 5 and len(set(steps)) == 5
    assert min(steps) >= 99 - FAILURE_WINDOW_STEPS + 1 and max(steps) <= 99  # before the contact state
    timeout = Rollout(np.zeros((151, 27)), np.zeros((151, 7)), "timeout", steps=150)
    assert min(relabel_steps(timeout, 1, 2, np.random.default_rng(0), failure_count=5)) > 150 - FAILURE_WINDOW_STEPS
    success = Rollout(np.zeros((101, 27)), np.zeros((101, 7)), "success", steps=100)
    assert len(relabel_steps(success, 1, 2, np.random.default_rng(0), failure_count=5)) == 1


def test_drift_window_starts_where_a_runaway_turned_away():
    # closest to the pre-grasp at step 30, then running off until the time limit
    distances = np.concatenate([np.linspace(1.0, 0.2, 31), np.linspace(0.25, 2.0, 120)])
    runaway = Rollout(np.zeros((151, 27)), np.zeros((151, 7)), "timeout", steps=150, distances=distances)
    steps = relabel_steps(runaway, 1, 2, np.random.default_rng(0), failure_count=4, failure_window="drift")
    assert len(steps) == 4 and min(steps) >= 30 and max(steps) <= 30 + FAILURE_WINDOW_STEPS - 1
    # the last-second window for the same rollout: far off already
    assert min(relabel_steps(runaway, 1, 2, np.random.default_rng(0), 4, "last")) > 150 - FAILURE_WINDOW_STEPS
    # a rollout that got closest at its end (a stall, a contact on the way in): the last second either way
    stall = Rollout(np.zeros((151, 27)), np.zeros((151, 7)), "timeout", steps=150, distances=np.linspace(1, 0.1, 151))
    assert min(relabel_steps(stall, 1, 2, np.random.default_rng(0), 4, "drift")) > 150 - FAILURE_WINDOW_STEPS
    with pytest.raises(ValueError, match="distances"):
        relabel_steps(Rollout(np.zeros((151, 27)), np.zeros((151, 7)), "timeout", steps=150), 1, 2,
                      np.random.default_rng(0), 4, "drift")
    with pytest.raises(ValueError, match="unknown failure_window 'middle'"):
        DaggerConfig(output="d", failure_window="middle")


def test_unknown_driver_names_the_known_ones(tmp_path):
    assert parse_driver("prior") == ("prior", None)
    assert parse_driver("RTV3:single-dof") == ("rtv3", "single_dof")
    assert parse_driver("ho:noisy") == ("ho", "noisy")
    with pytest.raises(ValueError, match="METHOD:USER"):
        parse_driver("oracle:noisy")  # told the goal: not a driver
    with pytest.raises(ValueError, match="noisy"):
        DaggerConfig(output=tmp_path / "d", drivers=("direct:sleepy",))


def test_rtv3_drivers_run_the_presets_fusion_and_a_round_records_it(tmp_path):
    parser = argparse.ArgumentParser()
    add_arguments(parser)
    paper = dagger_config(parser.parse_args(["--output", str(tmp_path / "d"), "--preset", "paper"]))
    easy = dagger_config(parser.parse_args(["--output", str(tmp_path / "d"), "--preset", "easy"]))
    assert (paper.fusion, easy.fusion) == ("tuned_ycb", "tuned")
    assert (paper.objects, paper.scene_type) == ("ycb", "packed_ycb")
    # A round made with another fusion relabels other states: resuming it under this one is refused.
    assert paper.settings(512, 64)["fusion"] == "tuned_ycb"
    assert "fusion" not in easy.settings(512, 64)  # rounds made before the option resume unchanged
    with pytest.raises(ValueError, match="unknown fusion preset 'gentle'.*tuned_ycb"):
        DaggerConfig(output=tmp_path / "d", fusion="gentle")


@pytest.mark.sim
def test_relabelled_episode_keeps_the_rollout_history_and_the_experts_actions(tmp_path):
    """A Direct rollout of the ideal user, relabelled at a visited step: the stored episode starts at the
    visited state, its history holds the rollout's states before it, its actions are the expert's plan,
    and the rollout's own frames never become dataset frames."""
    from lerobot.datasets.lerobot_dataset import LeRobotDataset

    from rtv3_maniskill.datagen.dagger import DaggerCollector, rollout_variant
    from rtv3_maniskill.datagen.lerobot_export import StagingArea, export_lerobot_dataset
    from rtv3_maniskill.features import REPO_ID
    from rtv3_maniskill.policies.rtv3 import load_policy

    policy = load_policy()
    config = DaggerConfig(output=tmp_path / "dagger", drivers=("direct:ideal",), scene_type="packed")
    collector = DaggerCollector(config, policy)
    try:
        goals = collector.load_scene(500001)
        assert goals, "the scene has feasible goals"
        rollout = collector.rollout(goals[0], "direct:ideal", seed=1)
        assert rollout.outcome == "success" and rollout.steps >= 12
        assert len(rollout.states) == len(rollout.distances) == rollout.steps + 1
        assert rollout.distances[-1] < 0.5 * rollout.distances[0]  # the ideal user closes in on the pre-grasp
        step = 10
        episode = collector.relabel(rollout, goals[0], step, seed=2)
        assert not isinstance(episode, str), episode
    finally:
        collector.close()
    np.testing.assert_array_equal(episode.state[0], rollout.states[step])
    np.testing.assert_array_equal(episode.history_prefix, rollout.states[step - 7 : step])
    # the expert's actions: a plan from the visited state to the pre-grasp, ending at rest
    assert np.abs(episode.action[-1]).max() == 0.0 and np.abs(episode.action[:5]).max() > 1e-3
    assert episode.info["dagger"]["step"] == step

    config.output.mkdir(parents=True)
    with StagingArea(config.output, settings=config.settings(policy.config.num_points,
                                                             policy.config.max_grasps)) as staging:
        staging.save(episode, variant=rollout_variant(0, step))
        staging.log_attempt(episode.scene_seed, episode.target_grasp_index, "success", len(episode.state),
                            variant=rollout_variant(0, step))
    frames = export_lerobot_dataset(config.output, policy.config.num_points, policy.config.max_grasps,
                                    progress=False)
    assert frames == len(episode.state)  # no rollout frame is a frame (an action target)
    ds = LeRobotDataset(REPO_ID, root=config.output)
    first = features.unflatten(features.STATE_HISTORY, ds[0][features.STATE_HISTORY].numpy())
    np.testing.assert_allclose(first[:-1], rollout.states[step - 7 : step], atol=1e-6)
    np.testing.assert_allclose(ds[0][features.ACTION].numpy(), episode.action[0], atol=1e-6)
    assert json.loads((config.output / "rtv3_generation.json").read_text())["source"] == "dagger"
