"""Expert motion planner for demonstrations: OMPL RRTConnect + TOPP-RA on the Panda.

Replaces ManiSkill's ``mplib`` (which segfaults under numpy 2). The paper generated its
demonstrations with cuRobo ("a collision-free trajectory ... from a random initial
pose to the target", Sec. V-A); here:

* ``plan_to_pose``: joint-space RRTConnect (OMPL) to a set of IK solutions of the
  target TCP pose, OMPL shortcutting, cubic-spline fit and TOPP-RA time
  parameterization under scaled Panda limits plus a TCP speed cap, resampled at the
  20 Hz control rate.
* ``plan_straight_line``: the final Cartesian approach (pre-grasp -> grasp along the
  approach axis), a minimum-jerk SE(3) interpolation solved by IK sample by sample.

All poses are ``(4, 4)`` world-frame transforms of ManiSkill's TCP link
``panda_hand_tcp`` (z = approach axis, y = finger closing axis; see ``panda_model``).
Joint vectors are ``(7,)`` arm joints in radians (fingers locked open).

Collision checking of motions: OMPL checks every segment at ``collision_resolution``
rad (joint-space L2, via ``setStateValidityCheckingResolution`` as a fraction of the
space extent); the final time-parameterized trajectory is re-checked at the same
resolution (joint-space L-inf) before it is returned, so what is returned is
collision-free in between its 20 Hz samples too.
"""

from __future__ import annotations

import math
import time
from collections.abc import Iterable
from dataclasses import dataclass, field
from typing import Literal

import numpy as np
import ompl.base as ob
import ompl.geometric as og
import ompl.util as ou
import toppra
import toppra.algorithm
import toppra.constraint
import torch

from rtv3_maniskill import se3
from rtv3_maniskill.robot.collision_world import CollisionMargins, PandaCollisionWorld
from rtv3_maniskill.robot.panda_model import (
    DOF,
    PANDA_ACCELERATION_LIMITS,
    PANDA_VELOCITY_LIMITS,
    REST_QPOS,
    PandaKinematics,
    as_joint_vector,
    as_pose_matrix,
)
from rtv3_maniskill.robot.scene_geometry import SceneGeometry

FailureReason = Literal["ik_failed", "start_in_collision", "goal_in_collision", "planning_failed", "timeout"]
FAILURE_REASONS: tuple[str, ...] = ("ik_failed", "start_in_collision", "goal_in_collision", "planning_failed",
                                    "timeout")

ou.setLogLevel(ou.LogLevel.LOG_WARN)


@dataclass
class JointTrajectory:
    """A time-parameterized arm trajectory sampled at the control rate.

    ``q`` ``(S, 7)`` joint positions (rad), ``qd`` ``(S, 7)`` joint velocities (rad/s),
    ``t`` ``(S,)`` times (s) from 0 in steps of ``dt``. The last sample is the goal,
    at rest.
    """

    q: np.ndarray
    qd: np.ndarray
    t: np.ndarray

    def __post_init__(self) -> None:
        self.q = np.asarray(self.q, dtype=np.float64)
        self.qd = np.asarray(self.qd, dtype=np.float64)
        self.t = np.asarray(self.t, dtype=np.float64)
        if self.q.ndim != 2 or self.q.shape[1] != DOF:
            raise ValueError(f"q must be (S, 7), got {self.q.shape}")
        if self.qd.shape != self.q.shape:
            raise ValueError(f"qd must match q's shape {self.q.shape}, got {self.qd.shape}")
        if self.t.shape != (self.q.shape[0],):
            raise ValueError(f"t must be ({self.q.shape[0]},), got {self.t.shape}")
        if not (np.isfinite(self.q).all() and np.isfinite(self.qd).all() and np.isfinite(self.t).all()):
            raise ValueError("trajectory contains NaN or inf")

    @property
    def duration(self) -> float:
        """Time of the last sample (s)."""
        return float(self.t[-1]) if len(self.t) else 0.0

    def __len__(self) -> int:
        return self.q.shape[0]

    def concatenate(self, other: JointTrajectory) -> JointTrajectory:
        """This trajectory followed by ``other``, which must start where this one ends.

        ``other``'s first sample (a duplicate of this one's last) is dropped and its
        times are shifted so the result stays on the same ``dt`` grid.
        """
        if np.abs(other.q[0] - self.q[-1]).max() > 1e-3:
            raise ValueError("other trajectory does not start at this trajectory's last configuration")
        return JointTrajectory(
            q=np.concatenate([self.q, other.q[1:]]),
            qd=np.concatenate([self.qd, other.qd[1:]]),
            t=np.concatenate([self.t, self.t[-1] + other.t[1:] - other.t[0]]),
        )


