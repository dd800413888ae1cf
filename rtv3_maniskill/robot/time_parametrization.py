"""Time parameterization of a joint path: a cubic spline timed by TOPP-RA, sampled at the control rate.

The spline passes through a densified copy of the piecewise-linear joint path (``(K, 7)``,
rad) and is timed to be as fast as the joint velocity and acceleration limits and a cap on the
TCP's linear speed allow; the result starts and ends at rest. Times in seconds.
"""

from __future__ import annotations

import math

import numpy as np
import toppra
import toppra.algorithm
import toppra.constraint

from rtv3_maniskill.robot.panda_model import DOF, PandaKinematics
from rtv3_maniskill.robot.trajectory import JointTrajectory


class TcpSpeedConstraint(toppra.constraint.LinearConstraint):
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


def densify(path: np.ndarray, spacing: float) -> np.ndarray:
    """Insert points so consecutive points of ``path (K, 7)`` are at most ``spacing`` apart (L2)."""
    out = [path[0]]
    for a, b in zip(path[:-1], path[1:]):
        n = max(1, math.ceil(np.linalg.norm(b - a) / spacing))
        for k in range(1, n + 1):
            out.append(a + (b - a) * (k / n))
    return np.stack(out)


def time_optimal_trajectory(
    dense: np.ndarray,
    kinematics: PandaKinematics,
    velocity_limits: np.ndarray,
    acceleration_limits: np.ndarray,
    max_tcp_speed: float,
    control_dt: float,
    collision_resolution: float,
) -> tuple[JointTrajectory, np.ndarray] | None:
    """Time-optimal parameterization of a spline through ``dense (K, 7)``; None when TOPP-RA fails.

    Limits: ``velocity_limits`` (rad/s) and ``acceleration_limits`` (rad/s^2), ``(7,)`` each,
    and ``max_tcp_speed`` (m/s). Returns the trajectory sampled every ``control_dt`` s and
    ``(M, 7)`` samples of the continuous trajectory fine enough for collision checking (joint
    step <= ``collision_resolution`` rad between samples at the velocity limits).
    """
    if len(dense) < 2:
        return _rest_trajectory(dense[0], control_dt), dense[:1]
    ss_wp = np.concatenate([[0.0], np.cumsum(np.linalg.norm(np.diff(dense, axis=0), axis=1))])
    spline = toppra.SplineInterpolator(ss_wp, dense, bc_type="natural")
    # 0.5 % head-room: TOPP-RA's discretized solution may exceed a bound by ~0.02 %.
    constraints = [
        toppra.constraint.JointVelocityConstraint(velocity_limits * 0.995),
        toppra.constraint.JointAccelerationConstraint(acceleration_limits * 0.995),
        TcpSpeedConstraint(kinematics, max_tcp_speed * 0.995),
    ]
    n_grid = max(100, int(ss_wp[-1] / 0.01))
    grid = np.linspace(0.0, ss_wp[-1], n_grid + 1)
    algo = toppra.algorithm.TOPPRA(constraints, spline, gridpoints=grid, parametrizer="ParametrizeConstAccel")
    timed = algo.compute_trajectory(0.0, 0.0)
    if timed is None:
        return None
    fine_dt = collision_resolution / float(velocity_limits.max())
    fine_t = np.append(np.arange(0.0, timed.duration, fine_dt), timed.duration)
    return _resample(timed, control_dt, dense[0], dense[-1]), np.asarray(timed(fine_t))


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
    """Two samples ``dt`` s apart, both at ``q (7,)`` and at rest."""
    return JointTrajectory(q=np.stack([q, q]), qd=np.zeros((2, DOF)), t=np.array([0.0, dt]))
