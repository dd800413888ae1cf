"""NEO-style reactive QP twist controller and collision safety filter (NeoSS) for the Panda.

Haviland & Corke's NEO, as the RT-V3 authors use it (docs/PAPER_DETAILS.md, "Asynchronous Shared
Control"): each step the executed TCP body twist ``a = [v, w]`` becomes a pose target
``T_cur Exp(a dt)``; a quadratic program finds the arm's joint velocities that reach it, with a
slack on the task, joint position and velocity limits, NEO's manipulability term and velocity
dampers that keep the robot's links and hand out of the scene.

Decision variables ``x = [qd (7,), delta (6,)]`` (joint velocities in rad/s, task slack in the TCP
frame)::

    min  1/2 lambda_q |qd|^2 + 1/2 lambda_d |delta|^2 - k_m grad(m)^T qd
    s.t. J_tcp(q) qd + delta = nu                       (TCP body twist, TCP frame)
         -qd_max <= qd <= qd_max                          (velocity limits)
         -qd_i <= xi_q (d_low_i - rho_s) / (rho_i - rho_s)   for joints with d_low_i < rho_i
          qd_i <= xi_q (d_up_i - rho_s) / (rho_i - rho_s)    for joints with d_up_i < rho_i
         -d_dot_k = n_k^T J_p(p_k) qd <= xi (d_k - d_s) / (d_i - d_s)   for obstacle pairs with d_k < d_i

``nu`` is the pose target's twist, ``log(T_cur^-1 T_cur Exp(a dt)) / dt = a`` (the servo that
reaches the target in one control period); ``pose_target_twist`` gives NEO's proportional servo
``gain * log(T_cur^-1 T_target)`` for a fixed target. ``n_k`` points from the robot's nearest point
``p_k`` to the obstacle's. Distances and witness points come from coal through Pinocchio
(``PandaCollisionWorld.nearest_points``), Jacobians and the manipulability gradient from
Pinocchio, the QP from ``qpsolvers`` (DAQP by default). No SAPIEN here: the simulator's control
mode ``pd_ee_twist_qp`` (``robot/twist_controller.py``) wraps this module.

Frames: ``q`` is ManiSkill's ``qpos[:7]``; twists are TCP body twists ``[v (m/s), w (rad/s)]`` in
the TCP frame (``panda_hand_tcp``); everything geometric is in the world frame of the scene.
"""

from __future__ import annotations

import warnings
from collections.abc import Iterable
from dataclasses import dataclass, field

import numpy as np
import pinocchio as pin
import qpsolvers
import torch

from rtv3_maniskill import se3
from rtv3_maniskill.robot.collision_world import TABLE_OBJECT_INDEX, PandaCollisionWorld
from rtv3_maniskill.robot.panda_model import (
    DOF,
    PANDA_VELOCITY_LIMITS,
    PandaKinematics,
    as_joint_vector,
    as_pose_matrix,
)
from rtv3_maniskill.robot.scene_geometry import SceneGeometry

FINGER_GEOMETRY_PREFIXES = ("panda_leftfinger", "panda_rightfinger")
"""Robot collision geometries that may touch the target object (``allowed_contact_links``)."""


