"""Settings of the shared-control benchmark: :class:`BenchmarkConfig`, and what of them a run's folder records.

Every field carries its documentation as ``help`` in its metadata, and ``rtv3 benchmark-shared``
builds its options from the fields (:func:`rtv3_maniskill.cli.benchmark_shared.add_arguments`), so the
defaults and the help live here only. Metadata keys besides ``help``:

* ``flags``: the option's names (default ``--field-name``);
* ``choices``: the values the option takes;
* ``known``: a function returning the names the field takes (a registry; imported only when the help is shown);
* ``preset``: the option's default comes from ``--preset`` (``rtv3_maniskill.presets``);
* ``option=False``: no option of its own (the scene settings come from ``--preset`` and its overrides,
  the RT-V3 controller's from the fusion options).

:meth:`BenchmarkConfig.fingerprint` is what a run's ``config.json`` holds: an output folder made with
other settings is refused, so results of different settings are never mixed.
"""

from __future__ import annotations

import dataclasses
import hashlib
from collections.abc import Sequence
from dataclasses import MISSING, dataclass, field
from pathlib import Path
from typing import Any

from rtv3_maniskill.presets import GOAL_RULES
from rtv3_maniskill.records import scene_seeds
from rtv3_maniskill.robot.execution import EXECUTIONS

DEFAULT_USERS = ("noisy", "laggy", "mode_switching", "single_dof", "low_dof")
"""The simulated users a run drives with by default: every user but the ideal one."""
PROTOCOL = "authors: ready-pose start, feasible goals"
"""How trials are set up (docs/PAPER_DETAILS.md, "Authors' benchmark protocol"), recorded with the results:
every trial starts at the Panda ready pose, ends at the first robot contact (a failure), and the prior sees
the scene cloud rendered once per scene from the depth camera, as ``rtv3 generate`` stores it."""
_FIXED_SETTINGS = dict(stop_on_contact=True, obs_mode="state_dict", rendered_context=True)
"""Parts of :data:`PROTOCOL` that runs made before they were fixed recorded as settings; ``config.json``
keeps them, so those runs still resume."""
_SPEED_LIMIT_FIELDS = ("max_linear_speed", "max_angular_speed")
"""SharedControlConfig fields the benchmark takes from the env's controller, not from its settings."""


class BenchmarkError(ValueError):
    """A problem with the benchmark's settings or output folder (message meant for the user)."""


def _option(default: Any = MISSING, *, factory: Any = MISSING, help: str, **cli: Any) -> Any:
    """A :class:`BenchmarkConfig` field, documented by ``help``; ``cli``: how its option is made (module docstring)."""
    return field(default=default, default_factory=factory, metadata=dict(help=help, **cli))


def _default_methods() -> tuple[str, ...]:
    # Lazy: it loads torch, and the CLI's parser imports this module.
    from rtv3_maniskill.shared_control.methods import DEFAULT_METHODS

    return DEFAULT_METHODS


def _known_users() -> list[str]:
    # Lazy: it loads torch, and the CLI's parser imports this module.
    from rtv3_maniskill.shared_control.simulated_users import USERS

    return list(USERS)


def _known_methods() -> list[str]:
    # Lazy: it loads torch, and the CLI's parser imports this module.
    from rtv3_maniskill.shared_control.methods import METHODS

    return [f"{name} ({spec.description})" for name, spec in METHODS.items()]


def _known_fusions() -> list[str]:
    # Lazy: it loads torch, and the CLI's parser imports this module.
    from rtv3_maniskill.shared_control.config import FUSION_PRESETS

    return list(FUSION_PRESETS)


def _known_safety_filters() -> list[str]:
    # Lazy: it loads torch, and the CLI's parser imports this module.
    from rtv3_maniskill.benchmarks.episodes import SAFETY_FILTERS

    return [name for name in SAFETY_FILTERS if name is not None]


