"""ManiSkill tasks. Importing this loads ManiSkill and registers ``GraspClutter-v1`` (ManiSkill's
own registration, in place of the lazy one made by ``import rtv3_maniskill``) and the
``panda_twist`` agent."""

import gymnasium as gym
from mani_skill.utils.registration import make

from rtv3_maniskill import ENV_ID

gym.registry.pop(ENV_ID, None)  # the lazy spec: ManiSkill's register_env adds the real one

from rtv3_maniskill.tasks.grasp_clutter import GraspClutterEnv  # noqa: E402


def make_grasp_clutter(**kwargs):
    """gymnasium entry point of the lazy ``GraspClutter-v1`` (``import rtv3_maniskill``): importing this
    package replaced that registration by ManiSkill's, which builds the env."""
    return make(ENV_ID, **kwargs)


__all__ = ["GraspClutterEnv", "make_grasp_clutter"]
