"""Discrete maneuver class ``z`` (paper, Maneuver Class Sampling; Trajectron++ CVAE recipe)."""

from __future__ import annotations

import math

import torch
from torch import nn


def sigmoid_anneal(step: int, start: float, final: float, crossover: int, divisor: float) -> float:
    """``start + (final - start) * sigmoid((step - crossover) / (crossover / divisor))``."""
    width = max(crossover / divisor, 1e-9)
    return start + (final - start) / (1.0 + math.exp(-(step - crossover) / width))


def clip_logits(logits: torch.Tensor, clip: float) -> torch.Tensor:
    """Mean-centre ``(B, K)`` logits and clip them to ``[-clip, clip]``; returns normalised log-probs."""
    centred = logits - logits.mean(-1, keepdim=True)
    return torch.log_softmax(centred.clamp(-clip, clip), -1)


class ManeuverPrior(nn.Module):
    """``p(z | h0)``: MLP (one hidden layer) on the context encoding."""

    def __init__(self, in_dim: int, hidden_dim: int, num_classes: int):
        super().__init__()
        self.net = nn.Sequential(nn.Linear(in_dim, hidden_dim), nn.ReLU(), nn.Linear(hidden_dim, num_classes))

    def forward(self, h0: torch.Tensor, clip: float) -> torch.Tensor:
        """``(B, D) -> (B, K)`` log p(z | h0)."""
        return clip_logits(self.net(h0), clip)


class ManeuverPosterior(nn.Module):
    """``q(z | h_H)``: linear map of ``[h0, h+]`` (training only)."""

    def __init__(self, in_dim: int, num_classes: int):
        super().__init__()
        self.net = nn.Linear(in_dim, num_classes)

    def forward(self, h_future: torch.Tensor, clip: float) -> torch.Tensor:
        """``(B, D) -> (B, K)`` log q(z | h_H)."""
        return clip_logits(self.net(h_future), clip)


def kl_categorical(log_q: torch.Tensor, log_p: torch.Tensor) -> torch.Tensor:
    """``KL(q || p)`` per row: ``(B, K), (B, K) -> (B,)``."""
    return (log_q.exp() * (log_q - log_p)).sum(-1)


def mutual_information(log_p: torch.Tensor) -> torch.Tensor:
    """Batch estimate of ``I(x; z)`` under p: ``H(mean_b p) - mean_b H(p)`` (Trajectron++ ``I_p``)."""
    probs = log_p.exp()
    marginal = probs.mean(0)
    entropy_marginal = -(marginal * torch.log(marginal.clamp_min(1e-12))).sum()
    entropy_rows = -(probs * log_p).sum(-1).mean()
    return entropy_marginal - entropy_rows