@dataclass
class PlanResult:
    """Outcome of a planning call.

    ``trajectory`` is set iff ``success``; otherwise ``failure_reason`` is one of
    ``FAILURE_REASONS``. ``goal_q`` ``(7,)`` is the reached configuration,
    ``waypoints`` ``(K, 7)`` the simplified geometric path, ``planning_time`` in s.
    """

    success: bool
    trajectory: JointTrajectory | None = None
    failure_reason: FailureReason | None = None
    message: str = ""
    goal_q: np.ndarray | None = None
    waypoints: np.ndarray | None = None
    planning_time: float = 0.0

    def __post_init__(self) -> None:
        if self.success != (self.trajectory is not None):
            raise ValueError("a PlanResult has a trajectory iff it succeeded")
        if not self.success and self.failure_reason not in FAILURE_REASONS:
            raise ValueError(f"failure_reason must be one of {FAILURE_REASONS}, got {self.failure_reason!r}")


@dataclass
class IKSolutions:
    """IK outcome: collision-free ``solutions`` (each ``(7,)``), nearest to the seed first.

    ``num_in_collision`` counts converged solutions rejected for collisions (tells
    "goal in collision" apart from "unreachable").
    """

    solutions: list[np.ndarray] = field(default_factory=list)
    num_in_collision: int = 0


@dataclass(frozen=True)
class PlannerConfig:
    """Planner settings (SI units).

    Speeds: ``velocity_scale``/``acceleration_scale`` scale the Panda's joint limits
    (URDF velocities, datasheet accelerations) and ``max_tcp_speed`` caps the TCP's
    linear speed along the path, so demonstrations move at a teleoperation-like pace
    (~0.1-0.2 m/s) rather than at the robot's top speed.
    """

    control_dt: float = 0.05
    """Output sample period (ManiSkill's 20 Hz control)."""
    velocity_scale: float = 0.4
    acceleration_scale: float = 0.3
    max_tcp_speed: float = 0.2
    """Cap on the TCP's linear speed (m/s) for ``plan_to_pose``."""
    collision_resolution: float = 0.005
    """Joint-space step (rad) at which motions are collision-checked."""
    margins: CollisionMargins = CollisionMargins(objects=0.01, table=0.005, self=0.0)
    """Security margins for free-space motion (``plan_to_pose``)."""
    approach_margins: CollisionMargins = CollisionMargins(objects=0.003, table=0.002, self=0.0)
    """Security margins for the straight-line approach (the fingers come close)."""
    joint_limit_margin: float = 0.02
    """rad kept from every joint limit by IK goals and the planner's state space."""
    ik_attempts: int = 40
    """IK seeds tried per target (the seed configuration first, then random ones)."""
    num_goal_solutions: int = 4
    """Diverse IK goal configurations handed to OMPL as goal states."""
    ik_min_separation: float = 0.2
    """Two IK solutions count as distinct when they differ by more than this (rad, L-inf)."""
    ik_pos_tol: float = 1e-4
    ik_rot_tol: float = 1e-3
    simplify_time: float = 0.5
    """Time budget (s) for OMPL's path simplification."""
    approach_speed: float = 0.05
    """Peak TCP speed (m/s) of the straight-line approach."""
    approach_angular_speed: float = 0.5
    """Peak TCP angular speed (rad/s) of the straight-line approach."""
    max_joint_jump: float = 0.1
    """Largest joint change (rad) allowed between consecutive straight-line samples."""
    spline_spacing: float = 0.1
    """Joint-space spacing (rad) of the points the time-parameterization spline passes through."""


