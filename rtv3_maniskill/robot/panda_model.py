"""Pinocchio model of ManiSkill's Panda arm: forward kinematics, Jacobians and TCP IK.

Everything is in the **world frame** of the ManiSkill scene: the robot base
(``panda_link0``) stands at ``ROBOT_BASE_POSITION`` with identity rotation, the table
top is at z = 0.

End-effector frame: ManiSkill's TCP link ``panda_hand_tcp`` (10.34 cm in front of
``panda_hand``, between the finger pads). Its **z axis is the approach axis** (from the
hand towards the fingertips) and its **y axis the finger closing axis** (the finger
joints slide along +-y of ``panda_hand``, which has the same rotation as the TCP); this
matches ``mani_skill.agents.robots.panda.Panda.build_grasp_pose``, whose rotation
columns are ``[closing x approaching, closing, approaching]``.

The fingers are locked open (0.04 m each) in this model: planning happens with the
gripper open.

The model also carries the robot's collision geometry for
:mod:`rtv3_maniskill.robot.collision_world`: the URDF's 17 collision geometries (9 link
meshes + 8 finger boxes), link meshes replaced by their convex hulls, which is what
SAPIEN/PhysX simulates.
"""

from __future__ import annotations

import coal
import numpy as np
import pinocchio as pin

from rtv3_maniskill.robot.panda_hand import panda_asset_dir
from rtv3_maniskill.robot.scene_geometry import ROBOT_BASE_POSITION

ARM_JOINT_NAMES = tuple(f"panda_joint{i}" for i in range(1, 8))
FINGER_JOINT_NAMES = ("panda_finger_joint1", "panda_finger_joint2")
TCP_FRAME_NAME = "panda_hand_tcp"
FINGER_OPEN = 0.04
"""Finger joint position (m, each finger) used during planning."""

REST_QPOS = np.array([0.0, np.pi / 8, 0.0, -np.pi * 5 / 8, 0.0, np.pi * 3 / 4, np.pi / 4])
"""ManiSkill's Panda ``rest`` keyframe (arm joints only)."""

PANDA_VELOCITY_LIMITS = np.array([2.175, 2.175, 2.175, 2.175, 2.61, 2.61, 2.61])
"""Joint velocity limits (rad/s) from the URDF."""
PANDA_ACCELERATION_LIMITS = np.array([15.0, 7.5, 10.0, 12.5, 15.0, 20.0, 20.0])
"""Joint acceleration limits (rad/s^2) from Franka's datasheet (the URDF has none)."""

DOF = 7


def as_joint_vector(q, name: str = "q") -> np.ndarray:
    """Validate a ``(7,)`` arm configuration and return it as float64."""
    arr = np.asarray(q, dtype=np.float64)
    if arr.shape != (DOF,):
        raise ValueError(f"{name} must have shape (7,) (Panda arm joints), got {arr.shape}")
    if not np.all(np.isfinite(arr)):
        raise ValueError(f"{name} contains NaN or inf: {arr}")
    return arr


def as_pose_matrix(pose, name: str = "pose") -> np.ndarray:
    """Validate a ``(4, 4)`` rigid transform and return it as float64."""
    arr = np.asarray(pose, dtype=np.float64)
    if arr.shape != (4, 4):
        raise ValueError(f"{name} must be a (4, 4) homogeneous matrix, got shape {arr.shape}")
    if not np.all(np.isfinite(arr)):
        raise ValueError(f"{name} contains NaN or inf")
    rot = arr[:3, :3]
    if np.abs(rot.T @ rot - np.eye(3)).max() > 1e-4 or abs(np.linalg.det(rot) - 1.0) > 1e-4:
        raise ValueError(f"{name} has a rotation block that is not a proper rotation matrix")
    if np.abs(arr[3] - np.array([0.0, 0.0, 0.0, 1.0])).max() > 1e-9:
        raise ValueError(f"{name} must have last row [0, 0, 0, 1], got {arr[3]}")
    return arr


