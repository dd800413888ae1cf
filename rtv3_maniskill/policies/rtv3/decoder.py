"""Trajectory decoder (paper, Decoding Future Trajectory).

A GRU cell carries the latent dynamics ``h_{t+1} = GRU([z, W h0, a_{t-1}], h_t)`` with
``h_init = Linear([z, h0])``. From each state:

* factorized (paper): ``p(v_t | h_t, z) = N(mu, R diag(sigma^2) R^T)`` (Eq. velocitygmm) and
  ``p(w_t | h_t, z, v_t)`` (Eq. rotgmm), the same parametrisation conditioned on ``v_t``;
* joint ("6D pred" ablation): one 6-D Gaussian ``p([v_t, w_t] | h_t, z)``.

Everything here is in network units (translational velocity multiplied by the translation scale).
``a_{-1}`` is the current EE body twist.
"""

from __future__ import annotations

from dataclasses import dataclass

import torch
from torch import nn

from rtv3_maniskill.policies.rtv3.gaussians import AxisGaussian, JointGaussian

ROTATION_CONDITIONING_MODES = ("demonstrated", "sampled")
"""What the rotation head is evaluated at in training (``RTV3Config.rotation_conditioning``)."""


def _mlp(in_dim: int, hidden: int, out_dim: int) -> nn.Sequential:
    return nn.Sequential(nn.Linear(in_dim, hidden), nn.ReLU(), nn.Linear(hidden, out_dim))


@dataclass
class DecoderStart:
    """Decoder inputs that do not change over the horizon: ``(R, ...)`` rows (R = batch x classes)."""

    state: torch.Tensor  # (1, R, hidden) GRU state h_init
    static_input: torch.Tensor  # (R, K + context) [z, W h0]
    z: torch.Tensor  # (R, K) one-hot


