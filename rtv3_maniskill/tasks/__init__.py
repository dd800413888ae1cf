"""ManiSkill tasks. Importing this loads ManiSkill and registers ``GraspClutter-v1`` (ManiSkill's
own registration, in place of the lazy one made by ``import rtv3_maniskill``) and the
``panda_twist`` agent."""

import gymnasium as gym

from rtv3_maniskill import ENV_ID

gym.registry.pop(ENV_ID, None)  # the lazy spec: ManiSkill's register_env adds the real one

from rtv3_maniskill.tasks.grasp_clutter import GraspClutterEnv  # noqa: E402

__all__ = ["GraspClutterEnv"]
