"""GraspClutter-v1 behaves as a ManiSkill task users can rely on (CPU backend, one env)."""

from __future__ import annotations

import gymnasium as gym
import numpy as np
import pytest
import torch

import rtv3_maniskill  # noqa: F401  (registers the task)
from rtv3_maniskill import se3
from rtv3_maniskill.features import DEFAULT_MAX_GRASPS, GRASP_DIM

N_POINTS = 512


def make(**kwargs):
    kwargs.setdefault("obs_mode", "state_dict")
    kwargs.setdefault("control_mode", "pd_ee_twist")
    kwargs.setdefault("num_points", N_POINTS)
    return gym.make("GraspClutter-v1", **kwargs)


@pytest.fixture(scope="module")
def env():
    e = make()
    yield e
    e.close()


def _check_extra(extra: dict, num_points: int):
    assert extra["tcp_pose"].shape == (1, 7)
    assert extra["tcp_twist"].shape == (1, 6)
    assert extra["grasps"].shape == (1, DEFAULT_MAX_GRASPS, GRASP_DIM)
    assert extra["grasps_mask"].shape == (1, DEFAULT_MAX_GRASPS)
    assert extra["point_cloud"].shape == (1, num_points, 6)
    assert extra["point_cloud_mask"].shape == (1, num_points)
    mask = extra["point_cloud_mask"][0] > 0
    assert mask.sum() > 50, "the cloud should hold real points"
    points = extra["point_cloud"][0][mask]
    # Cropped to the workspace above the table: no table, floor or robot base points.
    assert (points[:, 2] > 0.0).all() and (points[:, 2] < 0.31).all()
    assert (points[:, 3:] >= 0).all() and (points[:, 3:] <= 1).all()
    assert (extra["point_cloud"][0][~mask] == 0).all()
    assert extra["grasps_mask"][0].sum() >= 1


@pytest.mark.sim
def test_state_dict_observation(env):
    obs, info = env.reset(seed=1)
    assert obs["agent"]["qpos"].shape == (1, 9)
    _check_extra(obs["extra"], N_POINTS)
    for key in ("success", "is_success", "collision", "pregrasp_distance", "target_grasp_index"):
        assert key in info


@pytest.mark.sim
def test_state_observation_is_flat_vector():
    e = make(obs_mode="state")
    obs, _ = e.reset(seed=1)
    assert obs.ndim == 2 and obs.shape[0] == 1
    assert obs.shape[1] > N_POINTS * 6
    assert e.observation_space.shape == obs.shape
    e.close()


@pytest.mark.sim
def test_pointcloud_observation_is_rendered_and_cropped():
    e = make(obs_mode="pointcloud")
    obs, _ = e.reset(seed=1)
    _check_extra(obs["extra"], N_POINTS)
    # Rendered cloud: points lie near the object surfaces of the scene's layout.
    layout = e.unwrapped.layouts[0]
    points = obs["extra"]["point_cloud"][0][obs["extra"]["point_cloud_mask"][0] > 0][:, :3].numpy()
    import trimesh

    meshes = trimesh.util.concatenate(layout.world_meshes())
    _, distance, _ = trimesh.proximity.closest_point(meshes, points)
    assert np.median(distance) < 0.005
    e.close()


@pytest.mark.sim
def test_same_seed_same_scene_and_grasps(env):
    _, info_a = env.reset(seed=7)
    base = env.unwrapped
    poses_a = base.layouts[0].object_poses.copy()
    names_a = [o.name for o in base.layouts[0].objects]
    grasps_a = base.grasps.clone()
    _, info_b = env.reset(seed=8)
    assert not torch.equal(base.grasps, grasps_a) or names_a != [o.name for o in base.layouts[0].objects]
    _, info_c = env.reset(seed=7)
    np.testing.assert_allclose(base.layouts[0].object_poses, poses_a)
    assert [o.name for o in base.layouts[0].objects] == names_a
    assert torch.equal(base.grasps, grasps_a)
    assert int(info_a["target_grasp_index"]) == int(info_c["target_grasp_index"])


@pytest.mark.sim
def test_grasps_spread_over_objects(env):
    spread = []
    for seed in range(4):
        env.reset(seed=100 + seed, options=dict())
        grasp_set = env.unwrapped.grasp_sets[0]
        if len(env.unwrapped.layouts[0].objects) >= 2:
            spread.append(len(np.unique(grasp_set.object_ids)))
    assert spread and max(spread) >= 2


@pytest.mark.sim
def test_target_grasp_settable_and_validated(env):
    _, info = env.reset(seed=3, options=dict(target_grasp_index=0))
    assert int(info["target_grasp_index"]) == 0
    count = int(env.unwrapped.grasps_mask[0].sum())
    with pytest.raises(ValueError, match="target_grasp_index"):
        env.reset(seed=3, options=dict(target_grasp_index=count + 5))


@pytest.mark.sim
def test_twist_control_tracks_command_in_free_space(env):
    env.reset(seed=2)
    command = torch.tensor([[0.08, -0.04, 0.06, 0.3, -0.2, 0.4, 0.0]])
    start = env.unwrapped.tcp_pose_matrix.clone()
    twists = []
    for _ in range(12):
        obs, *_ = env.step(command)
        twists.append(obs["extra"]["tcp_twist"][0])
    twists = torch.stack(twists[3:])
    np.testing.assert_allclose(twists.median(0).values.numpy(), command[0, :6].numpy(), atol=0.01)
    # Integrating the realised body twists reproduces the reached pose (frames agree).
    end = env.unwrapped.tcp_pose_matrix
    assert not torch.allclose(start, end)