class _TcpSpeedConstraint(toppra.constraint.LinearConstraint):
    """TOPP-RA constraint ``|v_tcp(s)| = |J_v(q(s)) q'(s)| sdot <= v_max``.

    Expressed as a bound on ``x = sdot^2`` at every grid point.
    """

    def __init__(self, kinematics: PandaKinematics, v_max: float) -> None:
        super().__init__()
        self.kin = kinematics
        self.v_max = v_max
        self.dof = DOF

    def compute_constraint_params(self, path, gridpoints):
        qs = path(gridpoints)
        dqs = path(gridpoints, 1)
        xbound = np.zeros((len(gridpoints), 2))
        for i, (q, dq) in enumerate(zip(qs, dqs)):
            speed_per_s = np.linalg.norm(self.kin.tcp_linear_jacobian_world(q) @ dq)
            xbound[i, 1] = (self.v_max / speed_per_s) ** 2 if speed_per_s > 1e-9 else 1e12
        return None, None, None, None, None, None, xbound


def _seed_ompl(seed: int) -> None:
    """Seed OMPL's RNG seed generator (``ompl.util.RNG.setSeed``).

    OMPL logs an error when the seed changes after random numbers were drawn; the
    reseed still applies to every RNG created afterwards, and a plan creates fresh
    planners and samplers, so planning is reproducible per seed. The log is muted.
    """
    level = ou.getLogLevel()
    ou.setLogLevel(ou.LogLevel.LOG_NONE)
    try:
        ou.RNG.setSeed(int(seed) % (2**31 - 2) + 1)  # OMPL rejects 0
    finally:
        ou.setLogLevel(level)


