"""Tests of the expert motion planner (OMPL + Pinocchio + TOPP-RA) on ManiSkill's Panda."""

from __future__ import annotations

import coal
import numpy as np
import pytest
import trimesh
from scipy.spatial.transform import Rotation

from rtv3_maniskill.robot.collision_world import CollisionMargins, PandaCollisionWorld
from rtv3_maniskill.robot.panda_hand import panda_asset_dir
from rtv3_maniskill.robot.panda_model import REST_QPOS, PandaKinematics
from rtv3_maniskill.robot.planner import PandaPlanner
from rtv3_maniskill.robot.planner_config import PlannerConfig, with_clearance
from rtv3_maniskill.robot.scene_geometry import (
    READY_QPOS,
    ROBOT_BASE_POSITION,
    CollisionShape,
    ObjectGeometry,
    SceneGeometry,
)
from rtv3_maniskill.robot.trajectory import FAILURE_REASONS

TOP_DOWN = np.diag([1.0, -1.0, -1.0])
"""TCP rotation pointing the approach (z) axis straight down."""


def tcp_pose(position, rotation=TOP_DOWN) -> np.ndarray:
    pose = np.eye(4)
    pose[:3, :3] = rotation
    pose[:3, 3] = position
    return pose


def rotation_error(a: np.ndarray, b: np.ndarray) -> float:
    """Angle (rad) of the relative rotation of two poses, accurate for small angles."""
    rel = np.asarray(a, dtype=np.float64)[:3, :3].T @ np.asarray(b, dtype=np.float64)[:3, :3]
    return float(Rotation.from_matrix(rel).magnitude())


def box_object(name: str, half_size, position) -> tuple[ObjectGeometry, np.ndarray]:
    pose = np.eye(4)
    pose[:3, 3] = position
    half = np.asarray(half_size, dtype=float)
    return ObjectGeometry(name, [CollisionShape("box", tuple(half))], trimesh.creation.box(extents=2 * half)), pose


def scene_of(*objects) -> SceneGeometry:
    return SceneGeometry([o for o, _ in objects], np.stack([p for _, p in objects]))


@pytest.fixture(scope="module")
def kinematics() -> PandaKinematics:
    return PandaKinematics()


@pytest.fixture(scope="module")
def wall_planner(kinematics) -> PandaPlanner:
    """A 20 cm tall, 20 cm long, 4 cm thick wall across the workspace at y = 0."""
    return PandaPlanner(scene_of(box_object("wall", (0.1, 0.02, 0.1), (0.0, 0.0, 0.1))), kinematics=kinematics)


# ---------------------------------------------------------------------- kinematics


def _sapien_panda():
    """ManiSkill's Panda URDF loaded into a bare SAPIEN physics scene (no renderer needed)."""
    sapien = pytest.importorskip("sapien")
    try:
        scene = sapien.Scene([sapien.physx.PhysxCpuSystem()])
        loader = scene.create_urdf_loader()
        builders, _, _ = loader.parse(str(panda_asset_dir() / "panda_v2.urdf"))
        for link_builder in builders[0].link_builders:
            link_builder.visual_records = []  # visuals need a Vulkan device; physics does not
        robot = builders[0].build(fix_root_link=True)
    except RuntimeError as exc:  # pragma: no cover - depends on the machine
        pytest.skip(f"SAPIEN cannot create a physics scene here: {exc}")
    robot.set_root_pose(sapien.Pose(ROBOT_BASE_POSITION.tolist()))
    return scene, robot


