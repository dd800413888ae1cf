"""RT-V3 shared control on ManiSkill3 and LeRobot.

``import rtv3_maniskill`` registers the ManiSkill task ``GraspClutter-v1`` with gymnasium
without loading the simulator: ManiSkill and SAPIEN load on the first
``gym.make("GraspClutter-v1", ...)`` (or on ``import rtv3_maniskill.tasks``). The pure parts
(``se3``, ``features``, ``shared_control``, ``policies``) never load them.
"""

from __future__ import annotations

__version__ = "0.1.0"

ENV_ID = "GraspClutter-v1"
MAX_EPISODE_STEPS = 150


def _register_lazily() -> None:
    try:
        import gymnasium as gym
    except ModuleNotFoundError:  # a machine that only trains the model (policies/rtv3/compact_training.py)
        return
    from gymnasium.envs.registration import WrapperSpec

    if ENV_ID in gym.registry:
        return
    gym.register(
        ENV_ID,
        entry_point="rtv3_maniskill.tasks:make_grasp_clutter",
        max_episode_steps=MAX_EPISODE_STEPS,
        disable_env_checker=True,
        # The wrapper ManiSkill's own registration adds (truncation from the env's step count).
        additional_wrappers=(WrapperSpec("MSTimeLimit", "mani_skill.utils.registration:TimeLimitWrapper",
                                         dict(max_episode_steps=MAX_EPISODE_STEPS)),),
    )


_register_lazily()
