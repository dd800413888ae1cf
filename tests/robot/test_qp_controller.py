"""NEO QP twist controller and NeoSS safety filter (robot/neo_qp.py, mode pd_ee_twist_qp)."""

from __future__ import annotations

import gymnasium as gym
import numpy as np
import pinocchio as pin
import pytest
import torch

import rtv3_maniskill  # noqa: F401  (registers the task)
from rtv3_maniskill import se3
from rtv3_maniskill.robot.neo_qp import (
    NeoConfig,
    NeoController,
    NeoSafetyFilter,
    manipulability_gradient,
    pose_target,
    pose_target_twist,
)
from rtv3_maniskill.robot.panda_model import PandaKinematics
from rtv3_maniskill.robot.scene_geometry import READY_QPOS
from rtv3_maniskill.robot.twist_controller import attach_safety_filters, target_object_index

DT = 1.0 / 20.0


@pytest.fixture(scope="module")
def kin():
    return PandaKinematics()


@pytest.fixture(scope="module")
def env():
    e = gym.make("GraspClutter-v1", obs_mode="state_dict", control_mode="pd_ee_twist_qp", num_points=256)
    yield e
    e.close()


def _realised_twist(kin, q0, q1, dt=DT) -> np.ndarray:
    t0, t1 = torch.as_tensor(kin.forward_kinematics(q0)), torch.as_tensor(kin.forward_kinematics(q1))
    return (se3.se3_log(se3.relative_transform(t0, t1)) / dt).numpy()


def test_manipulability_gradient_matches_finite_differences(kin):
    q = READY_QPOS + 0.1

    def m_and_jac(q):
        jac = pin.computeFrameJacobian(kin.model, kin.data, q, kin.tcp_frame_id, pin.LOCAL_WORLD_ALIGNED)
        return np.sqrt(np.linalg.det(jac @ jac.T)), jac

    m, grad = manipulability_gradient(m_and_jac(q)[1])
    fd = np.array([(m_and_jac(q + 1e-6 * e)[0] - m_and_jac(q - 1e-6 * e)[0]) / 2e-6 for e in np.eye(7)])
    assert m == pytest.approx(m_and_jac(q)[0])
    np.testing.assert_allclose(grad, fd, atol=1e-7)


def test_pose_target_servo_recovers_the_twist(kin):
    twist = np.array([0.1, -0.05, 0.2, 0.3, 0.0, -0.4])
    tcp = kin.forward_kinematics(READY_QPOS)
    target = pose_target(tcp, twist, DT)
    np.testing.assert_allclose(pose_target_twist(tcp, target, 1.0 / DT), twist, atol=1e-9)


def test_free_space_twist_is_tracked_within_1cm_per_s(kin):
    ctrl = NeoController(None, NeoConfig(collision_damper=False), kinematics=kin)
    command = np.array([0.08, -0.04, 0.06, 0.3, -0.2, 0.4])
    q = READY_QPOS.copy()
    for _ in range(10):
        step = ctrl.step(q, command)
        q_next = q + DT * step.joint_velocities
        # First order in the solver (J qd) and over a whole step of the integrated model.
        np.testing.assert_allclose(step.twist, command, atol=0.01)
        np.testing.assert_allclose(_realised_twist(kin, q, q_next), command, atol=0.01)
        q = q_next
    assert ctrl.infeasible_count == 0


@pytest.mark.sim
def test_free_space_twist_is_tracked_in_the_simulator(env):
    env.reset(seed=2)
    command = torch.tensor([[0.08, -0.04, 0.06, 0.3, -0.2, 0.4, 0.0]])
    twists = []
    for _ in range(12):
        obs, *_ = env.step(command)
        twists.append(obs["extra"]["tcp_twist"][0])
    realised = torch.stack(twists[3:]).median(0).values.numpy()
    np.testing.assert_allclose(realised, command[0, :6].numpy(), atol=0.01)


def test_joint_limits_are_never_exceeded(kin):
    ctrl = NeoController(None, NeoConfig(collision_damper=False), kinematics=kin)
    q = READY_QPOS.copy()
    # Spinning about the approach axis drives joint 7 into its limit; rolling the wrist drives joint 6.
    for command in (np.array([0, 0, 0, 0, 0, 1.2]), np.array([0, 0, 0, 1.2, 0, 0]), np.array([0, 0, 0, 0, 0, -1.2])):
        for _ in range(120):
            step = ctrl.step(q, command)
            q = q + DT * step.joint_velocities
            assert np.all(q >= kin.lower) and np.all(q <= kin.upper), q
        assert min(q - kin.lower).min() < 0.2 or min(kin.upper - q) < 0.2  # it got close: the damper held it
    assert ctrl.infeasible_count == 0


def test_twist_into_the_table_stops_above_the_stop_distance_model(kin):
    filt = NeoSafetyFilter(None, kinematics=kin)
    q = READY_QPOS.copy()
    down = np.array([0.0, 0.0, -0.25])
    for _ in range(80):
        rot = kin.forward_kinematics(q)[:3, :3]
        step = filt.filter(q, np.r_[rot.T @ down, np.zeros(3)])
        q = q + DT * step.joint_velocities
        assert filt.clearance(q) > filt.config.stop_distance
    assert filt.clearance(q) < filt.config.stop_distance + 0.01  # it went down as far as allowed
    assert np.linalg.norm(step.twist[:3]) < 0.01
    assert filt.infeasible_count == 0