@dataclass(frozen=True)
class NeoConfig:
    """Settings of the QP (authors' values where published, docs/PAPER_DETAILS.md).

    Units: m, rad, s. ``influence_distance``/``stop_distance``/``collision_gain``: the collision
    velocity damper (0.4 m, 0.05 m, 1.0); ``joint_*``: the joint-limit damper (NEO's 0.9 rad,
    0.05 rad, 1.0); ``servo_gain`` (15) and ``joint_velocity_weight`` ("damping", 0.1):
    NEO's servo gain and the weight ``lambda_q`` of ``|qd|^2``.
    """

    dt: float = 1.0 / 20.0
    """Control period (s) over which a twist is executed (the pose target ``T_cur Exp(a dt)``)."""
    servo_gain: float = 15.0
    joint_velocity_weight: float = 0.1
    slack_weight: float = 1.0e4
    """``lambda_d``: weight of the task slack; large, so the twist is tracked unless a constraint binds."""
    manipulability_gain: float = 0.01
    """``k_m``: weight of NEO's manipulability gradient (0 turns it off)."""
    velocity_limits: tuple[float, ...] = tuple(PANDA_VELOCITY_LIMITS)
    velocity_scale: float = 0.9
    """Fraction of the URDF joint velocity limits the QP may use."""
    joint_influence: float = 0.9
    joint_stop: float = 0.05
    joint_gain: float = 1.0
    influence_distance: float = 0.4
    stop_distance: float = 0.05
    collision_gain: float = 1.0
    mount_links: tuple[str, ...] = ("panda_link0", "panda_link1")
    """Robot geometries without a table damper: the base and the first link, which only turns about
    the vertical base axis (its distance to the table cannot change) and stands near the table's edge."""
    collision_damper: bool = True
    """False: track with limits only (no obstacle constraints): the ``pd_ee_twist_qp`` mode."""
    solver: str = "daqp"

    def __post_init__(self) -> None:
        for name in ("dt", "joint_velocity_weight", "slack_weight", "velocity_scale", "joint_gain", "collision_gain"):
            if not getattr(self, name) > 0:
                raise ValueError(f"NeoConfig.{name} must be positive, got {getattr(self, name)}")
        if not 0 <= self.joint_stop < self.joint_influence:
            raise ValueError(
                f"NeoConfig needs 0 <= joint_stop < joint_influence, got {self.joint_stop}, {self.joint_influence}"
            )
        if not 0 <= self.stop_distance < self.influence_distance:
            raise ValueError(
                "NeoConfig needs 0 <= stop_distance < influence_distance, "
                f"got {self.stop_distance}, {self.influence_distance}"
            )
        if len(self.velocity_limits) != DOF or min(self.velocity_limits) <= 0:
            raise ValueError(f"NeoConfig.velocity_limits must be 7 positive values, got {self.velocity_limits}")
        if self.solver not in qpsolvers.available_solvers:
            raise ValueError(f"QP solver {self.solver!r} is not installed; available: {qpsolvers.available_solvers}")


@dataclass
class NeoStep:
    """One solved step. ``joint_velocities (7,)`` rad/s; ``twist (6,)`` the TCP body twist they realise
    (``J_tcp qd``, TCP frame); ``slack (6,)``; ``feasible`` False when the QP had no solution (then
    ``joint_velocities`` is zero); ``num_collision_constraints``; ``min_distance`` (m, inf without
    obstacles in the influence distance)."""

    joint_velocities: np.ndarray
    twist: np.ndarray
    slack: np.ndarray
    feasible: bool
    num_collision_constraints: int = 0
    min_distance: float = float("inf")


def as_twist_vector(twist, name: str = "twist") -> np.ndarray:
    """Validate a ``(6,)`` TCP body twist ``[v, w]`` and return it as float64."""
    arr = np.asarray(twist.detach().cpu() if isinstance(twist, torch.Tensor) else twist, dtype=np.float64)
    if arr.shape != (6,):
        raise ValueError(f"{name} must have shape (6,) ([v (m/s), w (rad/s)] in the TCP frame), got {arr.shape}")
    if not np.all(np.isfinite(arr)):
        raise ValueError(f"{name} contains NaN or inf: {arr}")
    return arr


def pose_target(tcp_pose, twist, dt: float) -> np.ndarray:
    """The paper's pose target ``T_cur Exp(a dt)`` ``(4, 4)`` (world frame) for a body twist ``a (6,)``."""
    pose = torch.as_tensor(as_pose_matrix(tcp_pose, "tcp_pose"))
    xi = torch.as_tensor(as_twist_vector(twist)) * dt
    return (pose @ se3.se3_exp(xi)).numpy()


def pose_target_twist(tcp_pose, target_pose, gain: float) -> np.ndarray:
    """NEO's proportional servo: the body twist ``gain * log(T_cur^-1 T_target)`` ``(6,)``."""
    current = torch.as_tensor(as_pose_matrix(tcp_pose, "tcp_pose"))
    rel = se3.relative_transform(current, torch.as_tensor(as_pose_matrix(target_pose, "target_pose")))
    return gain * se3.se3_log(rel).numpy()


