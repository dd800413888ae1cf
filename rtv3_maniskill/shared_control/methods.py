"""The assistance methods by name: how each is built, what it needs, and what it is told before a trial.

:data:`METHODS` is the one list of the method names (``rtv3 benchmark-shared --methods``, ``rtv3
demo``, ``rtv3 teleop``, DAgger drivers): Direct teleoperation, Hindsight Optimization, RT-V3, the
diffusion copilot (:mod:`~rtv3_maniskill.shared_control.copilot`), and
RT-V3's controller around priors that know the scene, the ceilings of what a learned prior can give
the fusion (:mod:`~rtv3_maniskill.shared_control.oracle_prior`). Each entry, a :class:`MethodSpec`,
says whether the method needs the learned policy, whether it runs the RT-V3 fusion (so the fusion's
settings matter to its results), whether it needs the scene's motion planner, and what it is told of
each benchmark trial (:class:`Trial`) before the trial starts.

The planning oracle's prior (``oracle_plan``) follows the motion planner's path; it lives with the
benchmarks (``rtv3_maniskill.benchmarks.plan_oracle.PlanOraclePrior``), which hand its class to
:func:`make_method` as ``plan_prior``.
"""

from __future__ import annotations

import dataclasses
from collections.abc import Callable
from dataclasses import dataclass
from typing import Any

import torch

from rtv3_maniskill.shared_control.assistance import AssistanceMethod
from rtv3_maniskill.shared_control.config import SharedControlConfig
from rtv3_maniskill.shared_control.copilot import CopilotSettings, DiffusionCopilot
from rtv3_maniskill.shared_control.direct import DirectTeleoperation
from rtv3_maniskill.shared_control.hindsight_optimization import HindsightOptimization
from rtv3_maniskill.shared_control.oracle_prior import OraclePrior, TargetShownPrior
from rtv3_maniskill.shared_control.shared_controller import SharedController


@dataclass(frozen=True)
class Trial:
    """What a benchmark trial tells a method before it starts (:attr:`MethodSpec.prepare`).

    Attributes:
        target: index of the trial's target among the scene's grasp candidates.
        pregrasps: ``(M, 4, 4)`` float64 pre-grasp poses (world) of every grasp candidate of the scene.
        goals: indices of the candidates that are goals of the scene (the target among them).
        grasp_pose: ``(4, 4)`` the target's grasp pose (world).
        planner: the scene's motion planner (a ``PandaPlanner`` of the loaded layout) when a method
            needs one (:attr:`MethodSpec.needs_planner`), else None.
    """

    target: int
    pregrasps: torch.Tensor
    goals: tuple[int, ...]
    grasp_pose: Any
    planner: Any = None


@dataclass(frozen=True)
class MethodSpec:
    """One assistance method of :data:`METHODS`.

    Attributes:
        name: the method's name (lower case, ``_``-separated; ``-`` is accepted for ``_`` on input).
        label: its name in tables and plots (``summary.md``).
        description: one line for the command-line help.
        build: ``build(max_linear_speed, max_angular_speed, **context)`` returns the method, with the
            env controller's speed limits (m/s, rad/s); ``context``: ``policy``, ``config`` (the RT-V3
            controller's :class:`SharedControlConfig`), ``plan_prior``, ``copilot`` (:class:`CopilotSettings`).
        needs_policy: the method needs the learned RT-V3 policy.
        uses_fusion: the method runs RT-V3's fusion and gate (:class:`SharedController`), so its results
            depend on the controller's settings.
        needs_planner: :attr:`Trial.planner` must be set for it.
        prepare: ``prepare(method, trial)`` tells the method the coming trial's goals (None: nothing to tell).
        ceiling: the benchmark's summary gives each method's share of this method's gain over Direct.
        default: among the methods ``rtv3 benchmark-shared`` runs by default.
        aliases: other names accepted for it.
    """

    name: str
    label: str
    description: str
    build: Callable[..., AssistanceMethod]
    needs_policy: bool = False
    uses_fusion: bool = False
    needs_planner: bool = False
    prepare: Callable[[AssistanceMethod, Trial], None] | None = None
    ceiling: bool = False
    default: bool = False
    aliases: tuple[str, ...] = ()


def _fusion_config(config: SharedControlConfig | None, lin: float, ang: float) -> SharedControlConfig:
    """``config`` (default: the tuned fusion) with the env controller's speed limits."""
    return dataclasses.replace(config or SharedControlConfig(), max_linear_speed=lin, max_angular_speed=ang)


def _direct(lin: float, ang: float, **_: Any) -> AssistanceMethod:
    return DirectTeleoperation(lin, ang)


def _ho(lin: float, ang: float, **_: Any) -> AssistanceMethod:
    return HindsightOptimization(lin, ang)


def _rtv3(lin: float, ang: float, policy: Any = None, config: SharedControlConfig | None = None,
          **_: Any) -> AssistanceMethod:
    return SharedController(policy, _fusion_config(config, lin, ang))


def _copilot(lin: float, ang: float, copilot: CopilotSettings | None = None, **_: Any) -> AssistanceMethod:
    settings = copilot or CopilotSettings()
    return DiffusionCopilot.from_pretrained(settings.path, gamma=settings.gamma, reverse_steps=settings.reverse_steps,
                                            max_linear_speed=lin, max_angular_speed=ang)


def _rtv3_goal(lin: float, ang: float, policy: Any = None, config: SharedControlConfig | None = None,
               **_: Any) -> AssistanceMethod:
    # The target alone: no belief over the candidates to build.
    return SharedController(TargetShownPrior(policy),
                            dataclasses.replace(_fusion_config(config, lin, ang), goal_belief_margin=None))


