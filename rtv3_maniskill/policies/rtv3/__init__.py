"""RT-V3 prior as a LeRobot policy (type ``rtv3``).

Importing this package registers :class:`RTV3Config` under the name ``rtv3`` (cheap: only
LeRobot's config module is imported). The policy class and processor factory are loaded
lazily (they load LeRobot's policy stack), the way LeRobot's factory resolves third-party policies:
``configuration_rtv3.RTV3Config`` -> ``modeling_rtv3.RTV3Policy`` ->
``processor_rtv3.make_rtv3_pre_post_processors``.
"""

from __future__ import annotations

from typing import Any

from rtv3_maniskill.policies.rtv3.checkpoints import SHIPPED_CHECKPOINT, load_policy
from rtv3_maniskill.policies.rtv3.model import RTV3Model

try:
    from rtv3_maniskill.policies.rtv3.configuration_rtv3 import RTV3Config
except ModuleNotFoundError as err:  # a machine with PyTorch alone trains the model (compact_training.py)
    if (err.name or "").split(".")[0] != "lerobot":
        raise
    _LEROBOT_MISSING = err

__all__ = ["RTV3Config", "RTV3Policy", "RTV3Model", "SHIPPED_CHECKPOINT", "load_policy",
           "make_rtv3_pre_post_processors"]


def __getattr__(name: str) -> Any:
    if name in ("RTV3Config", "RTV3Policy", "make_rtv3_pre_post_processors") and "_LEROBOT_MISSING" in globals():
        raise ImportError(f"rtv3_maniskill.policies.rtv3.{name} needs LeRobot, which is not installed here "
                          f"({_LEROBOT_MISSING}); without it only the model trains (rtv3_maniskill.policies.rtv3."
                          "compact_training)")
    # Lazy: the policy and its processors load LeRobot's policy stack (~0.7 s more than the config).
    if name == "RTV3Policy":
        from rtv3_maniskill.policies.rtv3.modeling_rtv3 import RTV3Policy

        return RTV3Policy
    if name == "make_rtv3_pre_post_processors":
        from rtv3_maniskill.policies.rtv3.processor_rtv3 import make_rtv3_pre_post_processors

        return make_rtv3_pre_post_processors
    raise AttributeError(f"module {__name__!r} has no attribute {name!r}")
