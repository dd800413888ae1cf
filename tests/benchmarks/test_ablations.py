"""`rtv3 evaluate ablations`: Table I's rows from lerobot-train run folders, at one common step.

The two evaluations it runs per row are tested in ``test_evaluation.py``; here they are stand-ins that
write their reports, so that the test checks the step choice, the command lines and the table.
"""

from __future__ import annotations

import json
from pathlib import Path

import pytest

from rtv3_maniskill.cli import evaluate, main


def _runs(root: Path, steps: dict[str, list[int]]) -> Path:
    for row, saved in steps.items():
        for step in saved:
            model = root / row / "checkpoints" / f"{step:06d}" / "pretrained_model"
            model.mkdir(parents=True)
            (model / "model.safetensors").write_bytes(b"")
    (root / "full" / "checkpoints" / "000300").mkdir()  # no pretrained_model: an unfinished save
    return root


@pytest.fixture
def calls(monkeypatch) -> list[tuple[str, Path]]:
    """Stand-ins for the two evaluations: each writes the report its real one writes, from the row's name."""
    made: list[tuple[str, Path]] = []
    value = {"full": 1.0, "no_grasp_encoder": 2.0, "no_point_encoder": 3.0, "6d_pred": 4.0}

    def prediction(args):
        made.append(("prediction", args.policy_path))
        assert args.all_scenes and args.dataset_root == Path("held")
        x = value[args.policy_path.parts[-4]]
        args.output.write_text(json.dumps({"metrics": {"ade_bom": x, "fde_bom": 2 * x, "ade_ml": 3 * x,
                                                       "fde_ml": 4 * x}, "num_windows": 7}))

    def planning(args):
        made.append(("planning", args.policy_path))
        assert args.scenes == 3 and args.seed == 9 and args.max_grasps_per_scene == 2
        x = value[args.policy_path.parts[-4]]
        args.output.mkdir(parents=True, exist_ok=True)
        (args.output / "planning_summary.json").write_text(json.dumps(
            {"SR": x / 10, "CR": x / 20, "TOR": x / 40, "trials": 6}))

    monkeypatch.setattr(evaluate, "_run_prediction", prediction)
    monkeypatch.setattr(evaluate, "_run_planning", planning)
    return made


def test_every_row_is_evaluated_at_the_largest_common_step(tmp_path, calls):
    runs = _runs(tmp_path / "runs", {"full": [100, 200], "6d_pred": [100, 200, 400], "no_point_encoder": [200]})
    argv = ["evaluate", "ablations", "--runs", str(runs), "--dataset.root", "held", "--scenes", "3"]
    assert main(argv) == 0
    rows = ("full", "no_point_encoder", "6d_pred")
    assert calls == [(kind, runs / row / "checkpoints" / "000200" / "pretrained_model")
                     for row in rows for kind in ("prediction", "planning")]
    report = json.loads((runs / "table1.json").read_text())
    assert report["step"] == 200 and list(report["rows"]) == list(rows)
    assert report["rows"]["6d_pred"]["SR"] == 0.4 and report["rows"]["full"]["planning_trials"] == 6
    table = (runs / "table1.md").read_text().splitlines()
    assert table[4] == "| RT-V3 (full) | 1.00 (26.70) | 2.00 (37.90) | 3.00 (32.05) | 4.00 (47.87) | 10.0 (90.4) " \
                       "| 5.0 (7.9) | 2.5 (1.7) |"
    assert table[6].startswith("| 6D pred (joint 6-D Gaussian) | 4.00 (21.05) |")

    calls.clear()  # a rerun reuses the prediction reports; planning resumes from its own records
    assert main(argv) == 0
    assert [kind for kind, _ in calls] == ["planning"] * 3


def test_a_step_not_saved_by_every_row_or_no_run_is_one_error_line(tmp_path, calls):
    runs = _runs(tmp_path / "runs", {"full": [100, 200], "no_grasp_encoder": [100]})
    with pytest.raises(SystemExit) as err:
        main(["evaluate", "ablations", "--runs", str(runs), "--step", "200"])
    assert err.value.code == "error: step 200 is not saved by every row (full, no_grasp_encoder); common steps: [100]"
    with pytest.raises(SystemExit) as err:
        main(["evaluate", "ablations", "--runs", str(tmp_path / "nothing")])
    assert err.value.code == (f"error: no run folder (full, no_grasp_encoder, no_point_encoder, 6d_pred) "
                              f"under {tmp_path / 'nothing'}")
    assert calls == []
