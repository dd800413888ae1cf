"""What one step of the RT-V3 shared controller did (paper, Sec. V: mode, class weights, entropy).

Per batch element: the mode (shared / autonomous / user-only), the posterior and prior class
weights, the OOD flag, the distance to the scene, the user covariances and the step-0 mixture
behind the weights, whose entropy bounds are computed only when read.
"""

from __future__ import annotations

import math
from dataclasses import dataclass, field
from functools import cached_property

import torch

from rtv3_maniskill.shared_control import mixture_entropy
from rtv3_maniskill.shared_control.posterior import FactorizedTwistMixture


@dataclass
class SharedControlDiagnostics:
    """What happened in the last :meth:`SharedController.step` (B = batch size; B = 1 unbatched).

    Attributes:
        modes: per element one of ``"shared"``, ``"autonomous"``, ``"user_only"``.
        class_weights: ``(B, K)`` posterior class weights in shared mode, the prior's otherwise
            (empty ``(B, 0)`` when the policy was not called).
        prior_class_weights: ``(B, K)`` the prior's class weights.
        ood: ``(B,)`` bool, in the out-of-distribution window.
        surface_distance: ``(B,)`` EE distance to the nearest valid scene point (m; inf if none).
        user_trans_cov, user_rot_cov: ``(B, 3, 3)`` S_u and G_u used this step.
        fallback: ``(B,)`` bool, the empty-grasp-set fallback was used.
        shown_grasps: ``(B, M)`` bool, the candidates the prior was shown (see the field);
            grasp_candidates ``(B,)`` their number before the goal belief.
        mixture: the step-0 mixture behind ``class_weights`` (fused where shared, the prior's
            elsewhere); None when the policy was not called.

    The entropy bounds ``trans_entropy_lower``, ``trans_entropy_upper``, ``rot_entropy_lower``,
    ``rot_entropy_upper`` (``(B,)`` nats, NaN when the policy was not called) are computed from
    ``mixture`` when first read, so a control loop that does not look at them does not pay for them.
    """

    modes: tuple[str, ...]
    class_weights: torch.Tensor
    prior_class_weights: torch.Tensor
    ood: torch.Tensor
    surface_distance: torch.Tensor
    user_trans_cov: torch.Tensor
    user_rot_cov: torch.Tensor
    fallback: torch.Tensor = field(default_factory=lambda: torch.zeros(0, dtype=torch.bool))
    mixture: FactorizedTwistMixture | None = None
    shown_grasps: torch.Tensor | None = None
    """``(B, M)`` bool, the grasp candidates the prior was shown (``goal_belief_margin``; None
    without grasp candidates in the observation)."""
    grasp_candidates: torch.Tensor | None = None
    """``(B,)`` the number of grasp candidates in the observation (None without any)."""

    @property
    def mode(self) -> str:
        """The mode of a single (unbatched or B = 1) step."""
        if len(self.modes) != 1:
            raise ValueError(f"batched step with {len(self.modes)} elements: use .modes")
        return self.modes[0]

    @cached_property
    def _entropy_bounds(self) -> tuple[torch.Tensor, ...]:
        if self.mixture is None:
            nan = torch.full((len(self.modes),), math.nan, dtype=torch.float64)
            return nan, nan.clone(), nan.clone(), nan.clone()
        return (*mixture_entropy.translation_entropy_bounds(self.mixture),
                *mixture_entropy.rotation_entropy_bounds(self.mixture))

    @property
    def trans_entropy_lower(self) -> torch.Tensor:
        return self._entropy_bounds[0]

    @property
    def trans_entropy_upper(self) -> torch.Tensor:
        return self._entropy_bounds[1]

    @property
    def rot_entropy_lower(self) -> torch.Tensor:
        return self._entropy_bounds[2]

    @property
    def rot_entropy_upper(self) -> torch.Tensor:
        return self._entropy_bounds[3]
