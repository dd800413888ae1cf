"""Settings of the Panda motion planner (:class:`~rtv3_maniskill.robot.planner.PandaPlanner`)."""

from __future__ import annotations

import math
from dataclasses import dataclass, replace

from rtv3_maniskill.robot.collision_world import CollisionMargins

DEFAULT_CLEARANCE = 0.01
"""m the free-space motion keeps from the scene's objects by default (``PlannerConfig.margins.objects``)."""


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
    """Fraction of the URDF joint velocity limits the free-space trajectory may use."""
    acceleration_scale: float = 0.3
    """Fraction of the datasheet joint acceleration limits the free-space trajectory may use."""
    max_tcp_speed: float = 0.2
    """Cap on the TCP's linear speed (m/s) for ``plan_to_pose``."""
    collision_resolution: float = 0.005
    """Joint-space step (rad) at which motions are collision-checked."""
    margins: CollisionMargins = CollisionMargins(objects=0.01, table=0.005, self=0.0)
    """Security margins for free-space motion (``plan_to_pose``) and its IK goals: the least it keeps."""
    clearance: float = DEFAULT_CLEARANCE
    """m the free-space path keeps from the objects away from its ends (>= ``margins.objects``): beyond
    ``clearance_release`` of the start's and the goal's TCP positions every state must clear the objects by
    this much, so the path keeps away from the clutter on its way and comes close only where the start or the
    pre-grasp is. A soft preference, as the authors' collision cost is: when no such path turns up within half
    the time, the search runs again under ``margins`` alone."""
    clearance_release: float = 0.08
    """TCP distance (m) from the start and from the goal within which only ``margins`` apply."""
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
    """IK convergence: TCP position error (m)."""
    ik_rot_tol: float = 1e-3
    """IK convergence: TCP rotation error (rad)."""
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

    def __post_init__(self) -> None:
        positive = ("control_dt", "velocity_scale", "acceleration_scale", "max_tcp_speed", "collision_resolution",
                    "ik_pos_tol", "ik_rot_tol", "approach_speed", "approach_angular_speed", "max_joint_jump",
                    "spline_spacing")
        for name in positive:
            value = getattr(self, name)
            if not (math.isfinite(value) and value > 0):
                raise ValueError(f"PlannerConfig.{name} must be a positive number, got {value}")
        for name in ("joint_limit_margin", "ik_min_separation", "simplify_time"):
            value = getattr(self, name)
            if not (math.isfinite(value) and value >= 0):
                raise ValueError(f"PlannerConfig.{name} must be a number >= 0, got {value}")
        if not (math.isfinite(self.clearance) and self.margins.objects <= self.clearance <= 0.1):
            raise ValueError(f"PlannerConfig.clearance must be in [margins.objects = {self.margins.objects}, 0.1] m, "
                             f"got {self.clearance}")
        if not (math.isfinite(self.clearance_release) and self.clearance_release >= 0):
            raise ValueError(f"PlannerConfig.clearance_release must be a number >= 0, got {self.clearance_release}")
        for name in ("ik_attempts", "num_goal_solutions"):
            if getattr(self, name) < 1:
                raise ValueError(f"PlannerConfig.{name} must be >= 1, got {getattr(self, name)}")


def with_clearance(clearance: float, config: PlannerConfig | None = None) -> PlannerConfig:
    """``config`` (default: the defaults) whose free-space paths keep ``clearance`` m from the objects on
    their way (``PlannerConfig.clearance``); below ``margins.objects`` the margin itself is lowered.

    Demonstrations planned with about 3 cm (the authors' CuRobo starts its collision cost 2.5 cm out) keep
    further from the clutter on the way to the pre-grasp; the straight-line approach and the table keep their
    own margins, and every target reachable under the defaults stays reachable.
    """
    if not (math.isfinite(clearance) and 0 <= clearance <= 0.1):
        raise ValueError(f"clearance must be a distance in [0, 0.1] m, got {clearance}")
    config = config if config is not None else PlannerConfig()
    margins = replace(config.margins, objects=min(config.margins.objects, float(clearance)))
    return replace(config, margins=margins, clearance=float(clearance))