@dataclass
class BenchmarkConfig:
    """Settings of one benchmark run (``rtv3 benchmark-shared``; each field's ``help`` is its documentation)."""

    output: Path = _option(Path("outputs/benchmark_shared"),
                           help="folder for results.csv, goals.csv, summary.csv, summary.md, success_rates.png")
    policy_path: Path | None = _option(
        None, flags=("--policy.path",), preset=True,
        help="RT-V3 checkpoint folder (config.json + model.safetensors) or Hub repo id (default: the preset's; "
             "None: the shipped rtv3_maniskill/checkpoints/rtv3_grasp_clutter). Loaded only for the methods "
             "that need it")
    scenes: int = _option(50, help="clutter scenes (scene i: seed SEED*100000 + i)")
    users: Sequence[str] = _option(DEFAULT_USERS, known=_known_users, help="comma-separated simulated users")
    methods: Sequence[str] = _option(factory=_default_methods, known=_known_methods,
                                     help="comma-separated assistance methods ('-' for '_' is fine)")
    seed: int = _option(9, help="scene seed block (9, the test block, is held out from training scenes of "
                                "`rtv3 generate --seed 0..8`)")
    goals_per_scene: int | None = _option(
        None,
        help="feasible goals per scene (a seeded random subset; default: every feasible grasp; the paper ran 10-20)")
    max_steps: int = _option(150, help="control steps per trial (20 Hz)")
    scene_type: str = _option("mixed", option=False, help="GraspClutter-v1's layout (--preset, --scene-type)")
    object_source: str = _option("procedural", option=False,
                                 help="GraspClutter-v1's object_source, e.g. random_urdfs (--preset, --objects)")
    execution: str = _option("capped", option=False,
                             help="GraspClutter-v1's twist execution: capped or tracked, the authors' (--preset, "
                                  "--execution)")
    self_contacts: bool = _option(True, option=False,
                                  help="whether a robot self contact is a collision (False: the authors' rule; "
                                       "--preset, --self-contacts)")
    goals: str = _option(
        "reachable", preset=True, choices=GOAL_RULES,
        help="goal rule (default: the preset's): all (every floating-hand-feasible grasp, the authors' rule; paper) "
             "or reachable (only grasps the arm can reach without contact; easy); goals.csv holds the arm-reach "
             "check and summary.md counts both either way")
    fusion: str = _option(
        "tuned", preset=True, known=_known_fusions,
        help="RT-V3 fusion preset (default: the preset's; SharedControlConfig.preset): tuned (easy; chosen on its "
             "validation scenes: predictive gate at alpha 0.99, recursive goal belief, prior covariance x100, a "
             "command's zero axes missing away from the scene), tuned_ycb (paper; the same with the prior "
             "covariance x30, chosen on the paper preset's validation scenes), paper (the paper's reading: "
             "class-covariance gate at 0.85, no memory, x1); the options below override single settings")
    shared_control: dict[str, Any] = _option(
        factory=dict, option=False,
        help="overrides of SharedControlConfig fields for the methods that run RT-V3's fusion (e.g. "
             "{'ood_alpha': 0.95}); the speed limits always come from the env's controller")
    safety_filter: str | None = _option(
        None, known=_known_safety_filters,
        help="put the NEO collision damper in front of every method (the paper's 'w. NeoSS' rows; results are "
             "named METHOD+neoss)")

    copilot_path: Path | None = _option(
        None, help="the copilot method's diffusion policy (a pretrained_model folder of rtv3 train-copilot; "
                   "None: the shipped rtv3_maniskill/checkpoints/copilot_diffusion)")
    copilot_gamma: float | None = _option(
        None, help="the copilot's noising fraction in [0, 1] (0: the user's twist, 1: the copilot alone; None: its "
                   "default, chosen on the validation block)")
    copilot_steps: int | None = _option(
        None, help="the copilot's DDIM steps over the whole schedule (None: the checkpoint's)")

    def __post_init__(self) -> None:
        # Lazy: they load torch, and the CLI's parser imports this module.
        from rtv3_maniskill.shared_control.methods import method_spec
        from rtv3_maniskill.shared_control.simulated_users import USERS

        self.output = Path(self.output)
        self.users = tuple(str(u).strip().lower().replace("-", "_") for u in self.users)
        if not self.users or not self.methods:
            raise BenchmarkError("give at least one user and one method")
        for user in self.users:
            if user not in USERS:
                raise BenchmarkError(f"unknown simulated user {user!r}; known users: {', '.join(sorted(USERS))}")
        try:
            self.methods = tuple(method_spec(m).name for m in self.methods)
        except ValueError as err:
            raise BenchmarkError(str(err)) from None
        for name, values in (("users", self.users), ("methods", self.methods)):
            if len(set(values)) != len(values):
                raise BenchmarkError(f"{name} lists a name twice: {', '.join(values)}")
        for name, value in (("scenes", self.scenes), ("max_steps", self.max_steps),
                            ("goals_per_scene", self.goals_per_scene)):
            if value is not None and value < 1:
                raise BenchmarkError(f"{name} must be >= 1, got {value}")
        for name, value, known in (("goal rule", self.goals, GOAL_RULES), ("execution", self.execution, EXECUTIONS)):
            if value not in known:
                raise BenchmarkError(f"unknown {name} {value!r}; known: {', '.join(known)}")
        if self.safety_filter is not None and self.safety_filter not in _known_safety_filters():
            raise BenchmarkError(f"unknown safety filter {self.safety_filter!r}; known: "
                                 f"{', '.join(_known_safety_filters())}")
        if "copilot" in self.methods:
            try:
                copilot = self.copilot_settings()
            except ValueError as err:
                raise BenchmarkError(str(err)) from None
            if not (Path(copilot.path) / "model.safetensors").is_file():
                raise BenchmarkError(f"no copilot at {copilot.path} (model.safetensors): train one with "
                                     "`rtv3 train-copilot` and pass its pretrained_model folder as --copilot-path")
        self.shared_control = dict(self.shared_control)
        for key in _SPEED_LIMIT_FIELDS:
            if key in self.shared_control:
                raise BenchmarkError(f"shared_control may not set {key}: the speed limits come from the env")
        try:
            self.shared_control_config(0.3, 1.2)
        except (TypeError, ValueError) as err:
            raise BenchmarkError(f"bad shared_control settings {self.shared_control}: {err}") from None

    def copilot_settings(self):
        """The copilot method's :class:`~rtv3_maniskill.shared_control.copilot.CopilotSettings` (None: its defaults)."""
        # Lazy: it loads torch and LeRobot, and the CLI's parser imports this module.
        from rtv3_maniskill.shared_control.copilot import CopilotSettings

        given = dict(path=self.copilot_path and str(self.copilot_path), gamma=self.copilot_gamma,
                     reverse_steps=self.copilot_steps)
        return CopilotSettings(**{k: v for k, v in given.items() if v is not None})

    def shared_control_config(self, max_linear_speed: float, max_angular_speed: float):
        """The RT-V3 controller's settings: the fusion preset, these overrides and the env's speed limits."""
        # Lazy: it loads torch, and the CLI's parser imports this module.
        from rtv3_maniskill.shared_control.config import SharedControlConfig

        return SharedControlConfig.preset(self.fusion, max_linear_speed=max_linear_speed,
                                          max_angular_speed=max_angular_speed, **self.shared_control)

    def _specs(self) -> list:
        # Lazy: it loads torch, and the CLI's parser imports this module.
        from rtv3_maniskill.shared_control.methods import METHODS

        return [METHODS[m] for m in self.methods]

    @property
    def needs_policy(self) -> bool:
        """Whether a method needs the learned RT-V3 policy."""
        return any(spec.needs_policy for spec in self._specs())

    @property
    def uses_fusion(self) -> bool:
        """Whether a method runs the RT-V3 fusion (so the controller's settings matter to the results)."""
        return any(spec.uses_fusion for spec in self._specs())

    @property
    def needs_planner(self) -> bool:
        """Whether a method needs the scene's motion planner in every trial."""
        return any(spec.needs_planner for spec in self._specs())

    def scene_seeds(self) -> list[int]:
        return scene_seeds(self.seed, self.scenes)

    def fingerprint(self, policy_path: Path | None) -> dict[str, Any]:
        """Settings that change every trial's outcome (``config.json``): a resumed run must match them. The
        policy is identified by its path *and* the SHA-256 of its weights, so a checkpoint replaced in
        place is not mixed with results of the old one; the RT-V3 controller's settings (minus the speed
        limits, which come from the env) count where a method runs its fusion."""
        shared_control = None
        if self.uses_fusion:
            shared_control = dataclasses.asdict(self.shared_control_config(0.3, 1.2))
            for key in _SPEED_LIMIT_FIELDS:
                shared_control.pop(key)
        copilot = None
        if "copilot" in self.methods:
            settings = self.copilot_settings()
            copilot = dict(path=str(Path(settings.path).resolve()), gamma=settings.gamma,
                           reverse_steps=settings.reverse_steps, weights_sha256=weights_digest(Path(settings.path)))
        return dict(
            seed=self.seed, max_steps=self.max_steps, **({"copilot": copilot} if copilot else {}),
            **_FIXED_SETTINGS, scene_type=self.scene_type,
            goals_per_scene=self.goals_per_scene, protocol=PROTOCOL, safety_filter=self.safety_filter,
            policy_path=str(policy_path.resolve()) if policy_path is not None else None,
            policy_weights_sha256=weights_digest(policy_path) if policy_path is not None else None,
            shared_control=shared_control, object_source=self.object_source, goals=self.goals,
            execution=self.execution, self_contacts=self.self_contacts,
        )

    def env_kwargs(self) -> dict[str, Any]:
        """``GraspClutter-v1`` keyword arguments of these settings (scenes, objects, execution, contacts)."""
        return dict(obs_mode="state_dict", scene_type=self.scene_type, object_source=self.object_source,
                    execution=self.execution, self_contacts=self.self_contacts)


def weights_digest(policy_path: Path) -> str | None:
    """SHA-256 (hex) of ``policy_path/model.safetensors``; None when the file is missing."""
    weights = Path(policy_path) / "model.safetensors"
    if not weights.is_file():
        return None
    digest = hashlib.sha256()
    with open(weights, "rb") as f:
        for chunk in iter(lambda: f.read(1 << 20), b""):
            digest.update(chunk)
    return digest.hexdigest()
