"""The paper preset: YCB-sized objects, the authors' packed layout, their goal rule and execution."""

from __future__ import annotations

import argparse
import csv
import json
from pathlib import Path

import numpy as np
import pytest

from rtv3_maniskill.cli.scene_args import add_scene_arguments, scene_settings
from rtv3_maniskill.presets import PRESETS, get_preset
from rtv3_maniskill.robot.execution import EXECUTIONS
from rtv3_maniskill.robot.scene_geometry import WORKSPACE_CENTER
from rtv3_maniskill.tasks.object_library import make_object_set
from rtv3_maniskill.tasks.scene_generation import (
    PACKED_YCB_HALF_RANGE,
    PACKED_YCB_SCALE,
    _SettleScene,
    generate_layout,
)
from rtv3_maniskill.tasks.ycb_objects import YCB_BOXES, YCB_CYLINDERS, YCB_NAMES, YcbObjectSet, make_ycb_object


@pytest.mark.parametrize("name", YCB_NAMES)
def test_ycb_objects_have_their_nominal_size_and_stand_on_the_table(name):
    obj = make_ycb_object(name, scale=0.8)
    lo, hi = obj.collision_mesh().bounds
    assert lo[2] == pytest.approx(0.0, abs=1e-9)  # standing on z = 0
    assert (lo[:2] + hi[:2]) == pytest.approx([0.0, 0.0], abs=0.02)  # footprint around the origin
    extent = hi - lo
    if name in YCB_BOXES:
        assert extent == pytest.approx(0.8 * np.array(YCB_BOXES[name]), abs=1e-6)
    elif name in YCB_CYLINDERS:
        radius, height = YCB_CYLINDERS[name]
        assert extent[2] == pytest.approx(0.8 * height, abs=1e-6)
        assert extent[:2] == pytest.approx([1.6 * radius] * 2, rel=0.02)
    assert all(shape.kind in ("box", "cylinder") for shape in obj.shapes)  # convex parts


def test_ycb_object_source_and_its_errors():
    assert isinstance(make_object_set("ycb"), YcbObjectSet)
    assert make_object_set("ycb:mug,chips_can").names == ("mug", "chips_can")
    with pytest.raises(ValueError, match="unknown YCB objects.*'banana'"):
        make_object_set("ycb:mug,banana")
    with pytest.raises(FileNotFoundError, match="does not exist"):
        make_object_set("/no/such/ycb/models")
    picks = YcbObjectSet().sample_distinct(np.random.default_rng(0), 4, 0.8)
    assert len({o.name for o in picks}) == 4


def test_packed_ycb_scenes_follow_the_authors_rules():
    objects = make_object_set("ycb")
    for seed in range(6):
        layout = generate_layout(objects, np.random.default_rng(800000 + seed), "packed_ycb")
        names = [o.name for o in layout.objects]
        assert 3 <= len(names) <= 4 and len(set(names)) == len(names)  # distinct, at least 3 kept
        sim = _SettleScene()
        for obj, pose in zip(layout.objects, layout.object_poses):
            assert pose[:3, 2] == pytest.approx([0, 0, 1], abs=0.02)  # upright
            assert np.abs(pose[:2, 3] - WORKSPACE_CENTER[:2]).max() <= PACKED_YCB_HALF_RANGE + 0.01  # in the region
            assert pose[2, 3] == pytest.approx(0.0, abs=0.003)  # resting on the table
            base = make_ycb_object(obj.name, PACKED_YCB_SCALE)  # the authors' global scale
            assert obj.collision_mesh().extents == pytest.approx(base.collision_mesh().extents)
            sim.add(obj, pose)
        assert not any(sim.penetrates(actor, tolerance=1e-3) for actor in sim.actors)  # no contact between objects


def _args(*argv: str) -> argparse.Namespace:
    parser = argparse.ArgumentParser()
    add_scene_arguments(parser)
    return parser.parse_args(list(argv))


def test_presets_set_the_scene_execution_contacts_and_goals_and_options_override_them():
    paper = get_preset("paper")
    assert (paper.scene_type, paper.object_source, paper.goals) == ("packed_ycb", "ycb", "all")
    assert paper.execution in EXECUTIONS and PRESETS["easy"].goals == "reachable"
    assert scene_settings(_args("--preset", "paper")) == paper.env_kwargs()
    settings = scene_settings(_args("--preset", "paper", "--objects", "procedural", "--self-contacts", "count"))
    assert settings["object_source"] == "procedural" and settings["self_contacts"] is True
    assert settings["scene_type"] == "packed_ycb"
    with pytest.raises(ValueError, match="unknown preset 'hard'"):
        get_preset("hard")


