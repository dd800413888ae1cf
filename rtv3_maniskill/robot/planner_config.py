"""Settings of the Panda motion planner (:class:`~rtv3_maniskill.robot.planner.PandaPlanner`)."""

from __future__ import annotations

import math
from dataclasses import dataclass

from rtv3_maniskill.robot.collision_world import CollisionMargins


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
        for name in ("ik_attempts", "num_goal_solutions"):
            if getattr(self, name) < 1:
                raise ValueError(f"PlannerConfig.{name} must be >= 1, got {getattr(self, name)}")
