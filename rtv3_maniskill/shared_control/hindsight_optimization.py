"""Hindsight Optimization (HO) baseline: Javdani et al. 2018, "Shared autonomy via hindsight optimization".

Written from the published method with the RT-V3 paper's constants for its HO baseline
(docs/PAPER_DETAILS.md, "Hindsight Optimization"): one goal per grasp candidate and a
translation-only cost, so the rotation of the output is the user's own.

* per goal a Huber cost-to-go on the translation distance ``d`` (m):
  ``V(d) = 0.5 (m/delta) d^2 + c d`` for ``d <= delta``, else ``(m + c) d - m delta / 2``,
  with ``m = 1.5, delta = 0.10, c = 0.1``;
* ``Q(g, u) = action_apply_time * cost(d_now) + V(d after applying u for action_apply_time)``
  where ``cost(d) = dV/dd`` is the cost rate of moving at unit speed (apply time 0.1 s);
* belief: ``log p(g) -= Q_g - V_g`` every step, normalised, one goal capped at
  ``max_goal_probability`` (0.99) with the excess spread evenly over the others;
* per goal assistance ``a_g = -grad Q``: the translation gradient divided by 40 and scaled
  down linearly within 2 cm of the goal;
* blend ``u = sum_g p(g) a_g + u_user``.

Several target poses may belong to one goal (``target_groups``); a goal uses its target
with the smallest ``V``.

Frames: goals and EE pose are world ``(4, 4)``; twists are EE body frame ``[v, w]``.
"""

from __future__ import annotations

import copy
import math
from collections.abc import Sequence
from dataclasses import dataclass, field
from typing import Any

import torch

from rtv3_maniskill import features
from rtv3_maniskill.se3 import se3_exp
from rtv3_maniskill.shared_control.twist_utils import (
    as_poses,
    check_speed_limits,
    clamp_twist_speed,
    pregrasp_goals,
    step_inputs,
    tcp_poses,
)


@dataclass(frozen=True)
class HuberCost:
    """Huber cost-to-go ``V(d)`` with linear multiplier ``m``, switch ``delta`` (m) and constant ``c``."""

    linear_multiplier: float
    delta: float
    constant: float

    def value(self, d: torch.Tensor) -> torch.Tensor:
        """``V(d)``."""
        m, delta, c = self.linear_multiplier, self.delta, self.constant
        quad = 0.5 * (m / delta) * d * d + c * d
        lin = (m + c) * d - 0.5 * m * delta
        return torch.where(d <= delta, quad, lin)

    def rate(self, d: torch.Tensor) -> torch.Tensor:
        """``dV/dd``: cost per unit distance."""
        m, delta, c = self.linear_multiplier, self.delta, self.constant
        return torch.where(d <= delta, (m / delta) * d + c, torch.full_like(d, m + c))


@dataclass(frozen=True)
class HOConstants:
    """The constants of HO (defaults: the RT-V3 paper's baseline). Units: m, s."""

    translation: HuberCost = field(default_factory=lambda: HuberCost(1.5, 0.10, 0.1))
    """Cost-to-go on the translation distance to a target."""
    action_apply_time: float = 0.1
    """Time (s) a command is applied for in ``Q``."""
    translation_gradient_divisor: float = 40.0
    """The assistance is ``-grad Q`` divided by this."""
    translation_scaling_distance: float = 0.02
    """Within this distance (m) of the target the assistance is scaled down linearly."""
    max_goal_probability: float = 0.99
    """Cap on one goal's probability."""


