"""RT-V3 shared control on ManiSkill3 and LeRobot.

``import rtv3_maniskill`` registers the ManiSkill task ``GraspClutter-v1``.
"""

from rtv3_maniskill import tasks  # noqa: F401  (registers GraspClutter-v1)

__version__ = "0.1.0"