def manipulability_gradient(jacobian: np.ndarray) -> tuple[float, np.ndarray]:
    """Yoshikawa manipulability ``m = sqrt(det(J J^T))`` and ``dm/dq (7,)`` of a world-aligned Jacobian.

    ``jacobian (6, 7)`` rows ``[v; w]`` of the TCP in world axes, all joints revolute. Uses the
    kinematic Hessian of Haviland & Corke: ``dJw_j/dq_i = w_i x w_j`` (i < j, else 0) and
    ``dJv_j/dq_i = w_min(i,j) x v_max(i,j)``; ``dm/dq_i = m <(J J^T)^-1 J, dJ/dq_i>``.
    """
    jv, jw = jacobian[:3].T, jacobian[3:].T  # (7, 3) columns
    n = jacobian.shape[1]
    lo = np.minimum.outer(np.arange(n), np.arange(n))
    hi = np.maximum.outer(np.arange(n), np.arange(n))
    hess_v = np.cross(jw[lo], jv[hi])  # (i, j, 3)
    hess_w = np.cross(jw[:, None, :], jw[None, :, :]) * (np.arange(n)[:, None] < np.arange(n)[None, :])[..., None]
    jjt = jacobian @ jacobian.T
    m = float(np.sqrt(max(np.linalg.det(jjt), 0.0)))
    b = np.linalg.solve(jjt + 1e-12 * np.eye(6), jacobian)  # (6, 7)
    grad = m * (np.einsum("ijk,kj->i", hess_v, b[:3]) + np.einsum("ijk,kj->i", hess_w, b[3:]))
    return m, grad


@dataclass
class _Constraints:
    rows: list[np.ndarray] = field(default_factory=list)
    bounds: list[float] = field(default_factory=list)