class HindsightGoals:
    """The goals of one HO episode, the belief over them and their assistance (one robot, float64).

    Args:
        goals: ``(N, 4, 4)`` target poses (world), N >= 1.
        constants: :class:`HOConstants`.
        target_groups: optional ``(N,)`` goal id of every target (targets with the same id form
            one goal, e.g. a pre-grasp and its pi-about-z twin). Default: every target is a goal.
    """

    def __init__(self, goals: Any, constants: HOConstants | None = None,
                 target_groups: Sequence[int] | None = None) -> None:
        self.targets = as_poses(goals, "goals")
        n = self.targets.shape[0]
        if target_groups is None:
            group_ids = torch.arange(n)
        else:
            group_ids = torch.as_tensor(list(target_groups), dtype=torch.long)
            if group_ids.shape != (n,):
                raise ValueError(f"target_groups must have one id per goal pose ({n}), "
                                 f"got shape {tuple(group_ids.shape)}")
        unique, self._group_index = torch.unique(group_ids, return_inverse=True)
        self.goal_ids = unique
        """``(G,)`` goal ids in belief order."""
        self.constants = constants or HOConstants()
        self.reset()

    @property
    def num_goals(self) -> int:
        return int(self.goal_ids.shape[0])

    @property
    def belief(self) -> torch.Tensor:
        """``(G,)`` goal probabilities."""
        return self._log_belief.exp()

    def reset(self) -> None:
        """Uniform belief."""
        g = self.num_goals
        self._log_belief = torch.full((g,), -math.log(g), dtype=torch.float64)
        self.last_assistance = torch.zeros(6, dtype=torch.float64)
        """``(6,)`` the blended assistance ``sum_g p(g) a_g`` of the last step."""

    # ------------------------------------------------------------------ costs

    def _distances(self, pose: torch.Tensor) -> torch.Tensor:
        """Translation distance (m) of every target ``(N,)`` from EE pose ``(4, 4)``."""
        return (self.targets[:, :3, 3] - pose[:3, 3]).norm(dim=-1)

    def target_values(self, pose: torch.Tensor) -> torch.Tensor:
        """``V`` of every target ``(N,)`` at EE pose ``(4, 4)``."""
        return self.constants.translation.value(self._distances(pose))

    def _target_costs(self, pose: torch.Tensor) -> torch.Tensor:
        """One-step cost ``action_apply_time * cost rate`` of every target ``(N,)``."""
        k = self.constants
        return k.action_apply_time * k.translation.rate(self._distances(pose))

    def _best_targets(self, values: torch.Tensor) -> torch.Tensor:
        """``(G,)`` index of the smallest-V target of every goal."""
        best = torch.empty(self.num_goals, dtype=torch.long)
        for g in range(self.num_goals):
            idx = torch.nonzero(self._group_index == g).flatten()
            best[g] = idx[values[idx].argmin()]
        return best

    # ------------------------------------------------------------------ belief

    def _update_belief(self, q_minus_v: torch.Tensor) -> None:
        log_b = self._log_belief - q_minus_v
        log_b = log_b - torch.logsumexp(log_b, 0)
        g = self.num_goals
        cap = self.constants.max_goal_probability
        if g > 1:
            probs = log_b.exp()
            top = int(probs.argmax())
            if probs[top] > cap:
                excess = probs[top] - cap
                others = torch.arange(g) != top
                probs[others] = probs[others] + excess / (g - 1)
                probs[top] = cap
                log_b = probs.clamp_min(1e-300).log()
        self._log_belief = log_b

    # ------------------------------------------------------------------ assistance

    def _assistance(self, pose: torch.Tensor, pose_after: torch.Tensor, target: torch.Tensor) -> torch.Tensor:
        """``-grad Q`` for one target, as a body twist of the current pose ``(6,)`` (no rotation)."""
        k = self.constants
        out = torch.zeros(6, dtype=torch.float64)
        diff = pose_after[:3, 3] - target[:3, 3]
        dist = diff.norm()
        if dist > 1e-9:
            grad = k.translation.rate(dist) * diff / dist / k.translation_gradient_divisor
            if dist < k.translation_scaling_distance:
                grad = grad * dist / k.translation_scaling_distance
            out[:3] = pose[:3, :3].T @ (-grad)
        return out

    def step(self, pose: torch.Tensor, user: torch.Tensor) -> torch.Tensor:
        """Update the belief with the user command; return the assistance ``sum_g p(g) a_g (6,)``.

        Args:
            pose: ``(4, 4)`` float64 current TCP pose, world.
            user: ``(6,)`` float64 user body twist ``[v, w]``.
        """
        k = self.constants
        pose_after = pose @ se3_exp(user * k.action_apply_time)
        values_now = self.target_values(pose)
        best = self._best_targets(values_now)
        q = self._target_costs(pose)[best] + self.target_values(pose_after)[best]
        self._update_belief(q - values_now[best])
        belief = self.belief
        assistance = torch.zeros(6, dtype=torch.float64)
        for g in range(self.num_goals):
            assistance = assistance + belief[g] * self._assistance(pose, pose_after, self.targets[best[g]])
        self.last_assistance = assistance
        return assistance


