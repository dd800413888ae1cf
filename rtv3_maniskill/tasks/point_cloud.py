"""Scene point clouds: crop to the workspace, voxel-downsample, resample to a fixed size.

The same processing serves the rendered depth camera (``obs_mode="pointcloud"``) and
the mesh-sampled cloud of the state observation modes, so both give one format:
``(N, 6)`` xyz (world frame, m) + rgb in [0, 1], with a ``(N,)`` mask (1 = real point).
The table top is cropped away (only points above ``z_min``), as are robot points.
"""

from __future__ import annotations

from collections.abc import Sequence

import numpy as np
import torch

from rtv3_maniskill.robot.scene_geometry import WORKSPACE_CENTER, WORKSPACE_HALF_SIZE, SceneGeometry

DEFAULT_VOXEL_SIZE = 0.3 / 40  # 7.5 mm (docs/PAPER_DETAILS.md)
TABLE_CROP_Z = 0.004
"""Points at or below this height (m) are the table surface and are dropped."""


def workspace_mask(xyz: torch.Tensor, z_min: float = TABLE_CROP_Z) -> torch.Tensor:
    """``(..., 3)`` world points -> ``(...)`` bool, inside the 30 cm workspace cube above the table."""
    center = torch.as_tensor(WORKSPACE_CENTER, dtype=xyz.dtype, device=xyz.device)
    rel = xyz - center
    inside = (rel[..., 0].abs() <= WORKSPACE_HALF_SIZE) & (rel[..., 1].abs() <= WORKSPACE_HALF_SIZE)
    return inside & (xyz[..., 2] > z_min) & (xyz[..., 2] <= 2 * WORKSPACE_HALF_SIZE)


def voxel_downsample(points: torch.Tensor, voxel_size: float) -> torch.Tensor:
    """Average the ``(P, C)`` points (xyz first) falling in each voxel -> ``(V, C)``."""
    if voxel_size <= 0:
        raise ValueError(f"voxel_size must be positive, got {voxel_size}")
    if points.shape[0] == 0:
        return points
    keys = torch.floor(points[:, :3] / voxel_size).long()
    _, inverse = torch.unique(keys, dim=0, return_inverse=True)
    count = int(inverse.max()) + 1
    sums = torch.zeros(count, points.shape[1], dtype=points.dtype, device=points.device).index_add_(0, inverse, points)
    counts = torch.zeros(count, dtype=points.dtype, device=points.device).index_add_(
        0, inverse, torch.ones_like(points[:, 0])
    )
    return sums / counts[:, None]


def resample(points: torch.Tensor, num_points: int,
             generator: torch.Generator | None = None) -> tuple[torch.Tensor, torch.Tensor]:
    """Pick ``num_points`` of ``(P, C)`` points without replacement, or zero-pad.

    Returns ``(num_points, C)`` points and a ``(num_points,)`` float mask.
    """
    if num_points <= 0:
        raise ValueError(f"num_points must be positive, got {num_points}")
    out = torch.zeros(num_points, points.shape[1], dtype=points.dtype, device=points.device)
    mask = torch.zeros(num_points, dtype=points.dtype, device=points.device)
    count = points.shape[0]
    if count > num_points:
        idx = torch.randperm(count, generator=generator, device="cpu")[:num_points].to(points.device)
        out[:] = points[idx]
        mask[:] = 1
    else:
        out[:count] = points
        mask[:count] = 1
    return out, mask


def process_point_cloud(
    xyz: torch.Tensor,
    rgb: torch.Tensor,
    keep: torch.Tensor,
    num_points: int,
    voxel_size: float = DEFAULT_VOXEL_SIZE,
    generators: Sequence[torch.Generator | None] | None = None,
) -> tuple[torch.Tensor, torch.Tensor]:
    """Batched: ``xyz (B, P, 3)`` world, ``rgb (B, P, 3)`` in [0, 1], ``keep (B, P)`` bool.

    Crops to the workspace, voxel-downsamples and resamples each cloud; cloud ``b`` draws its
    resampling from ``generators[b]`` (None: torch's global generator, not reproducible).
    Returns ``(B, num_points, 6)`` and a ``(B, num_points)`` mask.
    """
    if generators is not None and len(generators) != xyz.shape[0]:
        raise ValueError(f"need one generator per cloud ({xyz.shape[0]}), got {len(generators)}")
    keep = keep & workspace_mask(xyz)
    clouds, masks = [], []
    for b in range(xyz.shape[0]):
        points = torch.cat([xyz[b][keep[b]], rgb[b][keep[b]]], -1).float()
        generator = generators[b] if generators is not None else None
        cloud, mask = resample(voxel_downsample(points, voxel_size), num_points, generator)
        clouds.append(cloud)
        masks.append(mask)
    return torch.stack(clouds), torch.stack(masks)


def sample_scene_surface(scene: SceneGeometry, rng: np.random.Generator, points_per_m2: float = 2.0e5) -> np.ndarray:
    """Surface samples of every object (world frame) with its colour: ``(P, 6)`` xyz + rgb.

    Stands in for the depth camera when nothing is rendered (state observation modes).
    """
    chunks = []
    for obj, pose in zip(scene.objects, scene.object_poses):
        mesh = obj.collision_mesh()
        mesh.apply_transform(pose)
        count = max(64, int(mesh.area * points_per_m2))
        seed = int(rng.integers(2**31))
        import trimesh

        points, _ = trimesh.sample.sample_surface(mesh, count, seed=seed)
        color = np.broadcast_to(np.asarray(obj.color[:3]), points.shape)
        chunks.append(np.concatenate([points, color], 1))
    if not chunks:
        return np.zeros((0, 6))
    return np.concatenate(chunks, 0)
