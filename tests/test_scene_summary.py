"""The scene summary (``observation.environment_state`` in datasets): its layout, as features.py documents it."""

from __future__ import annotations

import math

import numpy as np
import pytest
import torch

from rtv3_maniskill import features, se3
from rtv3_maniskill.robot.scene_geometry import WORKSPACE_CENTER, WORKSPACE_HALF_SIZE


def _scene(num_points: int = 8, max_grasps: int = 4):
    pc = torch.zeros(num_points, 6)
    pc_mask = torch.zeros(num_points)
    grasps = torch.zeros(max_grasps, features.GRASP_DIM)
    g_mask = torch.zeros(max_grasps)
    return pc, pc_mask, grasps, g_mask


def test_grasp_rows_hold_position_axes_width_score_and_validity():
    pc, pc_mask, grasps, g_mask = _scene()
    rot = se3.so3_exp(torch.tensor([0.0, 0.0, math.pi / 2]))  # tool y -> world -x, tool z stays world z
    grasps[1] = torch.cat([torch.tensor([0.1, -0.2, 0.05]), se3.matrix_to_quat(rot), torch.tensor([0.03, 0.7])])
    g_mask[1] = 1.0
    out = features.scene_summary(pc, pc_mask, grasps, g_mask)
    assert out.shape == (features.scene_summary_dim(4),) == (4 * 12 + 64,)
    rows = out[: 4 * 12].reshape(4, 12)
    names = features.SUMMARY_GRASP_CHANNELS
    row = dict(zip(names, rows[1].tolist()))
    assert np.allclose([row["x"], row["y"], row["z"]], [0.1, -0.2, 0.05], atol=1e-6)
    assert np.allclose([row["ax"], row["ay"], row["az"]], [0, 0, 1], atol=1e-6)
    assert np.allclose([row["cx"], row["cy"], row["cz"]], [-1, 0, 0], atol=1e-6)
    assert row["width"] == pytest.approx(0.03) and row["score"] == pytest.approx(0.7) and row["valid"] == 1.0
    assert torch.all(rows[[0, 2, 3]] == 0), "padding rows are zero (and finite)"
    assert len(features.scene_summary_names(4)) == len(out)


def test_height_map_keeps_the_highest_real_point_per_cell():
    pc, pc_mask, grasps, g_mask = _scene()
    cell = 2 * features.HEIGHT_MAP_HALF_SIZE / features.HEIGHT_MAP_CELLS
    corner = torch.tensor(features.HEIGHT_MAP_CENTER) - features.HEIGHT_MAP_HALF_SIZE
    at = lambda r, c: corner + cell * torch.tensor([r + 0.5, c + 0.5])  # noqa: E731
    pc[0, :3] = torch.cat([at(2, 5), torch.tensor([0.10])])
    pc[1, :3] = torch.cat([at(2, 5), torch.tensor([0.20])])
    pc[2, :3] = torch.cat([at(7, 0), torch.tensor([0.05])])
    pc[3, :3] = torch.cat([at(0, 0), torch.tensor([0.30])])  # padding: ignored
    pc[4, :3] = torch.tensor([1.0, 1.0, 0.25])  # outside the map: ignored
    pc_mask[[0, 1, 2, 4]] = 1.0
    height = features.scene_summary(pc.reshape(-1), pc_mask, grasps.reshape(-1), g_mask)[4 * 12:]
    grid = height.reshape(features.HEIGHT_MAP_CELLS, features.HEIGHT_MAP_CELLS)
    assert grid[2, 5] == pytest.approx(0.20) and grid[7, 0] == pytest.approx(0.05)
    assert grid.sum() == pytest.approx(0.25)


def test_height_map_covers_the_cropped_workspace():
    assert np.allclose(features.HEIGHT_MAP_CENTER, WORKSPACE_CENTER[:2])
    assert features.HEIGHT_MAP_HALF_SIZE == pytest.approx(WORKSPACE_HALF_SIZE)


def test_batched_and_bad_shapes():
    pc, pc_mask, grasps, g_mask = _scene()
    batch = features.scene_summary(pc[None].repeat(3, 1, 1), pc_mask[None].repeat(3, 1), grasps[None].repeat(3, 1, 1),
                                   g_mask[None].repeat(3, 1))
    assert batch.shape == (3, features.scene_summary_dim(4))
    with pytest.raises(ValueError, match="masks"):
        features.scene_summary(pc, pc_mask[:5], grasps, g_mask)