class HindsightOptimization:
    """Hindsight Optimization shared autonomy (paper baseline "HO").

    The goals are the pre-grasps of the observation's valid grasp candidates, each with its
    pi-about-z twin as a second target of the same goal, read at the first step after
    :meth:`reset`; or fixed world ``goals`` given here.

    Args:
        max_linear_speed, max_angular_speed: norm limits (m/s, rad/s) of the output; None = none.
        goals: optional ``(N, 4, 4)`` fixed target poses (world) instead of the grasps.
        target_groups: optional ``(N,)`` goal id of each fixed target.
    """

    name = "ho"

    def __init__(self, max_linear_speed: float | None = 0.3, max_angular_speed: float | None = 1.2,
                 goals: Any = None, target_groups: Sequence[int] | None = None) -> None:
        check_speed_limits(max_linear_speed, max_angular_speed)
        self.constants = HOConstants()
        self.max_linear_speed = max_linear_speed
        self.max_angular_speed = max_angular_speed
        self._fixed = None if goals is None else HindsightGoals(goals, self.constants, target_groups)
        """The fixed goals (checked here), copied for every batch element at the first step."""
        self.episodes: list[HindsightGoals] = []
        """One :class:`HindsightGoals` per batch element, made at the first step after reset."""

    def reset(self) -> None:
        """Forget the goals and their belief (a new episode)."""
        self.episodes = []

    def _start(self, observation: dict[str, Any], b: int) -> None:
        if self._fixed is not None:
            self.episodes = [copy.deepcopy(self._fixed) for _ in range(b)]
            return
        for key in (features.GRASPS, features.GRASPS_MASK):
            if key not in observation:
                raise ValueError(f"observation lacks {key!r}: HO takes its goals from the grasp candidates")
        grasps = features.unflatten(features.GRASPS, torch.as_tensor(observation[features.GRASPS]))
        mask = torch.as_tensor(observation[features.GRASPS_MASK])
        self.episodes = []
        for i in range(b):
            goals, groups = pregrasp_goals(grasps[i], mask[i])
            self.episodes.append(HindsightGoals(goals, self.constants, groups.tolist()))

    def step(self, observation: dict[str, Any], user_twist: Any) -> torch.Tensor:
        """Update each goal belief with the user command; return ``sum_g p(g) a_g + u_user``
        (norm-clipped) ``(B, 6)`` float32.

        Args:
            observation: feature dict with ``observation.state (B, 27)`` and, unless fixed goals
                were given, ``observation.grasps (B, M, 9)`` + ``observation.grasps_mask (B, M)``.
            user_twist: ``(B, 6)`` user body twist, or None (no input).
        """
        state, user = step_inputs(observation, user_twist)
        b = state.shape[0]
        if not self.episodes:
            self._start(observation, b)
        elif len(self.episodes) != b:
            raise ValueError(f"batch size changed from {len(self.episodes)} to {b} without reset()")
        poses = tcp_poses(state)
        user64 = user.double()
        assistance = torch.stack([episode.step(poses[i], user64[i]) for i, episode in enumerate(self.episodes)])
        out = clamp_twist_speed(assistance + user64, self.max_linear_speed, self.max_angular_speed)
        return out.float()

    def describe(self, index: int = 0) -> dict[str, Any]:
        """The last step of batch element ``index``: goal ids, belief, most likely goal, assistance."""
        if not self.episodes:
            return {"mode": "shared"}
        episode = self.episodes[index]
        belief = episode.belief
        return {
            "mode": "shared",
            "belief": belief.numpy().copy(),
            "goal_ids": episode.goal_ids.numpy().copy(),
            "most_likely_goal": int(episode.goal_ids[int(belief.argmax())]),
            "assistance": episode.last_assistance.numpy().copy(),
        }
