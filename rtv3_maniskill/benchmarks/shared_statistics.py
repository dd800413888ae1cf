"""Statistics of the shared-control benchmark: outcome rates per (user, method), and each method
paired with Direct on the same trials.

Rows are ``results.csv`` rows (:func:`rtv3_maniskill.benchmarks.shared_results.read_results`). Every
trial has one outcome (``success``, ``collision`` or ``timeout``; SR + CR + TOR = 100 %). A method is
paired with Direct on the trials both ran (same scene, goal and user noise): wins, losses and the
exact McNemar test; with an oracle among the methods (a ceiling,
:data:`~rtv3_maniskill.shared_control.methods.CEILINGS`), the share of the oracle's gain over Direct
that each method reaches, with a paired bootstrap interval. A method behind a safety filter
(``"rtv3+neoss"``) is compared with Direct and the oracle behind the same filter.
"""

from __future__ import annotations

import math
import zlib
from collections.abc import Iterable, Sequence
from typing import Any

import numpy as np

from rtv3_maniskill.shared_control.methods import CEILINGS

SUMMARY_FIELDS = ("user", "method", "trials", "SR", "CR", "TOR", "reached", "mean_iterations",
                  "paired_trials", "wins", "losses", "mcnemar_p",
                  *(f"{ceiling}_gain_share{end}" for ceiling in CEILINGS for end in ("", "_low", "_high")))
"""Columns of ``summary.csv``: one row per (user, method) of :func:`summarize`."""


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


def success_by_goal_check(rows: Iterable[dict[str, Any]], checks: dict[tuple[int, int], str]
                          ) -> dict[tuple[str, str], dict[str, tuple[int, float]]]:
    """``{(user, method): {check: (trials, SR %)}}``: the success rate on the goals of each arm-reach
    check (``checks``: ``{(scene_seed, grasp_index): check}`` from ``goals.csv``; a trial whose goal has
    no check is left out). Under the goal rule ``all`` it separates the goals the arm can reach from
    those it cannot."""
    counts: dict[tuple[str, str], dict[str, list[int]]] = {}
    for row in rows:
        check = checks.get((int(row["scene_seed"]), int(row["grasp_index"])))
        if check is None:
            continue
        tally = counts.setdefault((row["user"], row["method"]), {}).setdefault(check, [0, 0])
        tally[0] += 1
        tally[1] += row["outcome"] == "success"
    return {key: {c: (n, 100.0 * won / n) for c, (n, won) in by_check.items()} for key, by_check in counts.items()}


def _share_fields(share: dict[str, Any] | None, ceiling: str = "oracle") -> dict[str, Any]:
    """The summary's columns of :func:`oracle_gain_share` towards ``ceiling`` (None where it has no entry)."""
    share = share or {}
    return {f"{ceiling}_gain_share": share.get("share"), f"{ceiling}_gain_share_low": share.get("share_low"),
            f"{ceiling}_gain_share_high": share.get("share_high")}