class NeoController:
    """NEO QP for the Panda arm: ``step(q (7,), twist (6,)) -> NeoStep``.

    ``scene``: the obstacles of the collision damper (a ``SceneGeometry``, or None for the table
    only); ignored when ``config.collision_damper`` is False. ``target_object``: index of the
    object the fingers may touch (its pairs with ``allowed_contact_links`` carry no damper), or
    None. ``infeasible_count`` counts steps whose QP had no solution (the robot was stopped).
    """

    def __init__(
        self,
        scene: SceneGeometry | None = None,
        config: NeoConfig = NeoConfig(),
        *,
        target_object: int | None = None,
        allowed_contact_links: Iterable[str] = FINGER_GEOMETRY_PREFIXES,
        kinematics: PandaKinematics | None = None,
    ) -> None:
        self.config = config
        self.kin = kinematics if kinematics is not None else PandaKinematics()
        self.model = self.kin.model
        self.data = self.model.createData()
        self.allowed_contact_links = tuple(allowed_contact_links)
        self.velocity_limits = config.velocity_scale * np.asarray(config.velocity_limits, dtype=np.float64)
        self.infeasible_count = 0
        self.world: PandaCollisionWorld | None = None
        self.target_object: int | None = None
        if config.collision_damper:
            self.world = PandaCollisionWorld(self.kin, None)
        self.set_scene(scene, target_object)

    # ------------------------------------------------------------------ scene

    def set_scene(self, scene: SceneGeometry | None, target_object: int | None = None) -> None:
        """New obstacles (None: table only) and the target object (None: no allowed contact)."""
        if self.world is None:
            if scene is not None:
                raise ValueError("this NeoController has no collision damper (config.collision_damper=False)")
            return
        self.world.set_scene(scene)
        self._pairs = self.world.obstacle_pairs()
        self.set_target_object(target_object)

    def set_target_object(self, target_object: int | None) -> None:
        """Let ``allowed_contact_links`` touch object ``target_object`` (None: no object)."""
        if self.world is None:
            return
        known = set(self.world.pairs_by_object) - {TABLE_OBJECT_INDEX}
        if target_object is not None and target_object not in known:
            raise ValueError(
                f"target_object {target_object} is not an object of the scene ({self.world.num_objects} objects)"
            )
        names = [g.name for g in self.world.geometry.geometryObjects]
        allowed = {
            p
            for p, geom, obj in self._pairs
            if target_object is not None and obj == target_object and names[geom].startswith(self.allowed_contact_links)
        }
        self.target_object = target_object
        mount = self.config.mount_links
        mounted = {p for p, geom, obj in self._pairs if obj == TABLE_OBJECT_INDEX and names[geom].startswith(mount)}
        self.damped_pairs = np.array([p for p, _, _ in self._pairs if p not in allowed | mounted], dtype=np.int64)
        self.allowed_pairs = np.array(sorted(allowed), dtype=np.int64)

    def clearance(self, q) -> float:
        """Smallest signed distance (m) over the damped robot-obstacle pairs at ``q (7,)`` (inf: none)."""
        if self.world is None:
            return float("inf")
        near = self.world.nearest_points(q, self.damped_pairs, np.inf)
        return float(near.distances.min()) if len(near.distances) else float("inf")

    # ------------------------------------------------------------------ QP

    def _joint_limit_constraints(self, q: np.ndarray, out: _Constraints) -> None:
        c = self.config
        scale = c.joint_gain / (c.joint_influence - c.joint_stop)
        for j in range(DOF):
            d_low, d_up = q[j] - self.kin.lower[j], self.kin.upper[j] - q[j]
            if d_low < c.joint_influence:
                row = np.zeros(DOF)
                row[j] = -1.0
                out.rows.append(row)
                out.bounds.append(scale * (d_low - c.joint_stop))
            if d_up < c.joint_influence:
                row = np.zeros(DOF)
                row[j] = 1.0
                out.rows.append(row)
                out.bounds.append(scale * (d_up - c.joint_stop))

    def _collision_constraints(self, q: np.ndarray, out: _Constraints) -> tuple[int, float]:
        c = self.config
        near = self.world.nearest_points(q, self.damped_pairs, c.influence_distance)
        if len(near.distances) == 0:
            return 0, float("inf")
        # world.nearest_points ran the forward kinematics into world.data.
        pin.computeJointJacobians(self.model, self.world.data, q)
        scale = c.collision_gain / (c.influence_distance - c.stop_distance)
        joints = np.unique(near.robot_joints)
        jac = np.zeros((self.model.njoints, 6, DOF))
        origin = np.zeros((self.model.njoints, 3))
        for j in joints:
            jac[j] = pin.getJointJacobian(self.model, self.world.data, int(j), pin.LOCAL_WORLD_ALIGNED)
            origin[j] = self.world.data.oMi[int(j)].translation
        jk, n = near.robot_joints, near.normals
        # Velocity of each robot witness point p: v_p = J_v qd + w x (p - o) = (J_v - [p - o]x J_w) qd, and
        # n^T v_p = -d_dot (n points from the robot to the obstacle): rows (K, 7).
        rows = np.einsum("ki,kij->kj", n, jac[jk, :3]) - np.einsum(
            "ki,kij->kj", np.cross(n, near.robot_points - origin[jk]), jac[jk, 3:]
        )
        # Drop pairs the arm can neither approach nor leave (a zero row would be infeasible inside d_s).
        keep = np.linalg.norm(rows, axis=1) >= 1e-6
        out.rows.extend(rows[keep])  # n^T v_p <= xi (d - d_s) / (d_i - d_s)
        out.bounds.extend(scale * (near.distances[keep] - c.stop_distance))
        count = int(keep.sum())
        return count, float(near.distances.min())

    def step(self, q, twist) -> NeoStep:
        """Joint velocities ``(7,)`` that track the TCP body twist ``twist (6,)`` from ``q (7,)``."""
        q = as_joint_vector(q, "q")
        nu = as_twist_vector(twist)
        c = self.config
        jac_body = pin.computeFrameJacobian(self.model, self.data, q, self.kin.tcp_frame_id, pin.LOCAL)
        jac_world = pin.getFrameJacobian(self.model, self.data, self.kin.tcp_frame_id, pin.LOCAL_WORLD_ALIGNED)
        n_x = DOF + 6
        hessian = np.diag(np.r_[np.full(DOF, c.joint_velocity_weight), np.full(6, c.slack_weight)])
        linear = np.zeros(n_x)
        if c.manipulability_gain > 0:
            linear[:DOF] = -c.manipulability_gain * manipulability_gradient(jac_world)[1]
        cons = _Constraints()
        self._joint_limit_constraints(q, cons)
        n_coll, min_distance = (0, float("inf"))
        if self.world is not None:
            n_coll, min_distance = self._collision_constraints(q, cons)
        G = h = None
        if cons.rows:
            G = np.zeros((len(cons.rows), n_x))
            G[:, :DOF] = np.asarray(cons.rows)
            h = np.asarray(cons.bounds, dtype=np.float64)
        bound = np.r_[self.velocity_limits, np.full(6, 1e3)]
        problem = qpsolvers.Problem(hessian, linear, G, h, np.hstack([jac_body, np.eye(6)]), nu, -bound, bound)
        solution = qpsolvers.solve_problem(problem, solver=c.solver)
        x = solution.x
        if not solution.found or x is None or not np.all(np.isfinite(x)):
            self.infeasible_count += 1
            warnings.warn(
                f"NEO QP infeasible at q={np.round(q, 3).tolist()} (twist {np.round(nu, 3).tolist()}, "
                f"{n_coll} collision and {len(cons.rows) - n_coll} joint-limit constraints): stopping the arm",
                RuntimeWarning,
                stacklevel=2,
            )
            return NeoStep(np.zeros(DOF), np.zeros(6), np.zeros(6), False, n_coll, min_distance)
        qd = x[:DOF]
        return NeoStep(qd, jac_body @ qd, x[DOF:], True, n_coll, min_distance)