def test_fk_matches_sapien_and_tcp_axes(kinematics):
    _, robot = _sapien_panda()
    links = {link.name: link for link in robot.get_links()}
    rng = np.random.default_rng(0)
    configs = [REST_QPOS] + [kinematics.random_configuration(rng) for _ in range(5)]
    for q in configs:
        robot.set_qpos(np.concatenate([q, [0.04, 0.04]]).astype(np.float32))
        sapien_tcp = links["panda_hand_tcp"].entity_pose.to_transformation_matrix()
        ours = kinematics.forward_kinematics(q)
        assert np.abs(ours[:3, 3] - sapien_tcp[:3, 3]).max() < 1e-5
        assert rotation_error(ours, sapien_tcp) < 1e-5
        # z = approach axis: from the hand towards the fingertips.
        hand = links["panda_hand"].entity_pose.to_transformation_matrix()
        approach = ours[:3, 3] - hand[:3, 3]
        assert np.allclose(approach / np.linalg.norm(approach), ours[:3, 2], atol=1e-5)
        # y = closing axis: the open fingers sit at +-4 cm along it.
        left = links["panda_leftfinger"].entity_pose.p
        right = links["panda_rightfinger"].entity_pose.p
        assert np.allclose(left - right, 0.08 * ours[:3, 1], atol=1e-5)
    # The authors' placement: the ready pose holds the TCP 0.34 m above the table at the
    # workspace's near edge (x = -0.20 in the world), pointing down.
    ready = kinematics.forward_kinematics(READY_QPOS)
    assert np.allclose(ready[:3, 3], [-0.193, 0.0, 0.337], atol=2e-3)
    assert np.allclose(ready[:3, 2], [0.0, 0.0, -1.0], atol=1e-6)


def test_ik_round_trip(kinematics):
    planner = PandaPlanner(None, kinematics=kinematics)
    rng = np.random.default_rng(1)
    targets = []
    while len(targets) < 8:
        q = kinematics.random_configuration(rng, margin=0.1)
        if planner.is_collision_free(q):
            targets.append(kinematics.forward_kinematics(q))
    for i, target in enumerate(targets):
        q = planner.solve_ik(target, REST_QPOS, seed=i)
        assert q is not None
        reached = kinematics.forward_kinematics(q)
        assert np.linalg.norm(reached[:3, 3] - target[:3, 3]) < 1e-3
        assert rotation_error(reached, target) < 1e-3
        assert kinematics.within_limits(q)
        assert planner.is_collision_free(q)
    sols = planner.solve_ik_solutions(targets[0], REST_QPOS, num_solutions=3, seed=0).solutions
    assert len(sols) >= 2
    assert np.abs(sols[0] - sols[1]).max() > planner.config.ik_min_separation