class PandaPlanner:
    """Collision-aware motion planner for ManiSkill's Panda in one scene.

    >>> planner = PandaPlanner(scene)            # scene: SceneGeometry or None (table only)
    >>> res = planner.plan_to_pose(q0, pregrasp, seed=3)
    >>> app = planner.plan_straight_line(res.goal_q, grasp, ignore_objects={target_idx})
    """

    def __init__(
        self,
        scene: SceneGeometry | None = None,
        config: PlannerConfig = PlannerConfig(),
        kinematics: PandaKinematics | None = None,
    ) -> None:
        self.config = config
        self.kin = kinematics if kinematics is not None else PandaKinematics()
        self.scene = scene
        self.world = PandaCollisionWorld(self.kin, scene, config.margins)
        self._active_margins = config.margins
        self.velocity_limits = PANDA_VELOCITY_LIMITS * config.velocity_scale
        self.acceleration_limits = PANDA_ACCELERATION_LIMITS * config.acceleration_scale

    # ------------------------------------------------------------------ scene / checks

    def set_scene(self, scene: SceneGeometry | None) -> None:
        """Replace the obstacles (the robot model is kept)."""
        self.scene = scene
        self.world = PandaCollisionWorld(self.kin, scene, self.config.margins)
        self._active_margins = self.config.margins

    def _use_margins(self, margins: CollisionMargins) -> None:
        if margins != self._active_margins:
            self.world.set_margins(margins)
            self._active_margins = margins

    def _clip_start(self, q_start: np.ndarray) -> np.ndarray:
        """Clip a start ``(7,)`` that exceeds the joint limits by at most 1 mrad (simulator read-outs).

        Larger violations are left alone and reported as ``start_in_collision``.
        """
        lower, upper = self.kin.lower, self.kin.upper
        if np.all(q_start >= lower - 1e-3) and np.all(q_start <= upper + 1e-3):
            return np.clip(q_start, lower, upper)
        return q_start

    def forward_kinematics(self, q) -> np.ndarray:
        """``(4, 4)`` world pose of the TCP (``panda_hand_tcp``) at ``q (7,)``."""
        return self.kin.forward_kinematics(q)

    def is_collision_free(self, q, ignore_objects: Iterable[int] = ()) -> bool:
        """Whether ``q (7,)`` is within limits and collision-free under the free-space margins."""
        self._use_margins(self.config.margins)
        return self.world.is_collision_free(q, ignore_objects)

    def motion_collision_free(self, qs: np.ndarray, ignore_objects: Iterable[int] = (),
                              resolution: float | None = None) -> bool:
        """Whether the piecewise-linear joint path through ``qs (K, 7)`` is collision-free.

        Every segment is checked at ``resolution`` rad (L-inf; default
        ``config.collision_resolution``) with the currently active margins.
        """
        qs = np.asarray(qs, dtype=np.float64)
        if qs.ndim != 2 or qs.shape[1] != DOF:
            raise ValueError(f"qs must be (K, 7), got {qs.shape}")
        res = resolution if resolution is not None else self.config.collision_resolution
        if not self.world.is_collision_free(qs[0], ignore_objects):
            return False
        lower, upper = self.kin.lower - 1e-6, self.kin.upper + 1e-6
        for a, b in zip(qs[:-1], qs[1:]):
            n = max(1, math.ceil(np.abs(b - a).max() / res))
            for k in range(1, n + 1):
                q = a + (b - a) * (k / n)
                if np.any(q < lower) or np.any(q > upper) or not self.world.check_fast(q):
                    return False
        return True

    # ------------------------------------------------------------------ IK

    def solve_ik_solutions(
        self,
        target,
        q_seed=None,
        *,
        num_solutions: int = 1,
        check_collision: bool = True,
        ignore_objects: Iterable[int] = (),
        seed: int = 0,
        attempts: int | None = None,
    ) -> IKSolutions:
        """Up to ``num_solutions`` diverse IK solutions for the TCP pose ``target (4, 4)``.

        The first attempt starts from ``q_seed (7,)`` (default: ManiSkill's rest pose),
        then random configurations (``numpy`` generator seeded by ``seed``). Solutions
        are within the joint limits, collision-free under ``config.margins`` when
        ``check_collision`` (pass the grasped object in ``ignore_objects`` for grasp
        poses) and sorted by joint distance to ``q_seed``.
        """
        target = as_pose_matrix(target, "target")
        q_seed = REST_QPOS.copy() if q_seed is None else as_joint_vector(q_seed, "q_seed")
        if num_solutions < 1:
            raise ValueError(f"num_solutions must be >= 1, got {num_solutions}")
        cfg = self.config
        self._use_margins(cfg.margins)
        rng = np.random.default_rng(seed)
        ignore = list(ignore_objects)
        out = IKSolutions()
        converged: list[np.ndarray] = []
        n_attempts = attempts if attempts is not None else cfg.ik_attempts
        for attempt in range(n_attempts):
            start = q_seed if attempt == 0 else self.kin.random_configuration(rng, margin=0.05)
            q, ok = self.kin.ik_from_seed(
                target, start, pos_tol=cfg.ik_pos_tol, rot_tol=cfg.ik_rot_tol, limit_margin=cfg.joint_limit_margin
            )
            if not ok:
                continue
            if any(np.abs(q - c).max() < cfg.ik_min_separation for c in converged):
                continue
            converged.append(q)
            if check_collision and not self.world.is_collision_free(q, ignore):
                out.num_in_collision += 1
                continue
            out.solutions.append(q)
            if len(out.solutions) >= num_solutions:
                break
        out.solutions.sort(key=lambda s: float(np.linalg.norm(s - q_seed)))
        return out

    def solve_ik(self, target, q_seed=None, **kwargs) -> np.ndarray | None:
        """One collision-free IK solution ``(7,)`` for ``target (4, 4)``, or None.

        Keyword arguments as ``solve_ik_solutions``.
        """
        sols = self.solve_ik_solutions(target, q_seed, num_solutions=1, **kwargs).solutions
        return sols[0] if sols else None

    # ------------------------------------------------------------------ free-space planning

    def plan_to_pose(
        self,
        q_start,
        target,
        *,
        timeout: float = 5.0,
        seed: int = 0,
        ignore_objects: Iterable[int] = (),
    ) -> PlanResult:
        """Collision-free trajectory from ``q_start (7,)`` to the TCP pose ``target (4, 4)``.

        IK gives up to ``config.num_goal_solutions`` goal configurations; RRTConnect
        plans to any of them (OMPL ``GoalStates``) within what is left of ``timeout``
        s after IK; the path is shortcut, splined and time-parameterized (TOPP-RA) and
        resampled at ``config.control_dt``. Collisions use ``config.margins``;
        ``ignore_objects`` (object indices, -1 = table) are not checked. Reproducible
        for a given ``seed`` (OMPL and numpy are seeded from it).
        """
        t0 = time.perf_counter()
        q_start = self._clip_start(as_joint_vector(q_start, "q_start"))
        target = as_pose_matrix(target, "target")
        if timeout <= 0:
            raise ValueError(f"timeout must be > 0 s, got {timeout}")
        ignore = list(ignore_objects)
        self._use_margins(self.config.margins)

        def fail(reason: str, message: str) -> PlanResult:
            return PlanResult(False, failure_reason=reason, message=message, planning_time=time.perf_counter() - t0)

        if not self.world.is_collision_free(q_start, ignore):
            pairs = self.world.colliding_pairs(q_start, ignore)
            limits = "" if self.kin.within_limits(q_start, 1e-6) else " (outside joint limits)"
            return fail("start_in_collision", f"start configuration in collision{limits}: {pairs[:4]}")
        ik = self.solve_ik_solutions(target, q_start, num_solutions=self.config.num_goal_solutions,
                                     ignore_objects=ignore, seed=seed)
        if not ik.solutions:
            if ik.num_in_collision:
                return fail("goal_in_collision", f"all {ik.num_in_collision} IK solutions collide")
            return fail("ik_failed", f"no IK solution after {self.config.ik_attempts} attempts")
        goals = np.stack(ik.solutions)

        path, status = self._rrt_connect(q_start, goals, timeout - (time.perf_counter() - t0), seed, ignore)
        if path is None:
            if status == "timeout":
                return fail("timeout", f"RRTConnect found no path within {timeout:.2f} s")
            return fail("planning_failed", f"RRTConnect failed: {status}")
        traj = self._time_parameterize(path, ignore)
        if traj is None:
            return fail("planning_failed", "time-parameterized trajectory could not be made collision-free")
        return PlanResult(
            True,
            trajectory=traj,
            goal_q=path[-1].copy(),
            waypoints=path,
            planning_time=time.perf_counter() - t0,
            message=f"{len(path)} waypoints, {traj.duration:.2f} s",
        )

    def _rrt_connect(self, q_start, goals, time_left, seed, ignore) -> tuple[np.ndarray | None, str]:
        """OMPL RRTConnect + simplification; returns ``(path (K, 7) or None, status)``."""
        if time_left <= 0:
            return None, "timeout"
        _seed_ompl(seed)
        space = ob.RealVectorStateSpace(DOF)
        bounds = ob.RealVectorBounds(DOF)
        for i in range(DOF):
            bounds.setLow(i, float(self.kin.lower[i] + self.config.joint_limit_margin))
            bounds.setHigh(i, float(self.kin.upper[i] - self.config.joint_limit_margin))
        space.setBounds(bounds)
        ss = og.SimpleSetup(space)
        world = self.world
        world.set_ignored(ignore)
        buf = np.zeros(DOF)

        def valid(state) -> bool:
            for i in range(DOF):
                buf[i] = state[i]
            return world.check_fast(buf)

        ss.setStateValidityChecker(valid)
        si = ss.getSpaceInformation()
        si.setStateValidityCheckingResolution(self.config.collision_resolution / space.getMaximumExtent())

        def to_state(q):
            s = space.allocState()
            for i in range(DOF):
                s[i] = float(q[i])
            return s

        ss.setStartState(to_state(q_start))
        goal = ob.GoalStates(si)
        for g in goals:
            goal.addState(to_state(g))
        ss.setGoal(goal)
        ss.setPlanner(og.RRTConnect(si))
        status = ss.solve(float(time_left))
        name = str(status)
        if not ss.haveExactSolutionPath():
            return None, "timeout" if status.getStatus() == ob.PlannerStatus.TIMEOUT else name
        ss.simplifySolution(self.config.simplify_time)
        path = ss.getSolutionPath()
        out = np.array([[path.getState(k)[i] for i in range(DOF)] for k in range(path.getStateCount())])
        # Drop repeated states (zero-length segments break the arc-length spline).
        keep = [0] + [k for k in range(1, len(out)) if np.linalg.norm(out[k] - out[k - 1]) > 1e-9]
        return out[keep], name

    def _time_parameterize(self, path: np.ndarray, ignore) -> JointTrajectory | None:
        """TOPP-RA on a cubic spline through the (densified) path, then a dense collision check.

        The spline passes through points every ``config.spline_spacing`` rad of the
        piecewise-linear path; if the spline cuts a corner into an obstacle the
        spacing is halved (up to 3 times).
        """
        spacing = self.config.spline_spacing
        for _ in range(4):
            dense = _densify(path, spacing)
            traj = self._toppra(dense)
            if traj is not None and self.motion_collision_free(traj[1], ignore):
                return traj[0]
            spacing /= 2
        return None

    def _toppra(self, dense: np.ndarray) -> tuple[JointTrajectory, np.ndarray] | None:
        """Time-optimal parameterization of a spline through ``dense (K, 7)``.

        Returns the 20 Hz trajectory and ``(M, 7)`` samples of the continuous
        trajectory fine enough for collision checking (joint step <=
        ``collision_resolution`` between samples at the velocity limits).
        """
        if len(dense) < 2:
            return _rest_trajectory(dense[0], self.config.control_dt), dense[:1]
        ss_wp = np.concatenate([[0.0], np.cumsum(np.linalg.norm(np.diff(dense, axis=0), axis=1))])
        spline = toppra.SplineInterpolator(ss_wp, dense, bc_type="natural")
        # 0.5 % head-room: TOPP-RA's discretized solution may exceed a bound by ~0.02 %.
        constraints = [
            toppra.constraint.JointVelocityConstraint(self.velocity_limits * 0.995),
            toppra.constraint.JointAccelerationConstraint(self.acceleration_limits * 0.995),
            _TcpSpeedConstraint(self.kin, self.config.max_tcp_speed * 0.995),
        ]
        n_grid = max(100, int(ss_wp[-1] / 0.01))
        grid = np.linspace(0.0, ss_wp[-1], n_grid + 1)
        algo = toppra.algorithm.TOPPRA(constraints, spline, gridpoints=grid, parametrizer="ParametrizeConstAccel")
        timed = algo.compute_trajectory(0.0, 0.0)
        if timed is None:
            return None
        fine_dt = self.config.collision_resolution / float(self.velocity_limits.max())
        fine_t = np.append(np.arange(0.0, timed.duration, fine_dt), timed.duration)
        return _resample(timed, self.config.control_dt, dense[0], dense[-1]), np.asarray(timed(fine_t))

    # ------------------------------------------------------------------ straight-line approach

    def plan_straight_line(
        self,
        q_start,
        target,
        *,
        ignore_objects: Iterable[int] = (),
        speed: float | None = None,
        check_collision: bool = True,
    ) -> PlanResult:
        """Cartesian straight-line TCP motion from ``FK(q_start)`` to ``target (4, 4)``.

        Poses follow ``T(s) = T_0 Exp(s xi)``, ``xi = log(T_0^-1 T_target)`` (a straight
        line in position, a geodesic in rotation) with a minimum-jerk timing of peak
        TCP speed ``speed`` (default ``config.approach_speed``), sampled at the control
        rate and solved by IK sample by sample, each seeded from the previous one.
        Collisions use ``config.approach_margins``; ``ignore_objects`` (object indices)
        are skipped, e.g. the object about to be grasped.
        """
        t0 = time.perf_counter()
        q_start = self._clip_start(as_joint_vector(q_start, "q_start"))
        target = as_pose_matrix(target, "target")
        cfg = self.config
        speed = cfg.approach_speed if speed is None else float(speed)
        if not speed > 0:
            raise ValueError(f"speed must be > 0 m/s, got {speed}")
        ignore = list(ignore_objects)
        self._use_margins(cfg.approach_margins)
        try:

            def fail(reason: str, message: str) -> PlanResult:
                return PlanResult(False, failure_reason=reason, message=message, planning_time=time.perf_counter() - t0)

            if check_collision and not self.world.is_collision_free(q_start, ignore):
                return fail("start_in_collision",
                            f"start configuration in collision: {self.world.colliding_pairs(q_start, ignore)[:4]}")
            start_pose = self.kin.forward_kinematics(q_start)
            xi = se3.se3_log(se3.relative_transform(torch.from_numpy(start_pose), torch.from_numpy(target))).numpy()
            length, angle = float(np.linalg.norm(xi[:3])), float(np.linalg.norm(xi[3:]))
            # Minimum-jerk s(tau) = 10 tau^3 - 15 tau^4 + 6 tau^5 peaks at 1.875 / T.
            duration = max(1.875 * length / speed, 1.875 * angle / cfg.approach_angular_speed, cfg.control_dt)
            n = math.ceil(duration / cfg.control_dt - 1e-9)
            times = np.arange(n + 1) * cfg.control_dt
            tau = np.clip(times / duration, 0.0, 1.0)
            sigma = 10 * tau**3 - 15 * tau**4 + 6 * tau**5
            sigma_dot = (30 * tau**2 - 60 * tau**3 + 30 * tau**4) / duration
            poses = (torch.from_numpy(start_pose) @ se3.se3_exp(torch.from_numpy(sigma[:, None] * xi[None]))).numpy()
            qs = np.zeros((n + 1, DOF))
            qds = np.zeros((n + 1, DOF))
            qs[0] = q_start
            for k in range(1, n + 1):
                q, ok = self.kin.ik_from_seed(poses[k], qs[k - 1], max_iters=100, pos_tol=cfg.ik_pos_tol,
                                              rot_tol=cfg.ik_rot_tol)
                if not ok:
                    return fail("ik_failed", f"IK failed at straight-line sample {k}/{n}")
                if np.abs(q - qs[k - 1]).max() > cfg.max_joint_jump:
                    return fail("planning_failed",
                                f"joint jump of {np.abs(q - qs[k - 1]).max():.3f} rad at sample {k}/{n}")
                qs[k] = q
            for k in range(1, n):
                # Body twist along the line is xi * sigma_dot; joint rates from the Jacobian.
                qds[k] = np.linalg.lstsq(self.kin.tcp_jacobian(qs[k]), xi * sigma_dot[k], rcond=None)[0]
            if check_collision:
                if not self.world.is_collision_free(qs[-1], ignore):
                    return fail("goal_in_collision",
                                f"target configuration in collision: {self.world.colliding_pairs(qs[-1], ignore)[:4]}")
                if not self.motion_collision_free(qs, ignore):
                    return fail("planning_failed", "straight-line motion collides")
            traj = JointTrajectory(q=qs, qd=qds, t=times)
            return PlanResult(True, trajectory=traj, goal_q=qs[-1].copy(), waypoints=qs[[0, -1]].copy(),
                              planning_time=time.perf_counter() - t0)
        finally:
            self._use_margins(cfg.margins)