def _oracle(lin: float, ang: float, config: SharedControlConfig | None = None, **_: Any) -> AssistanceMethod:
    return SharedController(OraclePrior(max_linear_speed=lin, max_angular_speed=ang), _fusion_config(config, lin, ang))


def _oracle_plan(lin: float, ang: float, config: SharedControlConfig | None = None,
                 plan_prior: Callable[..., Any] | None = None, **_: Any) -> AssistanceMethod:
    if plan_prior is None:
        raise ValueError("method 'oracle_plan' needs its prior: pass plan_prior="
                         "rtv3_maniskill.benchmarks.plan_oracle.PlanOraclePrior")
    return SharedController(plan_prior(max_linear_speed=lin, max_angular_speed=ang), _fusion_config(config, lin, ang))


def _tell_every_goal(method: Any, trial: Trial) -> None:
    method.policy.set_goals(trial.pregrasps[list(trial.goals)])


def _tell_the_target_goal(method: Any, trial: Trial) -> None:
    method.policy.set_goals(trial.pregrasps[[trial.target]])


def _tell_the_target(method: Any, trial: Trial) -> None:
    method.policy.set_target(trial.target)


def _tell_the_trial(method: Any, trial: Trial) -> None:
    method.policy.set_trial(trial)


METHODS: dict[str, MethodSpec] = {spec.name: spec for spec in (
    MethodSpec("direct", "Direct", "the user's twist as it is", _direct, default=True),
    MethodSpec("ho", "HO", "Hindsight Optimization over the grasp candidates", _ho, default=True),
    MethodSpec("rtv3", "RT-V3", "the learned prior fused with the user's twist", _rtv3, needs_policy=True,
               uses_fusion=True, default=True, aliases=("rt_v3",)),
    MethodSpec("copilot", "Copilot", "a diffusion policy that noises the user's twist part of the way and "
               "denoises it (partial diffusion)", _copilot, aliases=("diffusion_copilot",)),
    MethodSpec("oracle", "Oracle", "RT-V3's fusion with a prior that knows every goal of the scene", _oracle,
               uses_fusion=True, prepare=_tell_every_goal, ceiling=True),
    MethodSpec("oracle_goal", "Oracle (goal)", "RT-V3's fusion with a prior that knows the true goal", _oracle,
               uses_fusion=True, prepare=_tell_the_target_goal),
    MethodSpec("oracle_plan", "Oracle (plan)", "RT-V3's fusion with a prior that follows the motion planner's "
               "path to the true goal", _oracle_plan, uses_fusion=True, needs_planner=True, prepare=_tell_the_trial,
               ceiling=True),
    MethodSpec("rtv3_goal", "RT-V3 (goal)", "RT-V3 with its learned prior shown only the true target grasp",
               _rtv3_goal, needs_policy=True, uses_fusion=True, prepare=_tell_the_target),
)}
"""Every assistance method, by name, in the order tables list them."""

METHOD_NAMES = tuple(METHODS)
DEFAULT_METHODS = tuple(name for name, spec in METHODS.items() if spec.default)
CEILINGS = tuple(name for name, spec in METHODS.items() if spec.ceiling)
"""The methods whose gain over Direct a benchmark summary shares out: the straight-line and the planning oracle."""
UNINFORMED_METHODS = tuple(name for name, spec in METHODS.items() if spec.prepare is None)
"""The methods told nothing of the trial's goal: the ones a person at the controls can use (``rtv3 teleop``)."""


def method_spec(name: str) -> MethodSpec:
    """The :class:`MethodSpec` of ``name`` (case, ``-`` / ``_`` and aliases are interchangeable).

    Raises:
        ValueError: unknown name (the message lists the known ones).
    """
    key = str(name).strip().lower().replace("-", "_")
    for spec in METHODS.values():
        if key == spec.name or key in spec.aliases:
            return spec
    raise ValueError(f"unknown assistance method {name!r}; known methods: {', '.join(METHOD_NAMES)}")


def make_method(name: str, speed_limits: tuple[float, float], policy: Any = None,
                config: SharedControlConfig | None = None, plan_prior: Callable[..., Any] | None = None,
                copilot: CopilotSettings | None = None) -> AssistanceMethod:
    """The assistance method ``name`` (:data:`METHODS`) with the env controller's ``speed_limits`` (m/s, rad/s).

    Args:
        policy: the learned RT-V3 prior, for the methods that need it.
        config: the RT-V3 controller's settings for the methods that run its fusion (default: the tuned
            fusion); its speed limits are replaced by ``speed_limits``.
        plan_prior: the planning oracle's prior class (``benchmarks.plan_oracle.PlanOraclePrior``), built
            with ``max_linear_speed`` and ``max_angular_speed``.
        copilot: which diffusion copilot ``copilot`` runs, with which gamma (default: the shipped one).

    The methods with a :attr:`MethodSpec.prepare` are told each trial's goals by the caller.

    Raises:
        ValueError: unknown name, or a method that needs a policy without one.
    """
    spec = method_spec(name)
    if spec.needs_policy and policy is None:
        raise ValueError(f"method {name!r} needs a policy (load one with rtv3_maniskill.policies.rtv3.load_policy)")
    lin, ang = speed_limits
    return spec.build(lin, ang, policy=policy, config=config, plan_prior=plan_prior, copilot=copilot)


__all__ = ["CEILINGS", "DEFAULT_METHODS", "METHODS", "METHOD_NAMES", "MethodSpec", "Trial", "make_method",
           "method_spec"]
