"""`rtv3 study`: the counterbalanced plan, the statistics against scipy, analyze on simulated-user sessions."""

from __future__ import annotations

import numpy as np
import pytest
from scipy import stats

from rtv3_maniskill.cli import main
from rtv3_maniskill.teleop.study import compare_methods, latin_square, plan_study


def test_statistics_match_scipy_on_a_hand_made_example():
    values = {"direct": [12.0, 15.5, 11.2, 19.0, 14.1], "ho": [10.1, 9.8, 12.5, 11.0, 13.3],
              "rtv3": [6.2, 7.9, 5.5, 8.8, 7.1, 6.6]}
    result = compare_methods(values)
    h = stats.kruskal(*values.values())
    assert np.allclose(result["kruskal"], (h.statistic, h.pvalue))
    pairs = [("direct", "ho"), ("direct", "rtv3"), ("ho", "rtv3")]
    p = np.array([stats.mannwhitneyu(values[a], values[b], alternative="two-sided").pvalue for a, b in pairs])
    order = np.argsort(p)  # Benjamini-Hochberg by hand: p * m / rank, monotone from the largest
    ranked = p[order] * len(p) / np.arange(1, len(p) + 1)
    adjusted = np.empty_like(p)
    adjusted[order] = np.minimum.accumulate(ranked[::-1])[::-1].clip(max=1.0)
    assert [r[:2] for r in result["pairs"]] == pairs
    assert np.allclose([r[3] for r in result["pairs"]], p)
    assert np.allclose([r[4] for r in result["pairs"]], adjusted)
    assert result["pairs"][1][4] < 0.05  # rtv3 is clearly faster than direct here


def test_plan_is_a_latin_square_with_practice():
    square = latin_square(3)
    assert all(sorted(row) == [0, 1, 2] for row in square)
    assert all(sorted(col) == [0, 1, 2] for col in zip(*square))
    rows = plan_study(participants=3, methods=["direct", "ho", "rtv3"], trials_per_block=2, practice_trials=1)
    assert len(rows) == 3 * 3 * 3
    study = [r for r in rows if not r["practice"]]
    firsts = {r["participant"]: r["method"] for r in reversed(rows)}
    assert sorted(firsts.values()) == ["direct", "ho", "rtv3"]  # each method opens once
    for p in ("P01", "P02", "P03"):
        mine = [r for r in study if r["participant"] == p]
        assert sorted({r["method"] for r in mine}) == ["direct", "ho", "rtv3"]
        assert len({r["scene_group"] for r in mine}) == 3  # each method on its own scene group
    assert not {r["scene_seed"] for r in rows if r["practice"]} & {r["scene_seed"] for r in study}


@pytest.mark.sim
def test_analyze_sessions_recorded_with_simulated_users(tmp_path, capsys):
    sessions = []
    for participant, method, user in (("P01", "direct", "ideal"), ("P02", "ho", "ideal")):
        folder = tmp_path / f"{participant}_{method}"
        assert main(["teleop", "--method", method, "--input", f"simulated:{user}", "--headless", "--trials", "2",
                     "--timeout", "10", "--participant", participant, "--record", str(folder),
                     "--preset", "easy", "--scene-type", "pile"]) == 0  # scenes the ideal user grasps in
        sessions.append(str(folder))
    out = tmp_path / "analysis"
    assert main(["study", "analyze", *sessions, "--output", str(out)]) == 0
    text = capsys.readouterr().out
    assert "per participant and method" in text and "kruskal" in text and "mannwhitneyu" in text
    assert "P01" in text and "P02" in text
    for name in ("trials.csv", "summary.csv", "stats.csv", "boxplots.png"):
        assert (out / name).stat().st_size > 0
