"""Simulated shared-control benchmark (paper Sec. "Simulated Shared Control Experiments", Table II).

The authors' protocol (docs/PAPER_DETAILS.md, "Authors' benchmark protocol"): the goals are the
*feasible* grasp candidates of each scene (:mod:`rtv3_maniskill.benchmarks.goals`: collision-free
IK at the pre-grasp and a free straight 5 cm approach; the others are counted by reason in
``goals.csv`` and never run), optionally a seeded random subset of ``goals_per_scene`` per scene;
every trial starts from the Panda ready pose, and each simulated user drives towards the goal's
pre-grasp with each assistance method for up to 150 steps (7.5 s). As in the paper's planning and
shared-control tables (their SR + CR + TOR add up to 100 %), each trial has one outcome: it
ends as a *collision* at the first robot contact, as a *success* when the env's
``info["success"]`` comes first (pose distance to the pre-grasp < 0.1, shared-control
weights, either parallel-jaw twin), and as a *timeout* after the step limit. Reported per
(user, method): SR, CR, TOR, mean iterations of the successful trials, and "reached" (the
pre-grasp reached whether or not the robot touched something, which differs from SR when
``stop_on_contact=False`` lets trials go on after a contact, or when the contact and the arrival
fall on the same step).

Besides Direct, HO and RT-V3, the methods ``oracle`` and ``oracle_goal`` run the same fusion and
gate as RT-V3 with a prior that knows the scene (:class:`~rtv3_maniskill.shared_control.oracle_prior.
OraclePrior`: one class per feasible goal, or the true goal alone): the ceiling of what a learned
prior can reach under the current fusion; ``rtv3_goal`` is RT-V3 with its learned prior shown only
the true target (what reading the goal from the commands could at most give it). ``summary.md``
pairs every method with Direct on the same goals and user noise (wins, losses, exact McNemar p,
the share of the oracle's gain) and puts the paper's Table II beside.

Outputs in ``output``: ``results.csv`` (one row per trial, appended and flushed as trials
finish; a rerun skips the finished (scene, grasp, user, method) rows), ``goals.csv``,
``summary.csv``, ``summary.md`` and ``success_rates.png``; ``config.json`` guards a resumed run against
different settings. ``run_benchmark(..., workers=N)`` (``--workers``) runs the scenes in N
processes into one such folder; :func:`merge_runs` combines runs of disjoint users or methods made
separately (e.g. on other machines).

Scene ``i`` uses seed ``seed * 100000 + i`` (``rtv3 generate``'s convention; the default
seed 9 keeps the benchmark scenes apart from training scenes made with seeds 0..8). The
user's random stream depends only on (seed, scene, grasp, user), so every method faces the
same noise.
"""

from __future__ import annotations

import csv
import hashlib
import json
import math
import shutil
import time
import zlib
from collections.abc import Callable, Iterable, Sequence
from dataclasses import dataclass, field
from pathlib import Path
from typing import Any

import numpy as np

from rtv3_maniskill.features import pregrasp_poses
from rtv3_maniskill.presets import GOAL_RULES
from rtv3_maniskill.records import RecordStore, SettingsMismatch, scene_seeds, select_targets
from rtv3_maniskill.robot.execution import EXECUTIONS

RESULT_FIELDS = (
    "scene_seed", "grasp_index", "user", "method", "outcome", "success", "collision", "steps",
    "final_distance", "autonomous_steps", "user_only_steps", "user_seed", "wall_time_s", "qp_infeasible_steps",
    "contact",
)
_LATER_RESULT_FIELDS = {"qp_infeasible_steps": "0", "contact": ""}
"""Columns added to ``results.csv`` after its first version (the last ones of ``RESULT_FIELDS``, in the
order they were added), with the value a file written before them reads as."""
SUMMARY_FIELDS = ("user", "method", "trials", "SR", "CR", "TOR", "reached", "mean_iterations",
                  "paired_trials", "wins", "losses", "mcnemar_p", "oracle_gain_share", "oracle_gain_share_low",
                  "oracle_gain_share_high", "oracle_plan_gain_share", "oracle_plan_gain_share_low",
                  "oracle_plan_gain_share_high")
CEILINGS = ("oracle", "oracle_plan")
"""The methods whose gain over Direct a summary shares out: the straight-line and the planning oracle."""
DEFAULT_USERS = ("noisy", "laggy", "mode_switching", "single_dof", "low_dof")
DEFAULT_METHODS = ("direct", "ho", "rtv3")
METHOD_LABELS = {"direct": "Direct", "ho": "HO", "rtv3": "RT-V3", "oracle": "Oracle", "oracle_goal": "Oracle (goal)",
                 "oracle_plan": "Oracle (plan)",
                 "rtv3_goal": "RT-V3 (goal)"}
def method_label(name: str) -> str:
    """Table label of a method name: ``"direct+neoss"`` -> ``"Direct w. NeoSS"``."""
    base, _, safety = name.partition("+")
    label = METHOD_LABELS.get(base, base)
    return f"{label} w. NeoSS" if safety == "neoss" else label


PAPER_TABLE2_SR = {
    "noisy": {"rtv3": 84.1, "direct": 62.4, "ho": 42.8},
    "laggy": {"rtv3": 86.1, "direct": 80.3, "ho": 9.4},
    "mode_switching": {"rtv3": 83.3, "direct": 74.2, "ho": 18.0},
    "single_dof": {"rtv3": 69.8, "direct": 50.5, "ho": 23.1},
}
for _user, _values in zip(("noisy", "laggy", "mode_switching", "single_dof"),
                          ((72.0, 49.1, 82.2), (79.7, 9.9, 84.0), (81.5, 17.6, 81.1), (62.0, 25.5, 67.6))):
    PAPER_TABLE2_SR[_user].update(zip(("direct+neoss", "ho+neoss", "rtv3+neoss"), _values))  # "w. NeoSS" rows