# ---------------------------------------------------------------------- helpers


def _densify(path: np.ndarray, spacing: float) -> np.ndarray:
    """Insert points so consecutive points of ``path (K, 7)`` are at most ``spacing`` apart (L2)."""
    out = [path[0]]
    for a, b in zip(path[:-1], path[1:]):
        n = max(1, math.ceil(np.linalg.norm(b - a) / spacing))
        for k in range(1, n + 1):
            out.append(a + (b - a) * (k / n))
    return np.stack(out)


def _resample(timed, dt: float, q_first: np.ndarray, q_last: np.ndarray) -> JointTrajectory:
    """Sample a toppra trajectory every ``dt`` s; the last sample is the goal at rest."""
    duration = float(timed.duration)
    n = max(1, math.ceil(duration / dt - 1e-9))
    t = np.arange(n + 1) * dt
    ts = np.minimum(t, duration)
    q = np.asarray(timed(ts))
    qd = np.asarray(timed(ts, 1))
    q[0], qd[0] = q_first, 0.0
    q[-1], qd[-1] = q_last, 0.0
    return JointTrajectory(q=q, qd=qd, t=t)


def _rest_trajectory(q: np.ndarray, dt: float) -> JointTrajectory:
    return JointTrajectory(q=np.stack([q, q]), qd=np.zeros((2, DOF)), t=np.array([0.0, dt]))

