"""Settings of one DAgger round (:mod:`rtv3_maniskill.datagen.dagger`): :class:`DaggerConfig` and its drivers.

Kept apart from the collector, which loads the simulator: ``rtv3 dagger`` builds its options from
these defaults whenever the command line is parsed.
"""

from __future__ import annotations

from dataclasses import dataclass
from pathlib import Path
from typing import Any

from rtv3_maniskill.robot.planner_config import DEFAULT_CLEARANCE, with_clearance

DEFAULT_DRIVERS = ("prior", "rtv3:noisy", "direct:noisy", "rtv3:laggy", "rtv3:mode_switching",
                   "rtv3:single_dof", "direct:single_dof", "rtv3:low_dof")
"""The prior alone, and simulated users through RT-V3 (what the shared-control prior must read) and Direct."""
FAILURE_WINDOW_STEPS = 20
"""A failed rollout's ``failure_relabels`` come from a window of 20 steps (1 s at 20 Hz)."""
FAILURE_WINDOWS = ("last", "drift")
"""Where that window lies: ``"last"``, the rollout's last second (where it stalled or touched something);
``"drift"``, the second from its closest approach to the pre-grasp on (where it turned away: the last second
of a rollout that ran off lies far out of reach; it is the last second again when the rollout got closest
at its end)."""


def parse_driver(spec: str) -> tuple[str, str | None]:
    """``"prior"`` -> ``("prior", None)``; ``"rtv3:noisy"`` -> ``("rtv3", "noisy")``.

    Raises:
        ValueError: unknown method or user (the message lists the known ones).
    """
    # Lazy: they load torch, and the CLI's parser imports this module.
    from rtv3_maniskill.shared_control.methods import UNINFORMED_METHODS
    from rtv3_maniskill.shared_control.simulated_users import USERS

    text = str(spec).strip().lower().replace("-", "_")
    if text == "prior":
        return "prior", None
    method, _, user = text.partition(":")
    if method not in UNINFORMED_METHODS or user not in USERS:
        raise ValueError(f"unknown DAgger driver {spec!r}: expected 'prior' or METHOD:USER with METHOD in "
                         f"{UNINFORMED_METHODS} and USER in {sorted(USERS)}")
    return method, user


@dataclass
class DaggerConfig:
    """Settings of one ``rtv3 dagger`` round.

    Attributes:
        output: dataset folder (LeRobot root, resumable).
        policy_path: the checkpoint whose closed loop is rolled out (None = the shipped one).
        scenes, seed: scene ``i`` has seed ``seed * 100000 + i`` (use a training seed block).
        drivers: rollout drivers (:func:`parse_driver`); target ``j`` of scene ``i`` gets driver
            ``(i * targets_per_scene + j) mod len(drivers)``.
        targets_per_scene: seeded subset of each scene's grasp candidates (None = all).
        relabels_per_rollout: visited states re-planned per rollout (seeded, spread over the rollout).
        failure_relabels: 0, or the number of states re-planned from a failed rollout (contact or
            timeout) instead of ``relabels_per_rollout``, all from a window of
            :data:`FAILURE_WINDOW_STEPS` steps placed by ``failure_window``: where it went wrong, the
            recovery the expert shows.
        failure_window: one of :data:`FAILURE_WINDOWS`.
        min_step: earliest rollout step that is relabelled (step 0 is the start demonstrations cover).
        max_steps: rollout length limit (the benchmarks' 150).
        plan_timeout: seconds per OMPL query.
        clearance: m the expert's free-space motion keeps from the objects
            (:func:`~rtv3_maniskill.robot.planner_config.with_clearance`).
    """

    output: Path
    policy_path: Path | None = None
    scenes: int = 50
    seed: int = 5
    drivers: tuple[str, ...] = DEFAULT_DRIVERS
    targets_per_scene: int | None = 4
    relabels_per_rollout: int = 3
    failure_relabels: int = 0
    failure_window: str = "last"
    min_step: int = 2
    max_steps: int = 150
    plan_timeout: float = 3.0
    clearance: float = DEFAULT_CLEARANCE
    scene_type: str = "mixed"
    objects: str = "procedural"
    execution: str = "capped"
    """How the rollouts' env executes twists (``rtv3_maniskill.presets.EXECUTIONS``)."""
    self_contacts: bool = True
    """Whether a robot self contact ends a rollout as a collision."""
    fusion: str = "tuned"
    """RT-V3's fusion for the ``rtv3:USER`` drivers (a ``shared_control.config.FUSION_PRESETS`` name; ``rtv3
    dagger`` passes the preset's), so that the relabelled states are the ones the benchmark's RT-V3 visits."""
    workers: int = 1

    def __post_init__(self) -> None:
        self.output = Path(self.output).expanduser().absolute()
        self.drivers = tuple(self.drivers)
        if not self.drivers:
            raise ValueError("drivers must name at least one driver")
        for spec in self.drivers:
            parse_driver(spec)
        for name in ("scenes", "relabels_per_rollout", "max_steps", "workers"):
            if getattr(self, name) < 1:
                raise ValueError(f"{name} must be >= 1, got {getattr(self, name)}")
        if self.targets_per_scene is not None and self.targets_per_scene < 1:
            raise ValueError(f"targets_per_scene must be >= 1 or None, got {self.targets_per_scene}")
        if self.failure_relabels < 0:
            raise ValueError(f"failure_relabels must be >= 0, got {self.failure_relabels}")
        if self.failure_window not in FAILURE_WINDOWS:
            raise ValueError(f"unknown failure_window {self.failure_window!r}: expected one of {FAILURE_WINDOWS}")
        with_clearance(self.clearance)  # a clear error for a bad distance
        if self.min_step < 1:
            raise ValueError(f"min_step must be >= 1, got {self.min_step}")
        # Lazy: it loads torch, and the CLI's parser imports this module. Checked here, before any
        # worker starts, by the lookup the rollouts use (its error names the known fusions).
        from rtv3_maniskill.shared_control.config import SharedControlConfig

        SharedControlConfig.preset(self.fusion)

    def settings(self, num_points: int, max_grasps: int) -> dict[str, Any]:
        """What a resumed run must share (the dataset format and the rollouts' definition)."""
        return dict(format="rtv3-grasp-clutter-v1", source="dagger", seed=self.seed, scene_type=self.scene_type,
                    objects=self.objects, num_points=num_points, max_grasps=max_grasps, context="rendered",
                    end_at="pregrasp", drivers=list(self.drivers), targets_per_scene=self.targets_per_scene,
                    relabels_per_rollout=self.relabels_per_rollout, failure_relabels=self.failure_relabels,
                    min_step=self.min_step, max_steps=self.max_steps, policy=str(self.policy_path or "shipped"),
                    # Only when set, so that rounds made before these options existed still resume.
                    **({"execution": self.execution} if self.execution != "capped" else {}),
                    **({"self_contacts": self.self_contacts} if not self.self_contacts else {}),
                    **({"fusion": self.fusion} if self.fusion != "tuned" else {}),
                    **({"clearance": self.clearance} if self.clearance != DEFAULT_CLEARANCE else {}),
                    **({"failure_window": self.failure_window} if self.failure_window != "last" else {}))


__all__ = ["DEFAULT_DRIVERS", "FAILURE_WINDOWS", "FAILURE_WINDOW_STEPS", "DaggerConfig", "parse_driver"]