"""The paper's Table II success rates (%) per user and method (their simulation)."""
PAPER_DIRECT_ITERATIONS = {"noisy": 81.1, "laggy": 58.0, "mode_switching": 118.0, "single_dof": 129.0}
GOAL_FIELDS = ("scene_seed", "grasp_index", "check")
TARGET_SALT = 17
"""Salt of the seeded goal choice (:func:`rtv3_maniskill.records.select_targets`) of benchmark runs."""
RESULT_KEY = ("scene_seed", "grasp_index", "user", "method")
_SPEED_LIMIT_FIELDS = ("max_linear_speed", "max_angular_speed")
"""SharedControlConfig fields the benchmark takes from the env's controller, not from its settings."""


class BenchmarkError(ValueError):
    """A problem with the benchmark's settings or output folder (message meant for the user)."""


@dataclass
class BenchmarkConfig:
    """Settings of one benchmark run (``rtv3 benchmark-shared``)."""

    output: Path
    policy_path: Path | None = None
    """RT-V3 checkpoint; None = the shipped one. Only loaded when ``"rtv3"`` or ``"rtv3_goal"`` is among the
    methods."""
    scenes: int = 50
    users: Sequence[str] = DEFAULT_USERS
    methods: Sequence[str] = DEFAULT_METHODS
    seed: int = 9
    safety_filter: str | None = None
    """``"neoss"``: every method runs behind the NEO collision damper (results named ``METHOD+neoss``)."""
    goals_per_scene: int | None = None
    """Feasible goals per scene (a seeded random subset); None = every feasible goal."""
    max_steps: int = 150
    stop_on_contact: bool = True
    """End a trial at the first robot contact, a failure (the paper's protocol); False lets it go on
    (the contact still counts as a collision, and "reached" says whether the pre-grasp was reached)."""
    obs_mode: str = "state_dict"
    rendered_context: bool = True
    """``state_dict`` mode: the scene cloud rendered once per scene from the depth camera, as `rtv3
    generate` stores it for training (and as ``rtv3 benchmark-shared`` runs by default); False: the
    mesh-sampled cloud (``--mesh-context``), which the shipped prior was not trained on."""
    scene_type: str = "mixed"
    object_source: str = "procedural"
    """GraspClutter-v1's ``object_source`` (e.g. ``"random_urdfs"``); in the fingerprint when not the default."""
    goals: str = "reachable"
    """Which candidates are goals (``rtv3_maniskill.presets.GOAL_RULES``): ``reachable`` (the arm-reach check) or
    ``all`` (every floating-hand-feasible grasp, the authors' rule); ``goals.csv`` holds the check either way."""
    execution: str = "capped"
    """GraspClutter-v1's twist execution: ``capped`` or ``tracked`` (the authors')."""
    self_contacts: bool = True
    """Whether a robot self contact is a collision (False: the authors' rule)."""
    ho_variant: str = "rtv3_authors"
    fusion: str = "tuned"
    """RT-V3's fusion preset (``SharedControlConfig.preset``): ``"tuned"`` or ``"paper"``."""
    shared_control: dict[str, Any] = field(default_factory=dict)
    """Overrides of :class:`SharedControlConfig` fields for RT-V3 (e.g. ``{"ood_dofs": "translation"}``);
    the speed limits always come from the env's controller."""
    extra: dict[str, Any] = field(default_factory=dict)

    def __post_init__(self) -> None:
        from rtv3_maniskill.shared_control.assistance import METHOD_NAMES
        from rtv3_maniskill.shared_control.simulated_users import USERS

        self.output = Path(self.output)
        self.users = tuple(_canonical(u) for u in self.users)
        self.methods = tuple(_canonical(m) for m in self.methods)
        if not self.users or not self.methods:
            raise BenchmarkError("give at least one user and one method")
        for user in self.users:
            if user not in USERS:
                raise BenchmarkError(f"unknown simulated user {user!r}; known users: {', '.join(sorted(USERS))}")
        for method in self.methods:
            if method not in METHOD_NAMES:
                raise BenchmarkError(f"unknown assistance method {method!r}; known methods: {', '.join(METHOD_NAMES)}")
        for name, values in (("users", self.users), ("methods", self.methods)):
            if len(set(values)) != len(values):
                raise BenchmarkError(f"{name} lists a name twice: {', '.join(values)}")
        if self.scenes < 1:
            raise BenchmarkError(f"scenes must be >= 1, got {self.scenes}")
        if self.goals_per_scene is not None and self.goals_per_scene < 1:
            raise BenchmarkError(f"goals_per_scene must be >= 1 or None, got {self.goals_per_scene}")
        if self.max_steps < 1:
            raise BenchmarkError(f"max_steps must be >= 1, got {self.max_steps}")
        if self.obs_mode not in ("state_dict", "pointcloud"):
            raise BenchmarkError(f"obs_mode must be 'state_dict' or 'pointcloud', got {self.obs_mode!r}")
        if self.safety_filter not in (None, "neoss"):
            raise BenchmarkError(f"unknown safety filter {self.safety_filter!r}; known: neoss")
        if self.goals not in GOAL_RULES:
            raise BenchmarkError(f"unknown goal rule {self.goals!r}; known: {', '.join(GOAL_RULES)}")
        if self.execution not in EXECUTIONS:
            raise BenchmarkError(f"unknown execution {self.execution!r}; known: {', '.join(EXECUTIONS)}")
        if self.ho_variant != "rtv3_authors":
            raise BenchmarkError(f"unknown HO variant {self.ho_variant!r}; known: rtv3_authors")
        self.shared_control = dict(self.shared_control)
        for key in _SPEED_LIMIT_FIELDS:
            if key in self.shared_control:
                raise BenchmarkError(f"shared_control may not set {key}: the speed limits come from the env")
        try:
            self.shared_control_config(0.3, 1.2)
        except (TypeError, ValueError) as err:
            raise BenchmarkError(f"bad shared_control settings {self.shared_control}: {err}") from None

    def shared_control_config(self, max_linear_speed: float, max_angular_speed: float):
        """The RT-V3 controller's settings: the defaults, these overrides and the env's speed limits."""
        from rtv3_maniskill.shared_control.shared_controller import SharedControlConfig

        return SharedControlConfig.preset(self.fusion, max_linear_speed=max_linear_speed,
                                          max_angular_speed=max_angular_speed, **self.shared_control)

    def _shared_control_settings(self) -> dict[str, Any]:
        """The RT-V3 controller's settings (OOD gate, user covariance, ...) minus the speed limits
        (those come from the env): results made with other settings are not mixed."""
        import dataclasses

        settings = dataclasses.asdict(self.shared_control_config(0.3, 1.2))
        for key in _SPEED_LIMIT_FIELDS:
            settings.pop(key)
        return settings

    @property
    def uses_shared_controller(self) -> bool:
        """Whether a method runs the RT-V3 fusion (RT-V3, RT-V3 told the goal, or an oracle)."""
        return any(m in ("rtv3", "rtv3_goal", "oracle", "oracle_goal", "oracle_plan") for m in self.methods)

    def scene_seeds(self) -> list[int]:
        return scene_seeds(self.seed, self.scenes)

    def fingerprint(self, policy_path: Path | None) -> dict[str, Any]:
        """Settings that change every trial's outcome: a resumed run must match them. The policy
        is identified by its path *and* the SHA-256 of its weights, so a checkpoint replaced in
        place is not mixed with results of the old one."""
        return dict(
            seed=self.seed, max_steps=self.max_steps, stop_on_contact=self.stop_on_contact, obs_mode=self.obs_mode,
            rendered_context=self.rendered_context,
            scene_type=self.scene_type, ho_variant=self.ho_variant, goals_per_scene=self.goals_per_scene,
            protocol="authors: ready-pose start, feasible goals", safety_filter=self.safety_filter,
            policy_path=str(policy_path.resolve()) if policy_path is not None else None,
            policy_weights_sha256=weights_digest(policy_path) if policy_path is not None else None,
            shared_control=self._shared_control_settings() if self.uses_shared_controller else None, **self.extra,
            # Only when set, so that runs made before the option existed still resume.
            **({"object_source": self.object_source} if self.object_source != "procedural" else {}),
            **({"goals": self.goals} if self.goals != "reachable" else {}),
            **({"execution": self.execution} if self.execution != "capped" else {}),
            **({"self_contacts": self.self_contacts} if not self.self_contacts else {}),
        )

    def env_kwargs(self) -> dict[str, Any]:
        """``GraspClutter-v1`` keyword arguments of these settings (scenes, objects, execution, contacts)."""
        return dict(obs_mode=self.obs_mode, scene_type=self.scene_type, object_source=self.object_source,
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


def _canonical(name: str) -> str:
    return str(name).strip().lower().replace("-", "_")


def user_seed(seed: int, scene_seed: int, grasp_index: int, user: str) -> int:
    """Seed of the user's noise in one trial: same for every method."""
    return int(np.random.SeedSequence([seed, scene_seed, grasp_index, zlib.crc32(user.encode())]).generate_state(1)[0])


# ----------------------------------------------------------------------------- results file


def _is_complete_result(row: dict[str, str]) -> bool:
    return row["outcome"] in ("success", "collision", "timeout") and row["wall_time_s"] != ""


def results_store(output: Path, settings: dict[str, Any] | None) -> RecordStore:
    """``results.csv``: one row per finished trial, guarded by ``config.json``."""
    try:
        return RecordStore(output / "results.csv", RESULT_FIELDS, RESULT_KEY, settings,
                           settings_path=output / "config.json", is_complete=_is_complete_result)
    except SettingsMismatch as err:
        raise BenchmarkError(str(err)) from None
    except ValueError as err:
        raise BenchmarkError(f"{err}; choose another --output") from None


def _result_rows(path: Path) -> list[dict[str, str]]:
    """The complete rows of a ``results.csv``; one written before a column of ``_LATER_RESULT_FIELDS``
    existed reads with that column's default (it can be summarised and merged, not resumed)."""
    first_error = None
    for dropped in range(len(_LATER_RESULT_FIELDS) + 1):
        fields = RESULT_FIELDS[:len(RESULT_FIELDS) - dropped]
        try:
            rows = RecordStore.read(path, fields, _is_complete_result)
        except ValueError as err:
            first_error = first_error or err
            continue
        missing = {name: _LATER_RESULT_FIELDS[name] for name in RESULT_FIELDS[len(fields):]}
        return [dict(row, **missing) for row in rows]
    raise BenchmarkError(str(first_error)) from None


def read_results(path: Path) -> list[dict[str, Any]]:
    """Rows of ``results.csv`` with numbers parsed (a torn last row is left out)."""
    return [{
        **row,
        "scene_seed": int(row["scene_seed"]), "grasp_index": int(row["grasp_index"]),
        "success": int(row["success"]), "collision": int(row["collision"]), "steps": int(row["steps"]),
    } for row in _result_rows(path)]


# ----------------------------------------------------------------------------- summary


def mcnemar_exact(wins: int, losses: int) -> float:
    """Two-sided exact McNemar p-value of ``wins`` against ``losses`` (the discordant pairs):
    a binomial test of ``wins`` in ``wins + losses`` trials at 1/2; 1.0 without discordant pairs."""
    from scipy.stats import binomtest

    n = int(wins) + int(losses)
    return 1.0 if n == 0 else float(binomtest(int(wins), n, 0.5).pvalue)


def _success_by_trial(rows: Iterable[dict[str, Any]]) -> dict[tuple[str, str], dict[tuple[int, int], bool]]:
    """``{(user, method): {(scene_seed, grasp_index): succeeded}}``: the trials to pair methods on."""
    outcome: dict[tuple[str, str], dict[tuple[int, int], bool]] = {}
    for row in rows:
        key = (int(row["scene_seed"]), int(row["grasp_index"]))
        outcome.setdefault((row["user"], row["method"]), {})[key] = row["outcome"] == "success"
    return outcome


def _behind_same_filter(name: str, method: str) -> str:
    """The method ``name`` behind ``method``'s safety filter: ``("direct", "rtv3+neoss")`` -> ``"direct+neoss"``."""
    _, plus, safety_filter = method.partition("+")
    return name + plus + safety_filter


def paired_with_baseline(rows: Iterable[dict[str, Any]],
                         baseline: str = "direct") -> dict[tuple[str, str], dict[str, Any]]:
    """Per (user, method) other than ``baseline``: the trials both ran (same scene, goal and user
    noise), ``wins`` (success where the baseline failed), ``losses`` (the reverse) and the exact
    McNemar p-value. A method behind a safety filter (``"rtv3+neoss"``) is paired with the baseline
    behind the same filter (``"direct+neoss"``), so the filter's own effect is not counted as help."""
    outcome = _success_by_trial(rows)
    out = {}
    for (user, method), trials in outcome.items():
        paired_baseline = _behind_same_filter(baseline, method)
        base = outcome.get((user, paired_baseline))
        if method == paired_baseline or base is None:
            continue
        common = trials.keys() & base.keys()
        wins = sum(1 for k in common if trials[k] and not base[k])
        losses = sum(1 for k in common if base[k] and not trials[k])
        out[(user, method)] = dict(paired_trials=len(common), wins=wins, losses=losses,
                                   mcnemar_p=mcnemar_exact(wins, losses))
    return out


def oracle_gain_share(rows: Iterable[dict[str, Any]], baseline: str = "direct", ceiling: str = "oracle",
                      resamples: int = 2000, seed: int = 0) -> dict[tuple[str, str], dict[str, Any]]:
    """Per (user, method) other than ``baseline`` and ``ceiling``: the share of the ceiling's gain
    over the baseline that the method reaches, ``(SR_m - SR_b) / (SR_c - SR_b)``, on the goals all
    three ran (same user noise; a method behind a safety filter with the baseline and ceiling behind
    the same filter), with a 95 % paired bootstrap interval: goals resampled with replacement
    ``resamples`` times, a resample where the ceiling does not beat the baseline left out (the share
    is undefined there). Users where the ceiling does not beat the baseline get no entry. Each (user,
    method) draws its resamples from its own stream of ``seed``, so its interval does not depend on
    which other users and methods the rows hold (a merged folder gives a part's intervals again).

    Returns ``{(user, method): dict(goals, baseline_SR, SR, ceiling_SR, share, share_low, share_high)}``
    (SR in %, share as a fraction; the interval None if fewer than half of the resamples count)."""
    outcome = _success_by_trial(rows)
    out = {}
    for (user, method), trials in sorted(outcome.items()):
        if method in (_behind_same_filter(baseline, method), _behind_same_filter(ceiling, method)):
            continue
        base = outcome.get((user, _behind_same_filter(baseline, method)))
        top = outcome.get((user, _behind_same_filter(ceiling, method)))
        if base is None or top is None:
            continue
        common = sorted(trials.keys() & base.keys() & top.keys())
        if not common:
            continue
        m, b, c = (np.array([d[k] for k in common], dtype=float) for d in (trials, base, top))
        if c.mean() <= b.mean():
            continue
        rng = np.random.default_rng([seed, zlib.crc32(user.encode()), zlib.crc32(method.encode())])
        idx = rng.integers(0, len(common), size=(resamples, len(common)))
        gain, top_gain = m[idx].mean(1) - b[idx].mean(1), c[idx].mean(1) - b[idx].mean(1)
        counted = top_gain > 0
        low = high = None
        if counted.mean() >= 0.5:
            low, high = (float(q) for q in np.quantile(gain[counted] / top_gain[counted], [0.025, 0.975]))
        out[(user, method)] = dict(goals=len(common), baseline_SR=100 * b.mean(), SR=100 * m.mean(),
                                   ceiling_SR=100 * c.mean(), share=(m.mean() - b.mean()) / (c.mean() - b.mean()),
                                   share_low=low, share_high=high)
    return out


def summarize(rows: Iterable[dict[str, Any]], users: Sequence[str] | None = None,
              methods: Sequence[str] | None = None) -> list[dict[str, Any]]:
    """Per (user, method): trials, SR / CR / TOR % (exclusive outcomes, they add up to 100), reached %
    (pre-grasp reached, contact or not), mean iterations of the successful trials (NaN if none), and
    the paired comparison with Direct behind the same safety filter (:func:`paired_with_baseline`;
    None for Direct itself), and the share of the oracle's gain over Direct with its interval
    (:func:`oracle_gain_share`; None without an oracle that beats Direct for that user).
    Every row counts; ``users`` / ``methods`` only set the order (names not listed follow, sorted)."""
    rows = list(rows)
    paired = paired_with_baseline(rows)
    shares = {ceiling: oracle_gain_share(rows, ceiling=ceiling) for ceiling in CEILINGS}
    groups: dict[tuple[str, str], list[dict[str, Any]]] = {}
    for row in rows:
        groups.setdefault((row["user"], row["method"]), []).append(row)
    order_u = list(dict.fromkeys([*(users or []), *sorted({u for u, _ in groups})]))
    order_m = list(dict.fromkeys([*(methods or []), *sorted({m for _, m in groups})]))
    out = []
    for u in order_u:
        for m in order_m:
            trials = groups.get((u, m), [])
            if not trials:
                continue
            n = len(trials)
            outcomes = [t["outcome"] for t in trials]
            wins = [t for t in trials if t["outcome"] == "success"]
            out.append(dict(
                user=u, method=m, trials=n,
                SR=100.0 * len(wins) / n,
                CR=100.0 * outcomes.count("collision") / n,
                TOR=100.0 * outcomes.count("timeout") / n,
                reached=100.0 * sum(int(t["success"]) for t in trials) / n,
                mean_iterations=float(np.mean([int(t["steps"]) for t in wins])) if wins else math.nan,
                **paired.get((u, m), dict(paired_trials=None, wins=None, losses=None, mcnemar_p=None)),
                **{k: v for c in CEILINGS for k, v in _share_fields(shares[c].get((u, m)), c).items()},
            ))
    return out


def _share_fields(share: dict[str, Any] | None, ceiling: str = "oracle") -> dict[str, Any]:
    """The summary's columns of :func:`oracle_gain_share` towards ``ceiling`` (None where it has no entry)."""
    share = share or {}
    return {f"{ceiling}_gain_share": share.get("share"), f"{ceiling}_gain_share_low": share.get("share_low"),
            f"{ceiling}_gain_share_high": share.get("share_high")}


def _percent(fraction: float) -> str:
    """A fraction as a whole percentage (``-0.003`` -> ``"0"``)."""
    return str(int(round(100 * fraction)))


def _fmt(value: float, digits: int = 1) -> str:
    return "-" if value is None or (isinstance(value, float) and math.isnan(value)) else f"{value:.{digits}f}"


def _paired_text(s: dict[str, Any]) -> tuple[str, str]:
    if s.get("wins") is None:
        return "-", "-"
    return f"{s['wins']} / {s['losses']}", f"{s['mcnemar_p']:.3g}"


def _paper_text(s: dict[str, Any]) -> str:
    paper = PAPER_TABLE2_SR.get(s["user"], {}).get(s["method"])
    return "-" if paper is None else f"{paper:.1f}"


def goal_counts(path: Path) -> dict[str, int]:
    """Candidates per goal check (``goals.csv``), plus ``candidates`` and ``scenes``."""
    rows = RecordStore.read(path, GOAL_FIELDS) if Path(path).is_file() else []
    counts = {check: sum(1 for r in rows if r["check"] == check) for check in sorted({r["check"] for r in rows})}
    return dict(counts, candidates=len(rows), scenes=len({r["scene_seed"] for r in rows}))


def summary_markdown(summary: Sequence[dict[str, Any]], goals: dict[str, int] | None = None,
                     goal_rule: str = "reachable") -> str:
    """Markdown table: one row per (user, method), paired with Direct, the paper's SR beside; the goal
    counts of ``goals.csv`` under ``goal_rule`` above it."""
    lines = []
    if goals and goals.get("candidates"):
        infeasible = ", ".join(f"{v} {k}" for k, v in goals.items() if k not in ("feasible", "candidates", "scenes"))
        if goal_rule == "all":
            lines += [f"Goals (rule `all`, the authors': every floating-hand-feasible grasp): {goals['candidates']} "
                      f"grasp candidates in {goals['scenes']} scenes, of which {goals.get('feasible', 0)} pass the "
                      f"arm-reach check (others: {infeasible or 'none'}).", ""]
        else:
            lines += [f"Goals (rule `reachable`): {goals.get('feasible', 0)} feasible of {goals['candidates']} grasp "
                      f"candidates in {goals['scenes']} scenes (infeasible, never run: {infeasible or 'none'}).", ""]
    lines += [
        "| User | Method | Trials | SR % (↑) | CR % (↓) | TOR % (↓) | reached % | Iter (↓) | W / L vs Direct "
        "| McNemar p | paper SR % |",
        "|---|---|---:|---:|---:|---:|---:|---:|---:|---:|---:|",
    ]
    for s in summary:
        paired, p = _paired_text(s)
        lines.append(
            f"| {s['user']} | {method_label(s['method'])} | {s['trials']} | {_fmt(s['SR'])} | "
            f"{_fmt(s['CR'])} | {_fmt(s['TOR'])} | {_fmt(s['reached'])} | {_fmt(s['mean_iterations'])} | "
            f"{paired} | {p} | {_paper_text(s)} |"
        )
    notes = (
        "\nOne outcome per trial: CR = a robot contact came first (the trial fails), SR = the target "
        "pre-grasp was reached first (pose distance < 0.1), TOR = neither within the step limit; reached: "
        "the pre-grasp was reached with or without a contact; Iter: mean control steps (20 Hz) of the "
        "successful trials. W / L: trials this method succeeded where Direct (behind the same safety "
        "filter) failed / the reverse, on the same goals and user noise; McNemar p: exact two-sided test "
        "of W against L. Paper SR: Table II "
        "(their simulation; their Direct took 81 / 58 / 118 / 129 iterations for noisy / laggy / "
        "mode-switching / single-DoF).\n"
    )
    for ceiling in CEILINGS:
        shares = [s for s in summary if s.get(f"{ceiling}_gain_share") is not None]
        if not shares:
            continue
        name = method_label(ceiling)
        notes += (
            f"\nShare of the {name} gain over Direct, (SR - Direct SR) / ({name} SR - Direct SR), on the goals "
            "all three ran, with a 95 % paired bootstrap interval over those goals:\n\n"
            f"| User | Method | share of the {name} gain % | 95 % interval |\n|---|---|---:|---:|\n"
        )
        for s in shares:
            low, high = s[f"{ceiling}_gain_share_low"], s[f"{ceiling}_gain_share_high"]
            interval = "-" if low is None else f"{_percent(low)} to {_percent(high)}"
            share = _percent(s[f"{ceiling}_gain_share"])
            notes += f"| {s['user']} | {method_label(s['method'])} | {share} | {interval} |\n"
    return "\n".join(lines) + "\n" + notes


def plot_success_rates(summary: Sequence[dict[str, Any]], path: Path) -> None:
    """Grouped bar plots: SR per user (groups) and method (bars) above, CR below."""
    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    users = list(dict.fromkeys(s["user"] for s in summary))
    methods = list(dict.fromkeys(s["method"] for s in summary))
    table = {(s["user"], s["method"]): s for s in summary}
    width = 0.8 / max(len(methods), 1)
    x = np.arange(len(users))
    fig, axes = plt.subplots(2, 1, figsize=(max(7, 1.9 * len(users)), 7), sharex=True)
    for ax, key, title in ((axes[0], "SR", "Success rate (%)"), (axes[1], "CR", "Collision rate (%)")):
        for j, m in enumerate(methods):
            values = [table[(u, m)][key] if (u, m) in table else 0.0 for u in users]
            bars = ax.bar(x + (j - (len(methods) - 1) / 2) * width, values, width, label=method_label(m))
            for bar, v in zip(bars, values):
                ax.annotate(f"{v:.0f}", (bar.get_x() + bar.get_width() / 2, v), ha="center", va="bottom", fontsize=7)
        ax.set_xticks(x, [u.replace("_", "-") for u in users])
        ax.set_ylim(0, 118)
        ax.set_yticks(range(0, 101, 20))
        ax.set_title(title)
        ax.grid(axis="y", alpha=0.3)
    axes[0].legend(loc="upper center", ncol=len(methods), fontsize=8, frameon=False)
    trials = sum(s["trials"] for s in summary)
    fig.suptitle(f"Simulated shared control ({trials} trials)")
    fig.tight_layout()
    fig.savefig(path, dpi=120)
    plt.close(fig)


def write_summaries(output: Path, users: Sequence[str] | None = None,
                    methods: Sequence[str] | None = None) -> list[dict[str, Any]]:
    """``summary.csv``, ``summary.md`` and ``success_rates.png`` from every row of ``output/results.csv``."""
    rows = read_results(output / "results.csv")
    summary = summarize(rows, users, methods)
    with (output / "summary.csv").open("w", newline="") as f:
        writer = csv.DictWriter(f, SUMMARY_FIELDS)
        writer.writeheader()
        for s in summary:
            writer.writerow({k: (f"{v:.3f}" if isinstance(v, float) else v) for k, v in s.items()})
    config_path = output / "config.json"
    goal_rule = json.loads(config_path.read_text()).get("goals", "reachable") if config_path.is_file() else "reachable"
    (output / "summary.md").write_text(summary_markdown(summary, goal_counts(output / "goals.csv"), goal_rule))
    if summary:
        plot_success_rates(summary, output / "success_rates.png")
    return summary


# ----------------------------------------------------------------------------- merging runs


def merge_runs(sources: Sequence[Path], output: Path) -> list[dict[str, Any]]:
    """Combine runs split over processes (e.g. ``--methods direct,ho`` and ``--methods rtv3``) into
    ``output`` (a new folder): ``results.csv``, the summaries and the plot; returns the summary rows.

    The runs must agree on every setting they both record (``config.json``; a run without RT-V3
    records no policy), and no trial may appear in two of them. ``output/config.json`` holds the
    combined settings, so the merged folder can be read and summarised but not resumed by a run
    that lacks one of the merged parts' settings.
    """
    sources = [Path(d) for d in sources]
    output = Path(output)
    if len(sources) < 2:
        raise BenchmarkError("give at least two benchmark output folders to merge")
    if output.resolve() in {d.resolve() for d in sources}:
        raise BenchmarkError(f"the merged output {output} must be a new folder, not one of the runs")
    if (output / "results.csv").exists():
        raise BenchmarkError(f"{output} already holds results.csv; choose a new --output for the merge")
    settings: dict[str, Any] = {}
    origin: dict[str, Path] = {}
    rows: list[dict[str, Any]] = []
    seen: dict[tuple[int, int, str, str], Path] = {}
    for folder in sources:
        config_path, results_path = folder / "config.json", folder / "results.csv"
        for path in (config_path, results_path):
            if not path.is_file():
                raise BenchmarkError(f"{folder} is not a benchmark output folder: {path.name} is missing")
        for key, value in json.loads(config_path.read_text()).items():
            if value is None:
                continue
            if key in settings and settings[key] != value:
                raise BenchmarkError(f"{origin[key]} and {folder} were run with other settings "
                                     f"({key}: {settings[key]!r} vs {value!r}); they cannot be merged")
            settings.setdefault(key, value)
            origin.setdefault(key, folder)
        for row in _result_rows(results_path):
            key = tuple(row[k] for k in RESULT_KEY)
            if key in seen:
                raise BenchmarkError(f"trial {key} is in both {seen[key]} and {folder}; merge runs of disjoint "
                                     "users or methods")
            seen[key] = folder
            rows.append(row)
    output.mkdir(parents=True, exist_ok=True)
    (output / "config.json").write_text(json.dumps(settings, indent=2))
    goals = [folder / "goals.csv" for folder in sources if (folder / "goals.csv").is_file()]
    if goals:  # the goal checks of the scenes (the same in every run of these settings)
        shutil.copyfile(goals[0], output / "goals.csv")
    with (output / "results.csv").open("w", newline="") as f:
        writer = csv.DictWriter(f, RESULT_FIELDS)
        writer.writeheader()
        writer.writerows(rows)
    return write_summaries(output, DEFAULT_USERS, DEFAULT_METHODS)  # the usual order; other names follow


# ----------------------------------------------------------------------------- the run


def trial_options(grasp_index: int) -> dict[str, Any]:
    """Reset options of one trial: its target, and the arm at the Panda ready pose."""
    from rtv3_maniskill.robot.scene_geometry import READY_QPOS

    return dict(target_grasp_index=int(grasp_index), init_qpos=READY_QPOS)


class _SceneRunner:
    """One process's env and assistance methods: runs the trials of one scene at a time (the whole
    run in a serial run, one worker's share with ``workers > 1``)."""

    def __init__(self, config: BenchmarkConfig, policy: Any = None) -> None:
        import torch

        from rtv3_maniskill.benchmarks.episodes import SharedControlEnv, controller_speed_limits, make_method

        torch.set_num_threads(1)
        self.config = config
        if _needs_policy(config) and policy is None:
            from rtv3_maniskill.policies.rtv3.checkpoints import load_policy

            policy = load_policy(_policy_path(config))  # clear error when missing
        env_kwargs = config.env_kwargs()
        if policy is not None:
            env_kwargs.update(num_points=int(policy.config.num_points), max_grasps=int(policy.config.max_grasps))
        self.env = SharedControlEnv(rendered_context=config.rendered_context, safety_filter=config.safety_filter,
                                    **env_kwargs)
        self.suffix = f"+{config.safety_filter}" if config.safety_filter else ""
        limits = controller_speed_limits(self.env.base)
        shared_config = config.shared_control_config(*limits)
        self.methods = {m: make_method(m, limits, policy=policy, ho_variant=config.ho_variant, config=shared_config)
                        for m in config.methods}

    def run_scene(self, scene_seed: int, checks: dict[int, str], done: set[tuple[str, ...]],
                  on_checks: Callable[[list[dict[str, Any]]], None] | None = None,
                  on_plan: Callable[[int], None] | None = None,
                  on_trial: Callable[[dict[str, Any]], None] | None = None) -> tuple[list[dict], list[dict]]:
        """Every trial of scene ``scene_seed`` not in ``done`` (result keys, as ``results.csv`` holds
        them: strings).

        ``checks`` maps the grasp indices already checked to their verdict (``goals.csv``); the
        scene's missing checks are made here; ``on_checks(rows)`` hears them before any trial runs,
        ``on_plan(n)`` the scene's number of trials, ``on_trial(row)`` each result as it finishes.
        Returns the new goal-check rows and the result rows.
        """
        from rtv3_maniskill.benchmarks.episodes import run_episode
        from rtv3_maniskill.benchmarks.goals import aimed_pregrasp, check_scene_goals
        from rtv3_maniskill.shared_control.simulated_users import make_user

        config, env = self.config, self.env
        env.reset(seed=scene_seed)
        count = int((env.base.grasps_mask[0] > 0.5).sum())
        new_checks: list[dict[str, Any]] = []
        unchecked = any(i not in checks for i in range(count))  # a scene not checked yet (or only in part)
        planner = None
        if unchecked or "oracle_plan" in self.methods:
            from rtv3_maniskill.robot.planner import PandaPlanner

            planner = PandaPlanner(env.base.layouts[0])
        if unchecked:
            checks = dict(checks)
            for i, check in enumerate(check_scene_goals(env.base, planner, seed=scene_seed)):
                if i not in checks:
                    checks[i] = check
                    new_checks.append(dict(scene_seed=scene_seed, grasp_index=i, check=check))
        if on_checks is not None:
            on_checks(new_checks)
        feasible = [i for i in range(count) if config.goals == "all" or checks[i] == "feasible"]
        grasps = select_targets(feasible, config.goals_per_scene, config.seed, scene_seed, salt=TARGET_SALT)
        pregrasps = pregrasp_poses(env.base.grasp_poses[0].double())
        if on_plan is not None:
            on_plan(len(grasps) * len(config.users) * len(config.methods))
        rows: list[dict[str, Any]] = []
        for g in grasps:
            for user_name in config.users:
                u_seed = user_seed(config.seed, scene_seed, g, user_name)
                for method_name, method in self.methods.items():
                    if (str(scene_seed), str(g), user_name, method_name + self.suffix) in done:
                        continue
                    start = time.perf_counter()
                    if method_name in ("oracle", "oracle_goal"):  # the prior that knows the scene
                        method.policy.set_goals(pregrasps[feasible] if method_name == "oracle" else pregrasps[[g]])
                    elif method_name == "rtv3_goal":  # the learned prior told the target
                        method.policy.set_target(g)
                    elif method_name == "oracle_plan":  # the true goal and the planner of this scene
                        method.policy.set_goal(planner, aimed_pregrasp(planner, env.base.grasp_poses[0, g]))
                    result = run_episode(env, method, make_user(user_name, u_seed), max_steps=config.max_steps,
                                         seed=scene_seed, options=trial_options(g),
                                         stop_on_contact=config.stop_on_contact)
                    counts = result.mode_counts
                    row = dict(
                        scene_seed=scene_seed, grasp_index=g, user=user_name, method=method_name + self.suffix,
                        outcome=result.outcome, success=int(result.success), collision=int(result.collision),
                        steps=result.steps,
                        final_distance=f"{result.final_distance:.4f}",
                        autonomous_steps=counts.get("autonomous", 0), user_only_steps=counts.get("user_only", 0),
                        user_seed=u_seed, wall_time_s=f"{time.perf_counter() - start:.2f}",
                        qp_infeasible_steps=result.qp_infeasible_steps, contact=result.contact,
                    )
                    rows.append(row)
                    if on_trial is not None:
                        on_trial(row)
        return new_checks, rows

    def close(self) -> None:
        self.env.close()


def _needs_policy(config: BenchmarkConfig) -> bool:
    return any(m in ("rtv3", "rtv3_goal") for m in config.methods)


def _policy_path(config: BenchmarkConfig) -> Path:
    """The checkpoint's local folder (a Hub repo id resolved to its cached snapshot)."""
    from rtv3_maniskill.policies.rtv3.checkpoints import resolve_checkpoint

    return resolve_checkpoint(config.policy_path)


def _run_scene_job(runner: _SceneRunner, job: tuple[int, dict[int, str], set[tuple[str, ...]]]
                   ) -> tuple[list[dict], list[dict]]:
    return runner.run_scene(*job)


def run_benchmark(config: BenchmarkConfig, policy: Any = None, progress: bool = True,
                  workers: int = 1, executor: str = "local", ray_address: str | None = None) -> list[dict[str, Any]]:
    """Run (or resume) the benchmark; returns the summary rows. ``policy`` overrides ``policy_path``.

    ``workers > 1`` or ``executor="ray"`` runs scenes in that many workers of the scene pool
    (:func:`rtv3_maniskill.scene_pool.run_scenes`; each loads the policy from ``policy_path``, so
    ``policy`` must be None); this process alone writes ``results.csv`` and ``goals.csv``, a scene's
    rows once the scene is done, so an interrupted run loses at most the scenes in flight and the
    folder is the same as a serial run's (either resumes the other). A failing worker stops the run
    (:class:`~rtv3_maniskill.scene_pool.SceneWorkerError`).
    """
    from tqdm import tqdm

    from rtv3_maniskill.scene_pool import EXECUTORS, run_scenes

    if workers < 1:
        raise BenchmarkError(f"workers must be >= 1, got {workers}")
    if executor not in EXECUTORS:
        raise BenchmarkError(f"unknown executor {executor!r}; known: {', '.join(EXECUTORS)}")
    serial = workers == 1 and executor == "local"
    if not serial and policy is not None:
        raise BenchmarkError("a policy object cannot be sent to worker processes: give policy_path with workers > 1")
    output = config.output
    if output.exists() and not output.is_dir():
        raise BenchmarkError(f"--output {output} is a file, not a folder; give a folder for the results")
    output.mkdir(parents=True, exist_ok=True)
    policy_path = None
    if _needs_policy(config) and (policy is None or config.policy_path is not None):
        policy_path = _policy_path(config)
    fingerprint = config.fingerprint(policy_path)
    results = results_store(output, fingerprint)
    goal_checks = RecordStore(output / "goals.csv", GOAL_FIELDS, ("scene_seed", "grasp_index"),
                              {k: fingerprint[k] for k in ("seed", "scene_type", "protocol", "object_source")
                               if k in fingerprint})
    done_by_scene: dict[int, set[tuple[str, ...]]] = {}
    for row in results.rows:
        done_by_scene.setdefault(int(row["scene_seed"]), set()).add(results.key(row))
    checked: dict[int, dict[int, str]] = {}
    for row in goal_checks.rows:
        checked.setdefault(int(row["scene_seed"]), {})[int(row["grasp_index"])] = row["check"]
    jobs = [(s, checked.get(s, {}), done_by_scene.get(s, set())) for s in config.scene_seeds()]

    # One process: a bar over trials (their number known scene by scene); several: over scenes.
    bar = tqdm(total=0 if serial else len(jobs), unit="trial" if serial else "scene",
               disable=not progress, dynamic_ncols=True)
    wins: dict[str, list[int]] = {}

    def plan(trials: int) -> None:
        bar.total += trials
        bar.refresh()

    def record(row: dict[str, Any]) -> None:
        results.append(row)
        wins.setdefault(row["method"], []).append(int(row["outcome"] == "success"))
        bar.set_postfix({method_label(m): f"{100 * np.mean(v):.0f}%" for m, v in wins.items()})

    def record_trial(row: dict[str, Any]) -> None:
        record(row)
        bar.update(1)

    def record_checks(rows: list[dict[str, Any]]) -> None:
        for row in rows:
            goal_checks.append(row)

    runner = None
    try:
        if serial:
            runner = _SceneRunner(config, policy)
            for scene_seed, checks, done in jobs:
                runner.run_scene(scene_seed, checks, done, on_checks=record_checks, on_plan=plan, on_trial=record_trial)
                bar.update(len(done))  # the scene's trials finished in an earlier run
        else:
            for new_checks, rows in run_scenes(_SceneRunner, config, _run_scene_job, jobs, workers=workers,
                                               executor=executor, ray_address=ray_address):
                record_checks(new_checks)
                for row in rows:
                    record(row)
                bar.update(1)
    finally:
        if runner is not None:
            runner.close()
        bar.close()
        results.close()
        goal_checks.close()
    return write_summaries(output, config.users, config.methods)
