"""RT-V3 prior as a LeRobot policy (type ``rtv3``).

Importing this package registers :class:`RTV3Config` under the name ``rtv3`` (cheap: only
LeRobot's config module is imported). The policy class and processor factory are loaded
lazily, the way LeRobot's factory resolves third-party policies:
``configuration_rtv3.RTV3Config`` -> ``modeling_rtv3.RTV3Policy`` ->
``processor_rtv3.make_rtv3_pre_post_processors``.
"""

from __future__ import annotations

from typing import Any

from rtv3_maniskill.policies.rtv3.checkpoints import SHIPPED_CHECKPOINT, load_policy
from rtv3_maniskill.policies.rtv3.configuration_rtv3 import RTV3Config

__all__ = ["RTV3Config", "RTV3Policy", "RTV3Model", "SHIPPED_CHECKPOINT", "load_policy",
           "make_rtv3_pre_post_processors"]


def __getattr__(name: str) -> Any:
    if name == "RTV3Policy":
        from rtv3_maniskill.policies.rtv3.modeling_rtv3 import RTV3Policy

        return RTV3Policy
    if name == "RTV3Model":
        from rtv3_maniskill.policies.rtv3.model import RTV3Model

        return RTV3Model
    if name == "make_rtv3_pre_post_processors":
        from rtv3_maniskill.policies.rtv3.processor_rtv3 import make_rtv3_pre_post_processors

        return make_rtv3_pre_post_processors
    raise AttributeError(f"module {__name__!r} has no attribute {name!r}")
