"""Outcome of one interactive grasp trial in ``GraspClutter-v1`` (the user-study protocol).

A trial ends, after each control step, with the first of:

* ``success``: the target object is at least ``lift_height`` (5 cm) above its start height,
  with the gripper closed, for ``hold_steps`` consecutive steps (lifted and held);
* ``unmatched``: another object is lifted that way (the wrong object was grasped);
* ``collision``: an unrecoverable contact: a robot link pushes against the table or a
  non-target object with more than ``contact_force`` N (touching the target is part of grasping);
* ``timeout``: ``timeout_s`` of simulated time (90 s) pass.

Light touches (any robot contact above the env's ``collision_force_threshold``) are counted as
``contacts`` (steps with contact) but do not end the trial.
"""

from __future__ import annotations

from dataclasses import dataclass
from typing import Any

import torch

from rtv3_maniskill.features import DT
from rtv3_maniskill.teleop.recorder import OUTCOMES


@dataclass
class TrialConfig:
    """Protocol settings (m, s, N, control steps)."""

    lift_height: float = 0.05
    hold_steps: int = 10
    timeout_s: float = 90.0
    contact_force: float = 5.0

    def __post_init__(self) -> None:
        if not (self.lift_height > 0 and self.timeout_s > 0 and self.contact_force > 0 and self.hold_steps >= 1):
            raise ValueError(f"invalid trial settings {self}")

    @property
    def max_steps(self) -> int:
        """Control steps before the timeout."""
        return max(1, round(self.timeout_s / DT))


class GraspTrialMonitor:
    """Watches one ``GraspClutterEnv`` (unwrapped, one sub-scene) and decides the trial outcome."""

    def __init__(self, base_env: Any, config: TrialConfig | None = None) -> None:
        self.base = base_env
        self.config = config or TrialConfig()
        self.reset()

    def reset(self) -> None:
        """Call after ``env.reset``: records the objects' start heights and the target object."""
        base = self.base
        self.objects = list(base.objects[0])
        self.target_object = int(base.grasp_sets[0].object_ids[int(base.target_grasp_index[0])])
        self.start_z = torch.stack([a.pose.p[0, 2] for a in self.objects]).double().cpu()
        self._links = [link for link in base.agent.robot.get_links() if link.name != "panda_link0"]
        self.steps = 0
        self.contacts = 0
        self.max_other_force = 0.0
        self._held = torch.zeros(len(self.objects), dtype=torch.long)
        self.outcome: str | None = None

    def heights(self) -> torch.Tensor:
        """``(num_objects,)`` float64 height of each object above its start (m)."""
        return torch.stack([a.pose.p[0, 2] for a in self.objects]).double().cpu() - self.start_z

    def other_contact_force(self) -> float:
        """Largest contact force (N) on a robot link from anything but the target object."""
        names = [link.name for link in self._links]
        net = self.base.agent.robot.get_net_contact_forces(names)[0].double().cpu()  # (L, 3)
        target = self.objects[self.target_object]
        scene = self.base.scene
        pair = torch.stack([scene.get_pairwise_contact_forces(link, target)[0] for link in self._links]).double().cpu()
        return float((net - pair).norm(dim=-1).max())

    def update(self, info: dict, gripper_closed: bool) -> str | None:
        """After a step: ``info`` of the env step; returns the outcome once the trial ends, else None."""
        if self.outcome is not None:
            return self.outcome
        cfg = self.config
        self.steps += 1
        self.contacts += int(bool(info["collision"][0]))
        force = self.other_contact_force()
        self.max_other_force = max(self.max_other_force, force)
        lifted = self.heights() >= cfg.lift_height
        held = lifted & torch.tensor(bool(gripper_closed))
        self._held = torch.where(held, self._held + 1, torch.zeros_like(self._held))
        if int(self._held[self.target_object]) >= cfg.hold_steps:
            self.outcome = "success"
        elif bool((self._held >= cfg.hold_steps).any()):
            self.outcome = "unmatched"
        elif force > cfg.contact_force:
            self.outcome = "collision"
        elif self.steps >= cfg.max_steps:
            self.outcome = "timeout"
        return self.outcome


__all__ = ["OUTCOMES", "GraspTrialMonitor", "TrialConfig"]