def test_each_preset_runs_rtv3_with_its_own_fusion_and_fusion_overrides_it():
    from rtv3_maniskill.benchmarks.shared_config import BenchmarkConfig
    from rtv3_maniskill.cli.benchmark_shared import add_arguments, config_settings, shared_control_overrides
    from rtv3_maniskill.shared_control.config import FUSION_PRESETS, SharedControlConfig

    assert (PRESETS["paper"].fusion, PRESETS["easy"].fusion) == ("tuned_ycb", "tuned")
    tuned, ycb = SharedControlConfig.preset("tuned"), SharedControlConfig.preset("tuned_ycb")
    assert (tuned.prior_covariance_scale, ycb.prior_covariance_scale) == (100.0, 30.0)
    assert {k: v for k, v in vars(ycb).items() if k != "prior_covariance_scale"} == {
        k: v for k, v in vars(tuned).items() if k != "prior_covariance_scale"}
    assert all(p.fusion in FUSION_PRESETS for p in PRESETS.values())
    assert "fusion" not in PRESETS["paper"].env_kwargs()

    parser = argparse.ArgumentParser()
    add_arguments(parser)

    def fusion(*argv: str) -> tuple[str, float]:
        args = parser.parse_args(list(argv))
        config = BenchmarkConfig(**config_settings(args), **scene_settings(args),
                                 shared_control=shared_control_overrides(args))
        return config.fusion, config.shared_control_config(0.3, 1.2).prior_covariance_scale

    assert fusion("--preset", "paper") == ("tuned_ycb", 30.0)
    assert fusion("--preset", "easy") == ("tuned", 100.0)
    assert fusion("--preset", "paper", "--fusion", "paper") == ("paper", 1.0)
    assert fusion("--preset", "paper", "--prior-covariance-scale", "100") == ("tuned_ycb", 100.0)


@pytest.mark.parametrize("command", ["demo", "teleop", "dagger"])
def test_commands_running_rtv3_take_the_presets_fusion_and_fusion_overrides_it(command, tmp_path):
    from rtv3_maniskill.cli import main
    from rtv3_maniskill.cli.dagger import add_arguments as dagger_arguments
    from rtv3_maniskill.cli.demo import add_arguments as demo_arguments
    from rtv3_maniskill.cli.scene_args import fusion_name
    from rtv3_maniskill.cli.teleop import add_arguments as teleop_arguments

    parser = argparse.ArgumentParser()
    dict(demo=demo_arguments, teleop=teleop_arguments, dagger=dagger_arguments)[command](parser)
    required = ["--output", str(tmp_path / "d")] if command == "dagger" else []

    def fusion(*argv: str) -> str:
        return fusion_name(parser.parse_args([*required, *argv]))

    assert fusion("--preset", "paper") == "tuned_ycb"
    assert fusion("--preset", "easy") == "tuned"
    assert fusion("--preset", "paper", "--fusion", "paper") == "paper"
    # An unknown name stops the command before it builds a scene, with the known names in the message.
    extra = dict(demo=["--no-video"], teleop=["--headless", "--input", "simulated:noisy"], dagger=[])[command]
    with pytest.raises(SystemExit, match="unknown fusion preset 'gentle'; known: tuned, tuned_ycb, paper"):
        main([command, *required, *extra, "--fusion", "gentle"])


