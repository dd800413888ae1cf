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

The search is :mod:`~rtv3_maniskill.robot.ompl_rrt`, the timing
:mod:`~rtv3_maniskill.robot.time_parametrization`, the settings
:class:`~rtv3_maniskill.robot.planner_config.PlannerConfig` and the results
:mod:`~rtv3_maniskill.robot.trajectory`; this module holds IK, the collision checks of
motions and the straight-line approach.

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
from dataclasses import dataclass, field, replace

import numpy as np
import torch

from rtv3_maniskill import se3
from rtv3_maniskill.robot.collision_world import CollisionMargins, PandaCollisionWorld
from rtv3_maniskill.robot.ompl_rrt import rrt_connect
from rtv3_maniskill.robot.panda_model import (
    DOF,
    PANDA_ACCELERATION_LIMITS,
    PANDA_VELOCITY_LIMITS,
    REST_QPOS,
    PandaKinematics,
    as_joint_vector,
    as_pose_matrix,
)
from rtv3_maniskill.robot.planner_config import PlannerConfig
from rtv3_maniskill.robot.scene_geometry import SceneGeometry
from rtv3_maniskill.robot.time_parametrization import densify, time_optimal_trajectory
from rtv3_maniskill.robot.trajectory import JointTrajectory, PlanResult


@dataclass
class IKSolutions:
    """IK outcome: collision-free ``solutions`` (each ``(7,)``), nearest to the seed first.

    ``num_in_collision`` counts converged solutions rejected for collisions (tells
    "goal in collision" apart from "unreachable").
    """

    solutions: list[np.ndarray] = field(default_factory=list)
    num_in_collision: int = 0


class PandaPlanner:
    """Collision-aware motion planner for ManiSkill's Panda in one scene.

    >>> planner = PandaPlanner(scene)            # scene: SceneGeometry or None (table only)
    >>> res = planner.plan_to_pose(q0, pregrasp, seed=3)
    >>> app = planner.plan_straight_line(res.goal_q, grasp, ignore_objects={target_idx})
    """

    def __init__(
        self,
        scene: SceneGeometry | None = None,
        config: PlannerConfig | None = None,
        kinematics: PandaKinematics | None = None,
    ) -> None:
        config = config if config is not None else PlannerConfig()
        self.config = config
        self.kin = kinematics if kinematics is not None else PandaKinematics()
        self.scene = scene
        self.world = PandaCollisionWorld(self.kin, scene, config.margins)
        self._active_margins = config.margins
        self._clear_world = None
        """The scene under ``config.clearance`` (None when it adds nothing to ``config.margins``)."""
        if config.clearance > config.margins.objects:
            self._clear_world = PandaCollisionWorld(self.kin, scene, replace(config.margins, objects=config.clearance))
        self.velocity_limits = PANDA_VELOCITY_LIMITS * config.velocity_scale
        self.acceleration_limits = PANDA_ACCELERATION_LIMITS * config.acceleration_scale

    # ------------------------------------------------------------------ scene / checks

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

    def _into_state_space(self, q_start: np.ndarray) -> np.ndarray:
        """A start ``(7,)`` within the joint limits moved into the planner's state space, which keeps
        ``config.joint_limit_margin`` from every limit (OMPL refuses a start outside its bounds).

        States the arm visits (a rollout's, a user's) may lie in that margin; the plan then starts at most
        ``joint_limit_margin`` rad from them. Starts outside the limits are left to the collision check.
        """
        if not self.kin.within_limits(q_start, 1e-6):
            return q_start
        margin = self.config.joint_limit_margin + 1e-6
        return np.clip(q_start, self.kin.lower + margin, self.kin.upper - margin)

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
        q_start = self._into_state_space(self._clip_start(as_joint_vector(q_start, "q_start")))
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

        self.world.set_ignored(ignore)
        margin = self.config.joint_limit_margin

        def search(is_valid, time_left: float):
            return rrt_connect(q_start, goals, time_left, seed, self.kin.lower + margin, self.kin.upper - margin,
                               is_valid, self.config.collision_resolution, self.config.simplify_time)

        path, status = None, "timeout"
        if self._clear_world is not None:  # first a path that keeps the clearance on its way
            self._clear_world.set_ignored(ignore)
            ends = np.stack([self.kin.forward_kinematics(q_start)[:3, 3], target[:3, 3]])
            path, status = search(self._clearance_check(ends), 0.5 * (timeout - (time.perf_counter() - t0)))
        if path is None:
            path, status = search(self.world.check_fast, timeout - (time.perf_counter() - t0))
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

    def _clearance_check(self, ends: np.ndarray):
        """OMPL's validity check for the clearance search: ``config.margins`` within
        ``config.clearance_release`` of the TCP positions ``ends (2, 3)`` (start, goal; m), ``config.clearance``
        beyond (either world's ignore set is the one last set).

        The clearance only adds to the margins, so a state that clears it is valid anywhere: most states of a
        search are, and cost one check; only one that does not is placed (by that check's kinematics) and,
        near an end, checked again under the margins alone.
        """
        release2 = self.config.clearance_release ** 2
        near_world, clear_world = self.world, self._clear_world
        (sx, sy, sz), (gx, gy, gz) = np.asarray(ends, dtype=np.float64).tolist()

        def is_valid(q: np.ndarray) -> bool:
            if clear_world.check_fast(q):
                return True
            x, y, z = clear_world.last_tcp_position().tolist()
            near = min((x - sx) ** 2 + (y - sy) ** 2 + (z - sz) ** 2,
                       (x - gx) ** 2 + (y - gy) ** 2 + (z - gz) ** 2) < release2
            return near and near_world.check_fast(q)

        return is_valid

    def _time_parameterize(self, path: np.ndarray, ignore) -> JointTrajectory | None:
        """TOPP-RA on a cubic spline through the (densified) path, then a dense collision check.

        The spline passes through points every ``config.spline_spacing`` rad of the
        piecewise-linear path; if the spline cuts a corner into an obstacle the
        spacing is halved (up to 3 times).
        """
        spacing = self.config.spline_spacing
        for _ in range(4):
            dense = densify(path, spacing)
            cfg = self.config
            traj = time_optimal_trajectory(dense, self.kin, self.velocity_limits, self.acceleration_limits,
                                           cfg.max_tcp_speed, cfg.control_dt, cfg.collision_resolution)
            if traj is not None and self.motion_collision_free(traj[1], ignore):
                return traj[0]
            spacing /= 2
        return None

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
