"""Shared control: RT-V3 posterior decision making, baselines, simulated users and input devices."""

from rtv3_maniskill.shared_control.direct import DirectTeleoperation
from rtv3_maniskill.shared_control.hindsight_optimization import HindsightOptimization
from rtv3_maniskill.shared_control.posterior import (
    FactorizedTwistMixture,
    UserCovarianceEstimator,
    fuse_user_command,
    mixture_mode,
    prior_twist_mixture,
)
from rtv3_maniskill.shared_control.shared_controller import (
    SharedControlConfig,
    SharedControlDiagnostics,
    SharedController,
)
from rtv3_maniskill.shared_control.simulated_users import SimulatedUser, make_user
from rtv3_maniskill.shared_control.teleop import GamepadMapping, KeyboardMapping

__all__ = [
    "DirectTeleoperation",
    "FactorizedTwistMixture",
    "GamepadMapping",
    "HindsightOptimization",
    "KeyboardMapping",
    "SharedControlConfig",
    "SharedControlDiagnostics",
    "SharedController",
    "SimulatedUser",
    "UserCovarianceEstimator",
    "fuse_user_command",
    "make_user",
    "mixture_mode",
    "prior_twist_mixture",
]