def test_scene_shapes_follow_scene_geometry_conventions(kinematics):
    """coal versions of box/sphere/cylinder/capsule/convex shapes occupy the same space as the scene's trimesh."""
    rot = trimesh.transformations.rotation_matrix(0.7, [0.3, 0.5, 0.8])
    local = trimesh.transformations.rotation_matrix(0.4, [1.0, 0.0, 0.0])
    local[:3, 3] = [0.01, -0.02, 0.03]
    rng = np.random.default_rng(2)
    shapes = [
        CollisionShape("box", (0.05, 0.02, 0.03), local),
        CollisionShape("sphere", (0.03,), local),
        CollisionShape("cylinder", (0.02, 0.06), local),
        CollisionShape("capsule", (0.015, 0.05), local),
        CollisionShape("convex", (), local, rng.uniform(-0.04, 0.04, size=(20, 3))),
    ]
    for i, shape in enumerate(shapes):
        pose = rot.copy()
        pose[:3, 3] = [0.1 * i - 0.2, 0.3, 0.2]
        obj = ObjectGeometry(shape.kind, [shape], shape.to_trimesh())
        world = PandaCollisionWorld(kinematics, SceneGeometry([obj], pose[None]))
        gid = world.object_geometry_ids[0][0]
        geom = world.geometry.geometryObjects[gid]
        placement = coal.Transform3s(geom.placement.rotation, geom.placement.translation)
        mesh = shape.to_trimesh()
        mesh.apply_transform(pose)
        centre = mesh.vertices.mean(0)
        probe = coal.Sphere(1e-4)
        for vertex in mesh.vertices[:: max(1, len(mesh.vertices) // 40)]:
            for scale, inside in ((0.9, True), (1.1, False)):
                point = centre + scale * (vertex - centre)
                res = coal.DistanceResult()
                coal.distance(geom.geometry, placement, probe, coal.Transform3s(np.eye(3), point),
                              coal.DistanceRequest(), res)
                assert (res.min_distance <= 1e-4) == inside, (shape.kind, scale)


# ---------------------------------------------------------------------- free-space planning


def dense_collision_free(world: PandaCollisionWorld, qs: np.ndarray, step: float = 1e-3) -> bool:
    """Check the polyline through ``qs (S, 7)`` every ``step`` rad with zero margins."""
    for a, b in zip(qs[:-1], qs[1:]):
        n = max(1, int(np.ceil(np.abs(b - a).max() / step)))
        for k in range(n + 1):
            if not world.is_collision_free(a + (b - a) * (k / n)):
                return False
    return True


def test_plan_around_wall_is_collision_free_and_within_limits(wall_planner, kinematics):
    planner = wall_planner
    q_start = planner.solve_ik(tcp_pose([0.0, -0.15, 0.05]), REST_QPOS)
    goal = tcp_pose([0.0, 0.15, 0.05])
    q_goal = planner.solve_ik(goal, q_start)
    assert q_start is not None and q_goal is not None
    exact = PandaCollisionWorld(kinematics, planner.scene, CollisionMargins(0.0, 0.0, 0.0))
    # The direct joint-space motion goes through the wall: the planner must go around.
    assert not dense_collision_free(exact, np.stack([q_start, q_goal]), step=0.01)

    result = planner.plan_to_pose(q_start, goal, seed=3)
    assert result.success, result.message
    traj = result.trajectory
    assert np.allclose(traj.q[0], q_start)
    reached = kinematics.forward_kinematics(traj.q[-1])
    assert np.linalg.norm(reached[:3, 3] - goal[:3, 3]) < 1e-3 and rotation_error(reached, goal) < 1e-3
    assert np.allclose(np.diff(traj.t), planner.config.control_dt)
    assert np.abs(traj.qd[[0, -1]]).max() == 0.0
    assert dense_collision_free(exact, traj.q, step=1e-3)

    # Velocity/acceleration limits (scaled Panda limits), reported and finite-differenced.
    dt = planner.config.control_dt
    assert np.all(np.abs(traj.qd) <= planner.velocity_limits)
    assert np.all(np.abs(np.diff(traj.q, axis=0)) / dt <= planner.velocity_limits)
    assert np.all(np.abs(np.diff(traj.qd, axis=0)) / dt <= planner.acceleration_limits * 1.01)
    tcp = np.array([kinematics.forward_kinematics(q)[:3, 3] for q in traj.q])
    assert np.linalg.norm(np.diff(tcp, axis=0), axis=1).max() / dt <= planner.config.max_tcp_speed * 1.01

    # Reproducible per seed.
    again = planner.plan_to_pose(q_start, goal, seed=3)
    assert np.array_equal(again.trajectory.q, traj.q)


def test_clearance_keeps_the_way_clear_and_the_targets_reachable(wall_planner, kinematics):
    """With 3 cm clearance every state of the path away from its ends clears the wall by 3 cm; near the
    start and the goal the 1 cm margin alone applies, so a goal next to the wall stays reachable."""
    config = with_clearance(0.03)
    assert config.margins.objects == 0.01 and config.clearance == 0.03
    planner = PandaPlanner(wall_planner.scene, config=config, kinematics=kinematics)
    q_start = planner.solve_ik(tcp_pose([0.0, -0.15, 0.05]), REST_QPOS)
    goal = tcp_pose([0.0, 0.14, 0.05])  # the hand 1-3 cm from the wall: inside the clearance
    result = planner.plan_to_pose(q_start, goal, seed=3)
    assert result.success, result.message
    clear = PandaCollisionWorld(kinematics, planner.scene, CollisionMargins(objects=0.029, table=0.005))
    ends = np.stack([kinematics.forward_kinematics(q_start)[:3, 3], goal[:3, 3]])
    far = [q for q in result.trajectory.q
           if np.linalg.norm(ends - kinematics.forward_kinematics(q)[:3, 3], axis=1).min() > config.clearance_release]
    assert far, "the path never leaves the ends' neighbourhoods: the test checks nothing"
    assert all(clear.is_collision_free(q) for q in far)
    assert not clear.is_collision_free(result.trajectory.q[-1])  # the goal itself is within 3 cm of the wall
    with pytest.raises(ValueError, match="clearance"):
        with_clearance(0.5)
    with pytest.raises(ValueError, match="clearance"):
        PlannerConfig(clearance=0.001)  # below the margin the search must keep anyway


def test_clearance_search_accepts_exactly_the_states_its_rule_names(wall_planner, kinematics):
    """The clearance search's validity test (one check for a state that keeps the clearance) accepts a state
    iff it clears the wall by the margins within ``clearance_release`` of the ends, by the clearance beyond."""
    config = with_clearance(0.03)
    planner = PandaPlanner(wall_planner.scene, config=config, kinematics=kinematics)
    start, goal = planner.solve_ik(tcp_pose([0.0, -0.15, 0.05]), REST_QPOS), tcp_pose([0.0, 0.14, 0.05])
    goal_q = planner.solve_ik(goal, REST_QPOS)
    ends = np.stack([kinematics.forward_kinematics(start)[:3, 3], goal[:3, 3]])
    is_valid = planner._clearance_check(ends)
    near = PandaCollisionWorld(kinematics, planner.scene, config.margins)
    clear = PandaCollisionWorld(kinematics, planner.scene, CollisionMargins(objects=0.03, table=config.margins.table))
    rng = np.random.default_rng(0)
    cases = set()
    for q in np.linspace(start, goal_q, 60)[:, None] + rng.normal(scale=0.08, size=(60, 8, 7)):
        for state in q:
            tcp = kinematics.forward_kinematics(state)[:3, 3]
            close = np.linalg.norm(ends - tcp, axis=1).min() < config.clearance_release
            expected = near.is_collision_free(state) if close else clear.is_collision_free(state)
            assert is_valid(state) == expected
            cases.add((close, expected))
    assert {(True, True), (False, True), (False, False)} <= cases, cases


def test_start_in_the_joint_limit_margin_is_planned_from(wall_planner):
    """A visited state between a joint limit and the planner's bounds (``joint_limit_margin`` inside it) is
    planned from, not refused by OMPL (DAgger relabels start at such states)."""
    planner = wall_planner
    q_start = planner.solve_ik(tcp_pose([0.0, -0.15, 0.05]), REST_QPOS).copy()
    q_start[6] = planner.kin.lower[6] + 0.3 * planner.config.joint_limit_margin
    assert planner.is_collision_free(q_start)
    result = planner.plan_to_pose(q_start, tcp_pose([0.0, 0.15, 0.05]), seed=3)
    assert result.success, result.message
    assert np.abs(result.trajectory.q[0] - q_start).max() <= planner.config.joint_limit_margin


def test_failure_reasons(wall_planner):
    planner = wall_planner
    q_start = planner.solve_ik(tcp_pose([0.0, -0.15, 0.05]), REST_QPOS)
    inside_wall = planner.plan_to_pose(q_start, tcp_pose([0.0, 0.0, 0.1]))
    assert not inside_wall.success
    assert inside_wall.failure_reason in ("goal_in_collision", "ik_failed")
    assert inside_wall.trajectory is None

    far = planner.plan_to_pose(q_start, tcp_pose([1.5, 0.0, 0.3]))
    assert far.failure_reason == "ik_failed"

    q_in_wall = planner.kin.ik_from_seed(tcp_pose([0.0, 0.0, 0.1]), REST_QPOS)[0]
    start_bad = planner.plan_to_pose(q_in_wall, tcp_pose([0.0, 0.15, 0.05]))
    assert start_bad.failure_reason == "start_in_collision"

    rushed = planner.plan_to_pose(q_start, tcp_pose([0.0, 0.15, 0.05]), timeout=1e-3)
    assert rushed.failure_reason == "timeout"
    assert {r.failure_reason for r in (inside_wall, far, start_bad, rushed)} <= set(FAILURE_REASONS)


def test_bad_inputs_are_rejected(wall_planner):
    with pytest.raises(ValueError, match=r"\(7,\)"):
        wall_planner.plan_to_pose(np.zeros(6), tcp_pose([0.0, 0.1, 0.1]))
    with pytest.raises(ValueError, match="NaN"):
        wall_planner.plan_to_pose(np.full(7, np.nan), tcp_pose([0.0, 0.1, 0.1]))
    with pytest.raises(ValueError, match=r"\(4, 4\)"):
        wall_planner.plan_to_pose(REST_QPOS, np.eye(3))
    with pytest.raises(ValueError, match="rotation"):
        wall_planner.plan_to_pose(REST_QPOS, np.diag([2.0, 1.0, 1.0, 1.0]))
    with pytest.raises(ValueError, match="unknown object"):
        wall_planner.is_collision_free(REST_QPOS, ignore_objects={5})
    with pytest.raises(ValueError, match="max_tcp_speed"):
        PlannerConfig(max_tcp_speed=0.0)
    with pytest.raises(ValueError, match="ik_attempts"):
        PlannerConfig(ik_attempts=0)


# ---------------------------------------------------------------------- straight-line approach


def test_straight_line_approach(kinematics):
    # A bar 12 cm long across the closing axis, grasped from a tilted direction: the
    # open fingertips end up inside it. The pre-grasp is 5 cm back along the approach axis.
    bar, bar_pose = box_object("bar", (0.015, 0.06, 0.015), (0.02, 0.1, 0.015))
    planner = PandaPlanner(scene_of((bar, bar_pose)), kinematics=kinematics)
    tilt = trimesh.transformations.rotation_matrix(0.3, [1.0, 0.0, 0.0])[:3, :3]
    grasp = tcp_pose([0.02, 0.1, 0.03], TOP_DOWN @ tilt)
    pregrasp = grasp.copy()
    pregrasp[:3, 3] -= 0.05 * grasp[:3, 2]
    q_pre = planner.solve_ik(pregrasp, REST_QPOS)
    assert q_pre is not None

    blocked = planner.plan_straight_line(q_pre, grasp)
    assert blocked.failure_reason == "goal_in_collision"  # the fingers end inside the bar

    result = planner.plan_straight_line(q_pre, grasp, ignore_objects={0})
    assert result.success, result.message
    traj = result.trajectory
    poses = np.stack([kinematics.forward_kinematics(q) for q in traj.q])
    offset = poses[:, :3, 3] - pregrasp[:3, 3]
    along = offset @ pregrasp[:3, 2]
    lateral = np.linalg.norm(offset - along[:, None] * pregrasp[:3, 2], axis=1)
    assert abs(along[-1] - 0.05) < 1e-3
    assert np.all(np.diff(along) >= -1e-6)  # monotonic advance
    assert lateral.max() < 1e-3
    assert max(rotation_error(p, grasp) for p in poses) < 1e-3
    speed = np.linalg.norm(np.diff(poses[:, :3, 3], axis=0), axis=1) / planner.config.control_dt
    assert speed.max() <= planner.config.approach_speed * 1.01
    # Reported joint velocities agree with the motion.
    fd = np.gradient(traj.q, planner.config.control_dt, axis=0)
    assert np.abs(fd - traj.qd).max() < 0.01

    # A demonstration = free-space motion to the pre-grasp, then the approach.
    free = planner.plan_to_pose(REST_QPOS, pregrasp, seed=0)
    assert free.success, free.message
    demo = free.trajectory.concatenate(planner.plan_straight_line(free.goal_q, grasp, ignore_objects={0}).trajectory)
    assert np.allclose(np.diff(demo.t), planner.config.control_dt)
    assert np.abs(np.diff(demo.q, axis=0)).max() < 0.1  # no jump at the junction
    assert np.linalg.norm(kinematics.forward_kinematics(demo.q[-1])[:3, 3] - grasp[:3, 3]) < 1e-3
