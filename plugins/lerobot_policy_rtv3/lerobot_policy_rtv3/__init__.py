"""LeRobot plugin shim for the RT-V3 policy.

LeRobot's CLIs (``lerobot-train``, ``lerobot-eval``, ``lerobot-record``) call
``register_third_party_plugins()``, which imports every installed distribution named
``lerobot_policy_*``. Importing this package imports :mod:`rtv3_maniskill.policies.rtv3`,
which registers ``RTV3Config`` as policy type ``rtv3``; LeRobot's factory then finds
``RTV3Policy`` (``modeling_rtv3``) and ``make_rtv3_pre_post_processors`` (``processor_rtv3``)
by its naming rules.
"""

from rtv3_maniskill.policies.rtv3 import RTV3Config  # noqa: F401  (registers policy type "rtv3")

__all__ = ["RTV3Config"]

# Registers `--env.type=rtv3_clutter` (GraspClutter-v1 for lerobot-eval).
from rtv3_maniskill import lerobot_env  # noqa: E402,F401