class NeoSafetyFilter:
    """NeoSS: puts the NEO QP with its collision damper in front of any twist command.

    ``filter(q (7,), twist (6,)) -> NeoStep``: the joint velocities to send and the TCP body twist
    they realise (``step.twist``), close to ``twist`` in free space and slowed down towards
    obstacles so that no link comes closer than ``config.stop_distance``. Call ``reset(scene,
    target_object)`` at each episode start. ``infeasible_count``: steps stopped for an infeasible QP.
    """

    def __init__(
        self,
        scene: SceneGeometry | None = None,
        config: NeoConfig = NeoConfig(),
        *,
        target_object: int | None = None,
        kinematics: PandaKinematics | None = None,
    ) -> None:
        if not config.collision_damper:
            raise ValueError("NeoSafetyFilter needs config.collision_damper=True")
        self.controller = NeoController(scene, config, target_object=target_object, kinematics=kinematics)

    @property
    def config(self) -> NeoConfig:
        return self.controller.config

    @property
    def infeasible_count(self) -> int:
        return self.controller.infeasible_count

    def reset(self, scene: SceneGeometry | None, target_object: int | None = None) -> None:
        """New episode: the scene's obstacles and the object the fingers may touch."""
        self.controller.set_scene(scene, target_object)

    def clearance(self, q) -> float:
        """Smallest distance (m) between the robot and the obstacles the damper keeps it from, at ``q (7,)``."""
        return self.controller.clearance(q)

    def filter(self, q, twist) -> NeoStep:
        """Joint velocities ``(7,)`` and realised TCP body twist ``(6,)`` for the command ``twist (6,)``."""
        return self.controller.step(q, twist)

    def filter_twist(self, q, twist) -> torch.Tensor:
        """The realised TCP body twist ``(6,)`` (float32 tensor) for ``twist (6,)``: a drop-in twist filter."""
        return torch.as_tensor(self.filter(q, twist).twist, dtype=torch.float32)


__all__ = [
    "FINGER_GEOMETRY_PREFIXES",
    "NeoConfig",
    "NeoController",
    "NeoSafetyFilter",
    "NeoStep",
    "as_twist_vector",
    "manipulability_gradient",
    "pose_target",
    "pose_target_twist",
]
