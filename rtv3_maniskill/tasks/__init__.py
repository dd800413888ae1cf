"""ManiSkill tasks. Importing this registers ``GraspClutter-v1`` and the ``panda_twist`` agent."""

from rtv3_maniskill.tasks.grasp_clutter import GraspClutterEnv

__all__ = ["GraspClutterEnv"]
