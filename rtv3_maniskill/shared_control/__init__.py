"""Shared control: RT-V3 posterior decision making, baselines and simulated users."""

from rtv3_maniskill.shared_control.config import SharedControlConfig
from rtv3_maniskill.shared_control.diagnostics import SharedControlDiagnostics
from rtv3_maniskill.shared_control.direct import DirectTeleoperation
from rtv3_maniskill.shared_control.hindsight_optimization import HindsightOptimization
from rtv3_maniskill.shared_control.mode_search import mixture_mode
from rtv3_maniskill.shared_control.posterior import FactorizedTwistMixture, fuse_user_command, prior_twist_mixture
from rtv3_maniskill.shared_control.shared_controller import SharedController
from rtv3_maniskill.shared_control.simulated_users import SimulatedUser, make_user
from rtv3_maniskill.shared_control.user_covariance import UserCovarianceEstimator

__all__ = [
    "DirectTeleoperation",
    "FactorizedTwistMixture",
    "HindsightOptimization",
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