@pytest.mark.sim
def test_twist_speed_limits(env):
    env.reset(seed=2)
    for _ in range(8):
        obs, *_ = env.step(torch.tensor([[5.0, 0, 0, 0, 0, 0, 0.0]]))
    assert obs["extra"]["tcp_twist"][0, :3].norm() < 0.33


def _drive_to(env, goal_fn, steps: int, gain: float = 3.0):
    info = None
    for _ in range(steps):
        current = env.unwrapped.tcp_pose_matrix
        twist = gain * se3.se3_log(se3.relative_transform(current, goal_fn()))
        obs, _, _, _, info = env.step(torch.cat([twist, torch.zeros(1, 1)], -1).float())
        if bool(info["success"]):
            break
    return info


@pytest.mark.sim
def test_success_when_driven_to_target_pregrasp(env):
    # Choose the highest pre-grasp (clear approach) and drive there in twist control.
    env.reset(seed=5)
    base = env.unwrapped
    count = int(base.grasps_mask[0].sum())
    offset = torch.eye(4)
    offset[2, 3] = -0.05
    heights = (base.grasp_poses[0, :count] @ offset)[:, 2, 3]
    target = int(heights.argmax())
    _, info = env.reset(seed=5, options=dict(target_grasp_index=target))
    assert not bool(info["success"])
    info = _drive_to(env, lambda: base.target_pregrasp_pose, 150)
    assert bool(info["success"]), f"pregrasp distance {float(info['pregrasp_distance']):.3f}"


@pytest.mark.sim
def test_collision_when_driven_into_table(env):
    env.reset(seed=6)
    assert env.unwrapped.robot_contact_kinds() == [set()]
    collided = False
    # Sideways out of the 30 cm workspace (the objects stay inside it), then straight down; world-frame
    # velocities expressed in the TCP body frame.
    for step in range(150):
        rot = env.unwrapped.tcp_pose_matrix[0, :3, :3]
        v_body = rot.T @ torch.tensor([0.0, 0.25, 0.0] if step < 25 else [0.0, 0.0, -0.25])
        _, _, _, _, info = env.step(torch.cat([v_body, torch.zeros(4)])[None])
        if bool(info["collision"]):
            collided = True
            break
    assert collided
    assert env.unwrapped.robot_contact_kinds() == [{"table"}]


@pytest.mark.sim
def test_contact_of_the_arm_with_itself_is_told_apart(env):
    # Down and back towards the base: the elbow folds onto the shoulder before the hand meets anything.
    env.reset(seed=6)
    for _ in range(120):
        rot = env.unwrapped.tcp_pose_matrix[0, :3, :3]
        v_body = rot.T @ torch.tensor([-0.15, 0.0, -0.25])
        _, _, _, _, info = env.step(torch.cat([v_body, torch.zeros(4)])[None])
        if bool(info["collision"]):
            break
    assert bool(info["collision"])
    assert env.unwrapped.robot_contact_kinds() == [{"self"}]


@pytest.mark.sim
def test_nan_action_rejected(env):
    env.reset(seed=0)
    with pytest.raises(ValueError, match="NaN"):
        env.step(torch.tensor([[float("nan"), 0, 0, 0, 0, 0, 0]]))


@pytest.mark.parametrize(
    "kwargs, message",
    [
        (dict(scene_type="tower"), "scene_type"),
        (dict(num_points=0), "num_points"),
        (dict(max_grasps=-1), "max_grasps"),
        (dict(num_objects=0), "num_objects"),
    ],
)
def test_bad_options_raise_clear_errors(kwargs, message):
    with pytest.raises(ValueError, match=message):
        make(**kwargs)


def test_empty_object_folder_is_a_clear_error(tmp_path):
    with pytest.raises(FileNotFoundError, match="no mesh files"):
        make(object_source=str(tmp_path))
    with pytest.raises(FileNotFoundError, match="does not exist"):
        make(object_source=str(tmp_path / "missing"))


@pytest.mark.sim
def test_mesh_folder_objects(tmp_path):
    import trimesh

    trimesh.creation.annulus(r_min=0.02, r_max=0.035, height=0.05).export(tmp_path / "ring.obj")
    trimesh.creation.box(extents=[40.0, 50.0, 60.0]).export(tmp_path / "box_in_mm.stl")
    e = make(object_source=str(tmp_path), num_objects=2)
    e.reset(seed=0)
    layout = e.unwrapped.layouts[0]
    assert {o.name for o in layout.objects} <= {"ring", "box_in_mm"}
    for obj in layout.objects:
        assert obj.collision_mesh().extents.max() < 0.15  # millimetre files are rescaled
    e.close()


@pytest.mark.sim
def test_rendered_point_cloud_is_reproducible_by_seed():
    # 64 slots for a few hundred visible points: the cloud is resampled. Two envs reset with the
    # same seed give the same cloud, whatever torch's global random state is.
    clouds = []
    for global_seed in (1, 2):
        e = make(obs_mode="pointcloud", num_points=64)
        torch.manual_seed(global_seed)
        obs, _ = e.reset(seed=11)
        assert bool((obs["extra"]["point_cloud_mask"] > 0).all()), "expected more visible points than slots"
        clouds.append(obs["extra"]["point_cloud"][0].clone())
        e.close()
    torch.testing.assert_close(clouds[0], clouds[1], atol=0, rtol=0)