class PandaKinematics:
    """Panda arm (7 joints, fingers locked open) in the world frame, with TCP IK.

    ``q`` is always ``(7,)`` arm joint positions in radians (ManiSkill's qpos[:7]).
    """

    def __init__(self, base_position: np.ndarray = ROBOT_BASE_POSITION) -> None:
        asset_dir = panda_asset_dir()
        self.urdf_path = asset_dir / "panda_v2.urdf"
        if not self.urdf_path.is_file():
            raise FileNotFoundError(f"panda_v2.urdf not found in {asset_dir}")
        self.srdf_path = asset_dir / "panda_v2.srdf"
        full = pin.buildModelFromUrdf(str(self.urdf_path))
        geom = pin.buildGeomFromUrdf(full, str(self.urdf_path), pin.GeometryType.COLLISION,
                                     package_dirs=[str(asset_dir)])
        # Placing the robot: append it to an empty world model at the base pose.
        base = pin.SE3(np.eye(3), np.asarray(base_position, dtype=np.float64))
        full, geom = pin.appendModel(pin.Model(), full, pin.GeometryModel(), geom, 0, base)
        q_ref = pin.neutral(full)
        lock = []
        for name in FINGER_JOINT_NAMES:
            jid = full.getJointId(name)
            q_ref[full.joints[jid].idx_q] = FINGER_OPEN
            lock.append(jid)
        self.model, self.robot_geometry = pin.buildReducedModel(full, geom, lock, q_ref)
        names = [self.model.names[j] for j in range(1, self.model.njoints)]
        if tuple(names) != ARM_JOINT_NAMES:
            raise RuntimeError(f"unexpected joint order in the reduced Panda model: {names}")
        for g in self.robot_geometry.geometryObjects:
            if isinstance(g.geometry, coal.BVHModelBase):
                g.geometry.buildConvexRepresentation(False)
                g.geometry = g.geometry.convex
        self.data = self.model.createData()
        self.tcp_frame_id = self.model.getFrameId(TCP_FRAME_NAME)
        self.lower = self.model.lowerPositionLimit.copy()
        self.upper = self.model.upperPositionLimit.copy()
        self.base_pose = base.homogeneous

    # ------------------------------------------------------------------ kinematics

    def forward_kinematics(self, q) -> np.ndarray:
        """``(4, 4)`` TCP pose in the world frame for arm joints ``q (7,)``."""
        q = as_joint_vector(q)
        pin.framesForwardKinematics(self.model, self.data, q)
        return self.data.oMf[self.tcp_frame_id].homogeneous.copy()

    def tcp_jacobian(self, q) -> np.ndarray:
        """``(6, 7)`` TCP Jacobian in the TCP (body) frame, rows ``[v, w]``."""
        q = as_joint_vector(q)
        return pin.computeFrameJacobian(self.model, self.data, q, self.tcp_frame_id, pin.LOCAL).copy()

    def tcp_linear_jacobian_world(self, q) -> np.ndarray:
        """``(3, 7)`` world-frame linear velocity Jacobian of the TCP origin."""
        q = as_joint_vector(q)
        jac = pin.computeFrameJacobian(self.model, self.data, q, self.tcp_frame_id, pin.LOCAL_WORLD_ALIGNED)
        return jac[:3].copy()

    def within_limits(self, q, tol: float = 0.0) -> bool:
        """Whether ``q (7,)`` lies within the joint limits (plus ``tol`` rad)."""
        q = as_joint_vector(q)
        return bool(np.all(q >= self.lower - tol) and np.all(q <= self.upper + tol))

    def random_configuration(self, rng: np.random.Generator, margin: float = 0.0) -> np.ndarray:
        """Uniform ``(7,)`` configuration within the limits shrunk by ``margin`` rad."""
        return rng.uniform(self.lower + margin, self.upper - margin)

    # ------------------------------------------------------------------ IK

    def ik_from_seed(
        self,
        target: np.ndarray,
        q_seed: np.ndarray,
        *,
        max_iters: int = 200,
        pos_tol: float = 1e-4,
        rot_tol: float = 1e-3,
        damping: float = 1e-4,
        max_step: float = 0.3,
        limit_margin: float = 1e-3,
    ) -> tuple[np.ndarray, bool]:
        """Damped least-squares IK of the TCP from one seed.

        ``target`` ``(4, 4)`` world pose, ``q_seed`` ``(7,)``. Iterates
        ``dq = -J^T (J J^T + lambda I)^-1 e`` on the body-frame error
        ``e = log6(T_tcp^-1 T_target)`` (with the log's Jacobian, so steps are exact to
        first order), clamping to the joint limits. Returns ``(q, converged)``;
        converged means position error < ``pos_tol`` m and rotation error <
        ``rot_tol`` rad.
        """
        target_se3 = pin.SE3(target[:3, :3], target[:3, 3])
        lower = self.lower + limit_margin
        upper = self.upper - limit_margin
        q = np.clip(np.asarray(q_seed, dtype=np.float64), lower, upper)
        model, data, fid = self.model, self.data, self.tcp_frame_id
        eye6 = np.eye(6)
        for _ in range(max_iters):
            pin.forwardKinematics(model, data, q)
            current = pin.updateFramePlacement(model, data, fid)
            i_m_d = current.actInv(target_se3)
            err = pin.log6(i_m_d).vector
            if np.linalg.norm(err[:3]) < pos_tol and np.linalg.norm(err[3:]) < rot_tol:
                return q, True
            pin.computeJointJacobians(model, data, q)
            jac = pin.getFrameJacobian(model, data, fid, pin.LOCAL)
            jac = -pin.Jlog6(i_m_d.inverse()) @ jac
            dq = -jac.T @ np.linalg.solve(jac @ jac.T + damping * eye6, err)
            norm = np.abs(dq).max()
            if norm > max_step:
                dq *= max_step / norm
            q = np.clip(q + dq, lower, upper)
        return q, False
