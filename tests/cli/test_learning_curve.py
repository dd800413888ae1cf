"""`rtv3 learning-curve`: the campaign's stages in training order, the curve files, the best stage."""

from __future__ import annotations

import csv
import json

import torch
from safetensors.torch import save_file

from rtv3_maniskill.cli import main


def _stage(out, name, episodes, step, sr, cr):
    folder = out / name
    (folder / "cache").mkdir(parents=True)
    (folder / "cache" / "summary.json").write_text(json.dumps(dict(episodes=episodes, frames=10 * episodes)))
    (folder / "run" / "checkpoints" / "last").mkdir(parents=True)
    save_file({"train_step": torch.tensor(step)}, str(folder / "run" / "checkpoints" / "last" / "model.safetensors"))
    (folder / "planning").mkdir()
    (folder / "planning" / "planning_summary.json").write_text(
        json.dumps(dict(trials=200, SR=sr, CR=cr, TOR=1 - sr - cr)))


def test_stages_in_training_order_and_the_best_by_sr_then_fewer_collisions(tmp_path, capsys):
    _stage(tmp_path, "long", 10000, 30000, 0.79, 0.10)
    _stage(tmp_path, "dagger_1", 9000, 14000, 0.80, 0.10)
    _stage(tmp_path, "demos_10", 8000, 12000, 0.80, 0.08)
    _stage(tmp_path, "demos_2", 5000, 10000, 0.745, 0.15)
    _stage(tmp_path, "dagger_2", 9500, 16000, 0.70, 0.12)  # a round after a later chunk
    _stage(tmp_path, "demos_11", 10000, 18000, 0.70, 0.12)
    (tmp_path / "demos_3").mkdir()  # not evaluated yet: left out
    assert main(["learning-curve", str(tmp_path)]) == 0
    with open(tmp_path / "curve.csv", newline="") as f:
        rows = list(csv.DictReader(f))
    assert [r["stage"] for r in rows] == ["demos_2", "demos_10", "dagger_1", "dagger_2", "demos_11", "long"]
    assert [r["model_step"] for r in rows] == ["10000", "12000", "14000", "16000", "18000", "30000"]
    assert (tmp_path / "curve.png").stat().st_size > 0
    capsys.readouterr()
    assert main(["learning-curve", str(tmp_path), "--best"]) == 0
    assert capsys.readouterr().out.strip() == str(tmp_path / "demos_10" / "run" / "checkpoints" / "last")


def test_a_folder_without_an_evaluated_stage_is_an_error(tmp_path):
    assert main(["learning-curve", str(tmp_path)]) == 1
    assert main(["learning-curve", str(tmp_path / "missing")]) == 1
