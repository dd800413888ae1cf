"""Recursive belief over the prior's maneuver classes across steps (an extension of the paper's Sec. V).

The paper's posterior re-weights the classes with the current command alone:
``pi_k' ∝ pi_k p(u_t | k)``. :class:`ClassBelief` keeps the evidence of earlier commands,
``E_k <- memory E_k + log p(u_t | k)`` over the shared steps, and adds it to the prior's class
log-weights before the fusion, so that consistent commands build up a belief in one class
(``memory`` 1: exact Bayes for a class that does not change; 0: the paper).
"""

from __future__ import annotations

import dataclasses

import torch

from rtv3_maniskill.shared_control.posterior import FactorizedTwistMixture
from rtv3_maniskill.twist_mixture import TwistMixture

EVIDENCE_FLOOR = 20.0
"""Nats: the recursive belief never rules a class out by more than this."""


class ClassBelief:
    """Evidence ``(B, K)`` (nats, 0 for the best class) per maneuver class since :meth:`reset`.

    Args:
        memory: decay of the evidence per step, in [0, 1]; 0 keeps no evidence.
        floor: the evidence never falls more than this many nats behind the best class.
    """

    def __init__(self, memory: float, floor: float = EVIDENCE_FLOOR) -> None:
        if not 0.0 <= memory <= 1.0 or not floor > 0:
            raise ValueError(f"ClassBelief needs memory in [0, 1] and floor > 0, got {memory}, {floor}")
        self.memory, self.floor = float(memory), float(floor)
        self.evidence: torch.Tensor | None = None
        """``(B, K)`` float64, or None before the first step of an episode (or with memory 0)."""

    def reset(self) -> None:
        """A new episode: no evidence."""
        self.evidence = None

    def apply(self, mixture: TwistMixture) -> TwistMixture:
        """The prior's mixture with the evidence added to its class log-weights (renormalised);
        ``mixture`` itself when ``memory`` is 0."""
        if self.memory == 0.0:
            return mixture
        lw = mixture.log_weights.double()
        if self.evidence is None or self.evidence.shape != lw.shape:
            self.evidence = torch.zeros_like(lw)
        lw = lw + self.evidence
        return dataclasses.replace(mixture, log_weights=lw - torch.logsumexp(lw, -1, keepdim=True))

    def remember(self, shared: torch.Tensor, prior: FactorizedTwistMixture,
                 fused: FactorizedTwistMixture | None) -> None:
        """Decay the evidence and add this step's class log-likelihoods ``log pi_k' - log pi_k``
        where ``shared (B,)`` (the command was fused); ``prior`` and ``fused`` are the mixtures of
        this step (``fused`` None when no command was fused)."""
        if self.memory == 0.0 or self.evidence is None:
            return
        gained = torch.zeros_like(self.evidence)
        if fused is not None:
            gained = torch.where(shared[:, None], fused.log_weights - prior.log_weights, gained)
        evidence = self.memory * self.evidence + gained
        # Relative to the best class, floored: a user who changes their mind can still be followed.
        self.evidence = (evidence - evidence.max(-1, keepdim=True).values).clamp_min(-self.floor)