class TrajectoryDecoder(nn.Module):
    """GRU decoder with Gaussian heads; see module docstring."""

    def __init__(self, context_dim: int, num_classes: int, hidden_dim: int, context_proj_dim: int,
                 head_hidden_dim: int, factorized_rotation: bool, log_sigma_min: float, log_sigma_max: float):
        super().__init__()
        self.factorized_rotation = factorized_rotation
        self.log_sigma_range = (log_sigma_min, log_sigma_max)
        self.initial_state = nn.Linear(num_classes + context_dim, hidden_dim)
        self.context_proj = nn.Linear(context_dim, context_proj_dim)
        self.gru = nn.GRU(num_classes + context_proj_dim + 6, hidden_dim, batch_first=True)
        if factorized_rotation:
            self.translation_head = _mlp(hidden_dim + num_classes, head_hidden_dim, 9)
            self.rotation_head = _mlp(hidden_dim + num_classes + 3, head_hidden_dim, 9)
        else:
            self.joint_head = _mlp(hidden_dim + num_classes, head_hidden_dim, JointGaussian.RAW_DIM)

    # ----------------------------------------------------------------------------- heads

    def translation(self, h: torch.Tensor, z: torch.Tensor) -> AxisGaussian:
        """Eq. velocitygmm: ``(mu_t^z, Sigma_t^z) = MLP(h_t, z)``."""
        return AxisGaussian.from_raw(self.translation_head(torch.cat([h, z], -1)), *self.log_sigma_range)

    def rotation(self, h: torch.Tensor, z: torch.Tensor, v: torch.Tensor) -> AxisGaussian:
        """Eq. rotgmm: ``(omega_t^z, Gamma_t^z) = MLP(h_t, z, v_t)``."""
        return AxisGaussian.from_raw(self.rotation_head(torch.cat([h, z, v], -1)), *self.log_sigma_range)

    def joint(self, h: torch.Tensor, z: torch.Tensor) -> JointGaussian:
        """"6D pred": one Gaussian over ``[v_t, w_t]``."""
        return JointGaussian.from_raw(self.joint_head(torch.cat([h, z], -1)), *self.log_sigma_range)

    # ----------------------------------------------------------------------------- unrolling

    def start(self, h0: torch.Tensor, z: torch.Tensor) -> DecoderStart:
        """``h0 (R, D)``, one-hot ``z (R, K)`` -> initial GRU state and per-step static input."""
        state = self.initial_state(torch.cat([z, h0], -1))[None]
        return DecoderStart(state, torch.cat([z, self.context_proj(h0)], -1), z)

    def _state_log_likelihood(self, h: torch.Tensor, z: torch.Tensor, actions: torch.Tensor, clamp: float,
                              rotation_conditioning: str) -> tuple[torch.Tensor, torch.Tensor]:
        """``log p(a | h, z)`` for GRU states ``h (..., hidden)`` and true actions ``(..., 6)``, each 3-D
        factor clamped at ``clamp``, and :meth:`mode_action` of the same state, detached (no autograd
        graph), from the heads' one evaluation. The rotation factor ``p(w | h, z, v)`` is evaluated at
        the true v (``rotation_conditioning="demonstrated"``) or at a detached draw ``v ~ p(v | h, z)``
        (``"sampled"``)."""
        if self.factorized_rotation:
            v, w = actions[..., :3], actions[..., 3:]
            head = self.translation(h, z)
            v_cond = head.sample().detach() if rotation_conditioning == "sampled" else v
            ll = head.log_prob(v).clamp(max=clamp) + self.rotation(h, z, v_cond).log_prob(w).clamp(max=clamp)
        else:
            head = self.joint(h, z)
            ll = head.log_prob(actions).clamp(max=2 * clamp)
        with torch.no_grad():
            return ll, self.mode_action(h, z, head).detach()

    def log_likelihood(self, start: DecoderStart, prev_action: torch.Tensor, actions: torch.Tensor,
                       clamp: float, rotation_conditioning: str = "demonstrated") -> torch.Tensor:
        """Per-step ``log p(a_t | h_t, z)``, each 3-D factor clamped at ``clamp``.

        The GRU runs free, as at inference: it reads its own most likely action (detached), not the
        true a_{t-1}, so the horizon must be predicted from ``h0`` (teacher-forced, the next twist is
        predictable from the last one alone, and little of the loss rewards reading the goal).

        Args:
            prev_action: ``(R, 6)`` a_{-1}. actions: ``(R, H, 6)`` true a_0..a_{H-1} (network units).
            rotation_conditioning: one of :data:`ROTATION_CONDITIONING_MODES` (see :meth:`_state_log_likelihood`).
        Returns:
            ``(R, H)`` log-likelihoods.
        """
        state, action, out = start.state, prev_action, []
        for t in range(actions.shape[1]):
            state = self.step(start, action, state)
            ll, action = self._state_log_likelihood(state[0], start.z, actions[:, t], clamp, rotation_conditioning)
            out.append(ll)
        return torch.stack(out, 1)

    def step(self, start: DecoderStart, prev_action: torch.Tensor, state: torch.Tensor) -> torch.Tensor:
        """One GRU step: ``(R, 6)`` a_{t-1}, ``(1, R, hidden)`` h_{t-1} -> ``(1, R, hidden)`` h_t."""
        _, state = self.gru(torch.cat([start.static_input, prev_action], -1)[:, None], state)
        return state

    def mode_action(self, h: torch.Tensor, z: torch.Tensor, head: AxisGaussian | JointGaussian | None = None
                    ) -> torch.Tensor:
        """Most likely action given the state: ``v = mu``, then ``w = omega(v)`` -> ``(R, 6)``. ``head``: the
        state's translation (factorized) or joint Gaussian where already evaluated, else computed here."""
        if self.factorized_rotation:
            v = (head if head is not None else self.translation(h, z)).mean
            return torch.cat([v, self.rotation(h, z, v).mean], -1)
        return (head if head is not None else self.joint(h, z)).mean

    def rollout_mode(self, start: DecoderStart, prev_action: torch.Tensor, steps: int) -> torch.Tensor:
        """Most-likely rollout: the mode of each Gaussian fed back as a_{t-1}: ``(R, steps, 6)``."""
        state, action, out = start.state, prev_action, []
        for _ in range(steps):
            state = self.step(start, action, state)
            action = self.mode_action(state[0], start.z)
            out.append(action)
        return torch.stack(out, 1)