@pytest.mark.sim
def test_twist_into_the_table_stops_before_contact_in_the_simulator(env):
    env.reset(seed=6)
    base = env.unwrapped
    filt = NeoSafetyFilter(base.layouts[0], target_object=target_object_index(env))
    attach_safety_filters(env, [filt])  # after every reset: a reconfiguring reset rebuilds the controllers
    clearances = []
    for _ in range(60):
        rot = base.tcp_pose_matrix[0, :3, :3]
        v_body = rot.T @ torch.tensor([0.0, 0.0, -0.25])
        _, _, _, _, info = env.step(torch.cat([v_body, torch.zeros(4)])[None])
        assert not bool(info["collision"])
        clearances.append(filt.clearance(base.agent.robot.get_qpos()[0, :7].double().numpy()))
    # The arm came down (the damper only slows it near the table) and stopped at the stop distance.
    assert min(clearances) > filt.config.stop_distance - 1e-3, min(clearances)
    assert clearances[-1] < filt.config.stop_distance + 0.01
    assert float(base.agent.tcp.pose.p[0, 2]) < 0.1
    assert filt.infeasible_count == 0


@pytest.mark.sim
def test_wrong_control_mode_is_a_clear_error():
    e = gym.make("GraspClutter-v1", obs_mode="state_dict", control_mode="pd_ee_twist", num_points=256)
    try:
        e.reset(seed=1)
        with pytest.raises(ValueError, match="pd_ee_twist_qp"):
            attach_safety_filters(e, [NeoSafetyFilter(None)])
    finally:
        e.close()


def _pregrasp_near_the_target_only(env, kin, seeds=range(6, 30)):
    """First scene whose target pre-grasp has nothing but the target within the stop distance of
    the robot (many pre-grasps also pass near the table or a neighbour, which the damper must keep)."""
    for seed in seeds:
        env.reset(seed=seed)
        base = env.unwrapped
        layout, target = base.layouts[0], target_object_index(env)
        blocked = NeoController(layout, kinematics=kin)
        allowed = NeoController(layout, target_object=target, kinematics=kin)
        q, ok = kin.ik_from_seed(base.target_pregrasp_pose[0].double().numpy(), READY_QPOS, max_iters=500)
        stop = blocked.config.stop_distance
        if ok and blocked.clearance(q) < stop < allowed.clearance(q):
            return layout, target, blocked, allowed, q
    raise AssertionError(f"no scene in seeds {seeds} has a pre-grasp near its target only")


@pytest.mark.sim
def test_fingers_may_touch_the_target_object_only(env, kin):
    layout, target, blocked, allowed, q = _pregrasp_near_the_target_only(env, kin)
    world = allowed.world
    names = {p: world.geometry.geometryObjects[g].name for p, g, _ in allowed._pairs}
    objects = {p: obj for p, _, obj in allowed._pairs}
    exempt = set(allowed.allowed_pairs.tolist())
    assert exempt and exempt == set(blocked.damped_pairs.tolist()) - set(allowed.damped_pairs.tolist())
    assert all(objects[p] == target and "finger" in names[p] for p in exempt)
    # The hand and the links keep their damper against the target, the fingers theirs against the others.
    damped = set(allowed.damped_pairs.tolist())
    assert any(objects[p] == target and names[p].startswith("panda_hand") for p in damped)
    assert any(objects[p] != target and "finger" in names[p] for p in damped)
    # At the pre-grasp the fingers are within the stop distance of the target (and nothing else is):
    # only the filter that allows that contact lets the hand go on along its approach axis (TCP z).
    approach = np.array([0.0, 0.0, 0.05, 0.0, 0.0, 0.0])
    assert blocked.step(q, approach).twist[2] < 0 < allowed.step(q, approach).twist[2]
    with pytest.raises(ValueError, match="target_object"):
        allowed.set_target_object(len(layout.objects))


def test_infeasible_qp_stops_the_arm_counts_and_warns(kin):
    ctrl = NeoController(None, NeoConfig(collision_damper=False), kinematics=kin)
    q = READY_QPOS.copy()
    q[0] = kin.lower[0] - 3.0  # the joint-limit damper asks for more than the velocity limit
    with pytest.warns(RuntimeWarning, match="infeasible"):
        step = ctrl.step(q, np.array([0.05, 0, 0, 0, 0, 0]))
    assert not step.feasible
    np.testing.assert_array_equal(step.joint_velocities, np.zeros(7))
    np.testing.assert_array_equal(step.twist, np.zeros(6))
    assert ctrl.infeasible_count == 1


@pytest.mark.parametrize(
    "q, twist, message",
    [
        (READY_QPOS, [0.0, 0.0, np.nan, 0.0, 0.0, 0.0], "NaN"),
        (READY_QPOS, [0.0, 0.0, 0.1], r"shape \(6,\)"),
        (READY_QPOS[:6], [0.0] * 6, r"shape \(7,\)"),
        (np.r_[READY_QPOS[:6], np.inf], [0.0] * 6, "NaN or inf"),
    ],
)
def test_bad_inputs_are_clear_errors(kin, q, twist, message):
    filt = NeoSafetyFilter(None, kinematics=kin)
    with pytest.raises(ValueError, match=message):
        filt.filter(q, twist)


def test_bad_config_is_a_clear_error():
    with pytest.raises(ValueError, match="stop_distance"):
        NeoConfig(stop_distance=0.5, influence_distance=0.4)
    with pytest.raises(ValueError, match="not installed"):
        NeoConfig(solver="no_such_solver")