@pytest.mark.parametrize("command", ["demo", "teleop", "dagger", "evaluate"])
def test_commands_running_rtv3_take_the_presets_checkpoint_and_policy_path_overrides_it(command, tmp_path):
    from rtv3_maniskill.cli.dagger import add_arguments as dagger_arguments
    from rtv3_maniskill.cli.demo import add_arguments as demo_arguments
    from rtv3_maniskill.cli.evaluate import add_arguments as evaluate_arguments
    from rtv3_maniskill.cli.scene_args import policy_path
    from rtv3_maniskill.cli.teleop import add_arguments as teleop_arguments
    from rtv3_maniskill.policies.rtv3.checkpoints import CHECKPOINT_FILES

    for preset in PRESETS.values():
        assert all((preset.policy_path / name).is_file() for name in CHECKPOINT_FILES), preset
        assert "checkpoint" not in preset.env_kwargs()
    parser = argparse.ArgumentParser()
    dict(demo=demo_arguments, teleop=teleop_arguments, dagger=dagger_arguments, evaluate=evaluate_arguments)[command](
        parser)
    required = dict(dagger=["--output", str(tmp_path / "d")], evaluate=["planning"]).get(command, [])
    for name, preset in PRESETS.items():
        assert policy_path(parser.parse_args([*required, "--preset", name])) == preset.policy_path
    assert policy_path(parser.parse_args([*required, "--preset", "paper", "--policy.path", str(tmp_path)])) == tmp_path


def test_the_shared_control_benchmark_takes_the_presets_checkpoint():
    from rtv3_maniskill.cli.benchmark_shared import add_arguments, config_settings

    parser = argparse.ArgumentParser()
    add_arguments(parser)
    for name, preset in PRESETS.items():
        assert config_settings(parser.parse_args(["--preset", name]))["policy_path"] == preset.policy_path
    assert config_settings(parser.parse_args(["--policy.path", "elsewhere"]))["policy_path"] == Path("elsewhere")


@pytest.mark.sim
def test_tracked_execution_moves_the_arm_by_three_quarters_of_the_command():
    import gymnasium as gym

    import rtv3_maniskill  # noqa: F401

    moved = {}
    for execution in ("capped", "tracked"):
        env = gym.make("GraspClutter-v1", obs_mode="state_dict", control_mode="pd_ee_twist", render_backend="none",
                       execution=execution, scene_type="packed_ycb", object_source="ycb")
        env.reset(seed=800001)
        start = env.unwrapped.tcp_pose_matrix[0, :3, 3].clone()
        for _ in range(10):
            env.step(np.array([0.0, 0.0, -0.2, 0.0, 0.0, 0.0, 1.0], dtype=np.float32))
        moved[execution] = float((env.unwrapped.tcp_pose_matrix[0, :3, 3] - start).norm())
        env.close()
    assert moved["capped"] == pytest.approx(0.1, rel=0.15)  # 10 steps of 0.2 m/s at 20 Hz
    assert moved["tracked"] / moved["capped"] == pytest.approx(0.75, abs=0.05)


@pytest.mark.sim
def test_a_small_paper_preset_benchmark_runs_every_candidate_and_counts_both_goal_rules(tmp_path):
    from rtv3_maniskill.cli import main

    out = tmp_path / "bench"
    assert main(["benchmark-shared", "--preset", "paper", "--seed", "8", "--scenes", "1", "--goals-per-scene", "2",
                 "--users", "ideal", "--methods", "direct,oracle,oracle-plan", "--output", str(out),
                 "--no-progress"]) == 0
    config = json.loads((out / "config.json").read_text())
    assert config["goals"] == "all" and config["object_source"] == "ycb" and config["scene_type"] == "packed_ycb"
    with open(out / "results.csv") as f:
        rows = list(csv.DictReader(f))
    assert len(rows) == 6 and {r["method"] for r in rows} == {"direct", "oracle", "oracle_plan"}
    summary = (out / "summary.md").read_text()
    assert "rule `all`" in summary and "pass the arm-reach check" in summary and "| Oracle (plan) |" in summary


def test_packed_ycb_takes_a_ycb_style_mesh_folder_with_distinct_objects(tmp_path):
    """ManiSkill's YCB folder holds `<id>/textured.obj` (and collision meshes, skipped): objects are named by folder."""
    import trimesh

    for i, name in enumerate(("002_master_chef_can", "003_cracker_box", "004_sugar_box", "005_tomato_soup_can")):
        (tmp_path / name).mkdir()
        trimesh.creation.box(extents=[0.05, 0.05 + 0.005 * i, 0.10]).export(tmp_path / name / "textured.obj")
        trimesh.creation.box(extents=[0.05, 0.05, 0.10]).export(tmp_path / name / "collision.obj")
    layout = generate_layout(make_object_set(str(tmp_path)), np.random.default_rng(0), "packed_ycb")
    names = [o.name for o in layout.objects]
    assert len(names) >= 3 and len(set(names)) == len(names) and all(n[:3].isdigit() for n in names)
