"""Names, shapes and frames of everything the dataset stores and the policy reads.

One schema for the ManiSkill task's observations, the LeRobot dataset and the RT-V3
policy. All arrays float32 unless noted. World frame = the ManiSkill scene frame
(z up, table top at z = 0). Twists are body-frame ``[v (m/s), w (rad/s)]``.
"""

from __future__ import annotations

import numpy as np
import torch

from rtv3_maniskill import se3

FPS = 20
"""Control and logging rate (docs/PAPER_DETAILS.md): dt = 0.05 s."""
DT = 1.0 / FPS
HISTORY_STEPS = 8
"""T: past steps including the current one."""
HORIZON_STEPS = 12
"""H: future steps predicted."""

PREGRASP_DISTANCE = 0.05
"""m: a pre-grasp is its grasp moved this far back along the approach (tool z) axis."""
DEFAULT_NUM_POINTS = 2048
DEFAULT_MAX_GRASPS = 64

STATE = "observation.state"
"""``(27,)`` [ee position (3, world, m), ee quaternion wxyz (4, world),
ee body twist (6), arm joint positions (7, rad), arm joint velocities (7, rad/s)]."""
STATE_DIM = 27
STATE_HISTORY = "observation.state_history"
"""``(T, 27)`` (stored flat, see :data:`STORED_FLAT`) the last T states (oldest first, the current one last),
the first state repeated before the episode start. Stored by the dataset so that training reads one row per sample
instead of a T-frame window of every ``observation.*`` key (point clouds included)."""
POINT_CLOUD = "observation.point_cloud"
"""``(N, 6)`` (stored flat, see :data:`STORED_FLAT`) xyz (world, m) + rgb in [0, 1];
rows where the mask is 0 are zeros."""
POINT_CLOUD_MASK = "observation.point_cloud_mask"
"""``(N,)`` 1.0 for a real point, 0.0 for padding."""
GRASPS = "observation.grasps"
"""``(M, 9)`` (stored flat, see :data:`STORED_FLAT`) grasp candidates: TCP position (3, world, m),
quaternion wxyz (4, world), gripper width (1, m), score (1, in [0, 1]). Rows where the mask is 0 are zeros."""
GRASP_DIM = 9
GRASPS_MASK = "observation.grasps_mask"
"""``(M,)`` 1.0 for a real candidate, 0.0 for padding."""
ACTION = "action"
"""``(6,)`` end-effector body twist [v, w] realised over this step: log(T_t^-1 T_{t+1}) / dt."""
GRIPPER_OPEN = 1.0
"""Normalised gripper action (the last entry of ``action``) that holds the Panda's fingers open (0.04 m)."""
GRIPPER_CLOSED = -1.0
"""Normalised gripper action that closes the fingers."""
REPO_ID = "local/rtv3_grasp_clutter"
"""Repository id of the LeRobot datasets this project writes (``--push-to-hub`` gives a real one)."""
ENV_STATE = "observation.environment_state"
"""LeRobot's environment-state key. In a dataset (``rtv3 generate``, ``rtv3 dagger``, ``teleop --record``) it
holds the scene summary ``(scene_summary_dim(M),)`` of :func:`scene_summary`, which stock LeRobot policies
(``--policy.type=diffusion``, ``act``) read; in the ``lerobot-eval`` env it holds either that summary or, for
RT-V3, the whole packed context (:func:`pack_context`), as ``--env.environment_state`` says."""
SUMMARY_GRASP_CHANNELS = ("x", "y", "z", "ax", "ay", "az", "cx", "cy", "cz", "width", "score", "valid")
"""Per grasp candidate in :func:`scene_summary`: TCP position (world, m), approach axis (tool z, world), closing
axis (tool y, world), gripper width (m), score, and 1.0 for a real candidate (0.0: padding, all zeros). The two
axes stand for the orientation without a quaternion's sign ambiguity."""
HEIGHT_MAP_CELLS = 8
"""The scene summary's height map has ``HEIGHT_MAP_CELLS x HEIGHT_MAP_CELLS`` cells."""
HEIGHT_MAP_CENTER = (-0.05, 0.0)
"""m, world xy: centre of the height map, the centre of the 30 cm workspace cube the point cloud is cropped to."""
HEIGHT_MAP_HALF_SIZE = 0.15
"""m: half the side of the height map (the workspace cube's half size): cells of 3.75 cm."""
TARGET_GRASP = "target_grasp_index"
"""``(1,)`` int64 index into the grasp set of the episode's target (privileged)."""

STORED_FLAT = {STATE_HISTORY: STATE_DIM, POINT_CLOUD: 6, GRASPS: GRASP_DIM}
"""Row width of the features that are 2-D ``(rows, width)`` but stored flat ``(rows * width,)``
(row-major) in the LeRobot dataset: LeRobot 0.4.4's dataset tools (``lerobot-edit-dataset``
delete_episodes / split / merge / modify_tasks) copy data through pandas, which cannot handle
the ``Array2D`` columns of 2-D features. Readers bring them back with :func:`unflatten`."""


STATE_NAMES = (
    [f"ee_pos_{a}" for a in "xyz"] + [f"ee_quat_{a}" for a in "wxyz"]
    + [f"ee_twist_{a}" for a in ("vx", "vy", "vz", "wx", "wy", "wz")]
    + [f"q{i}" for i in range(1, 8)] + [f"dq{i}" for i in range(1, 8)]
)
"""Channel names of :data:`STATE` (and of each row of :data:`STATE_HISTORY`)."""
FLAT_LAYOUTS = {
    STATE_HISTORY: ("step", STATE_NAMES),
    POINT_CLOUD: ("point", ["x", "y", "z", "r", "g", "b"]),
    GRASPS: ("grasp", ["x", "y", "z", "qw", "qx", "qy", "qz", "width", "score"]),
}
"""Per :data:`STORED_FLAT` feature: what a row is, and the names of its channels."""


def flat_names(key: str, rows: int) -> dict:
    """The ``names`` a :data:`STORED_FLAT` feature gets in a LeRobot ``info.json``: its per-item layout,
    ``{"layout": "(rows, width) row-major, stored flat", "rows": [item, rows], "channels": [...]}``, so a
    LeRobot user can read the flat vector without this package (:func:`unflatten_batch` does it here)."""
    item, channels = FLAT_LAYOUTS[key]
    return {"layout": f"({rows}, {len(channels)}) row-major, stored flat", "rows": [item, int(rows)],
            "channels": list(channels)}


def stored_shape(key: str, rows: int) -> tuple[int]:
    """Dataset shape of a :data:`STORED_FLAT` feature with ``rows`` rows: ``(rows * width,)``."""
    return (rows * STORED_FLAT[key],)


def rows_of(key: str, shape) -> int:
    """Row count (N points, M grasps, T steps) of a :data:`STORED_FLAT` feature from its
    dataset/policy feature shape, stored flat ``(rows * width,)`` or laid out ``(rows, width)``."""
    shape, width = tuple(int(s) for s in shape), STORED_FLAT[key]
    if len(shape) == 2 and shape[1] == width:
        return shape[0]
    if len(shape) == 1 and shape[0] % width == 0:
        return shape[0] // width
    raise ValueError(f"'{key}' has shape {shape}; expected (rows, {width}) or flat (rows * {width},)")


def unflatten(key: str, value):
    """A :data:`STORED_FLAT` feature as stored ``(..., rows * width)`` -> ``(..., rows, width)``
    (numpy or torch, any leading dims); a value whose last dim already is the row width and
    that has a rows dim passes through unchanged (so both layouts are accepted)."""
    width = STORED_FLAT[key]
    if value.ndim >= 2 and value.shape[-1] == width:
        return value
    if value.ndim < 1 or value.shape[-1] % width:
        raise ValueError(
            f"'{key}' has shape {tuple(value.shape)}; expected (..., rows, {width}) or flat (..., rows * {width})"
        )
    return value.reshape(*value.shape[:-1], value.shape[-1] // width, width)


def unflatten_batch(batch: dict) -> dict:
    """A LeRobot sample or batch with every :data:`STORED_FLAT` feature it holds brought back to
    ``(..., rows, width)`` (see :func:`unflatten`); other keys are passed through. A new dict."""
    return {key: unflatten(key, value) if key in STORED_FLAT else value for key, value in batch.items()}


# Slices of observation.state
EE_POS = slice(0, 3)
EE_QUAT = slice(3, 7)
EE_TWIST = slice(7, 13)
ARM_QPOS = slice(13, 20)
ARM_QVEL = slice(20, 27)


def environment_state_dim(num_points: int, max_grasps: int) -> int:
    """Length of the flat ``observation.environment_state`` vector (see :func:`pack_context`)."""
    return num_points * 7 + max_grasps * (GRASP_DIM + 1)


def scene_summary_dim(max_grasps: int) -> int:
    """Length of the scene summary :func:`scene_summary`: ``max_grasps * 12 + HEIGHT_MAP_CELLS ** 2``."""
    return max_grasps * len(SUMMARY_GRASP_CHANNELS) + HEIGHT_MAP_CELLS**2


def scene_summary_names(max_grasps: int) -> list[str]:
    """Channel names of :func:`scene_summary` (``grasp07_ax``, ..., ``height_r3_c5``), as a dataset's ``names``."""
    grasps = [f"grasp{i:02d}_{c}" for i in range(max_grasps) for c in SUMMARY_GRASP_CHANNELS]
    cells = range(HEIGHT_MAP_CELLS)
    return grasps + [f"height_r{r}_c{c}" for r in cells for c in cells]


def _float_tensor(value) -> torch.Tensor:
    """A float32 tensor of ``value`` (numpy arrays, read-only ones included, are copied)."""
    if isinstance(value, torch.Tensor):
        return value.float()
    return torch.from_numpy(np.array(value, dtype=np.float32))


def scene_summary(point_cloud, point_cloud_mask, grasps, grasps_mask) -> torch.Tensor:
    """The static scene as one fixed-size vector ``(..., scene_summary_dim(M))`` float32, for stock policies.

    Args:
        point_cloud: ``(..., N, 6)`` or flat ``(..., N * 6)``, world xyz (m) + rgb; its mask ``(..., N)``.
        grasps: ``(..., M, 9)`` or flat ``(..., M * 9)`` (:data:`GRASPS`); its mask ``(..., M)``.

    Layout: M grasp rows of :data:`SUMMARY_GRASP_CHANNELS` (world frame, padding rows zero), then the height
    map, row-major ``(HEIGHT_MAP_CELLS, HEIGHT_MAP_CELLS)``, rows along world x (away from the robot), columns
    along world y: the highest point (m above the table top) of the cloud in each cell, 0 where the cell holds
    none. numpy or torch in; a torch tensor out.
    """
    pc = unflatten(POINT_CLOUD, _float_tensor(point_cloud))
    pc_mask = _float_tensor(point_cloud_mask) > 0.5
    g = unflatten(GRASPS, _float_tensor(grasps))
    g_mask = _float_tensor(grasps_mask) > 0.5
    if pc_mask.shape != pc.shape[:-1] or g_mask.shape != g.shape[:-1]:
        raise ValueError(f"scene_summary: masks {tuple(pc_mask.shape)}, {tuple(g_mask.shape)} do not fit the "
                         f"point cloud {tuple(pc.shape)} and grasps {tuple(g.shape)}")
    identity = torch.tensor([1.0, 0.0, 0.0, 0.0])
    rot = se3.quat_to_matrix(torch.where(g_mask[..., None], g[..., 3:7], identity))
    rows = torch.cat([g[..., :3], rot[..., :, 2], rot[..., :, 1], g[..., 7:9], torch.ones_like(g[..., :1])], -1)
    rows = rows * g_mask[..., None]

    cells = HEIGHT_MAP_CELLS
    centre = torch.tensor(HEIGHT_MAP_CENTER)
    ij = torch.floor((pc[..., :2] - centre + HEIGHT_MAP_HALF_SIZE) / (2 * HEIGHT_MAP_HALF_SIZE) * cells).long()
    inside = pc_mask & (ij >= 0).all(-1) & (ij < cells).all(-1)
    index = (ij[..., 0] * cells + ij[..., 1]).clamp(0, cells * cells - 1)
    height = torch.where(inside, pc[..., 2].clamp_min(0.0), torch.zeros(()))
    lead = pc.shape[:-2]
    height_map = torch.zeros(*lead, cells * cells).scatter_reduce(-1, index, height, "amax", include_self=True)
    return torch.cat([rows.reshape(*lead, -1), height_map], -1)


CONTEXT_MODES = ("target", "all")
"""Which grasp candidates a policy is shown: only the episode's target (the paper's planning protocol:
the target poses are the context) or every candidate."""


def context_mask(grasps_mask: torch.Tensor, target: int, context: str) -> torch.Tensor:
    """``observation.grasps_mask (B, M)`` the policy sees: only ``target`` (``"target"``) or unchanged (``"all"``)."""
    if context not in CONTEXT_MODES:
        raise ValueError(f"unknown context mode {context!r}; expected one of {CONTEXT_MODES}")
    if context == "all":
        return grasps_mask
    if not 0 <= target < grasps_mask.shape[-1] or not bool(grasps_mask[..., target].gt(0.5).all()):
        raise ValueError(f"target grasp {target} is not a valid candidate of the scene")
    out = torch.zeros_like(grasps_mask)
    out[..., target] = 1.0
    return out


def pack_context(
    point_cloud: torch.Tensor, point_cloud_mask: torch.Tensor, grasps: torch.Tensor, grasps_mask: torch.Tensor
) -> torch.Tensor:
    """Flatten the static scene context into one vector ``(..., environment_state_dim)``.

    ``lerobot-eval`` keeps only a few gym observation keys (``environment_state`` among
    them), so the evaluation env hands the point cloud and grasps over in this form.
    Layout: point cloud ``(N*6)``, its mask ``(N)``, grasps ``(M*9)``, their mask ``(M)``.
    """
    lead = point_cloud.shape[:-2]
    return torch.cat(
        [
            point_cloud.reshape(*lead, -1),
            point_cloud_mask.reshape(*lead, -1).to(point_cloud.dtype),
            grasps.reshape(*lead, -1),
            grasps_mask.reshape(*lead, -1).to(point_cloud.dtype),
        ],
        -1,
    )


def unpack_context(packed: torch.Tensor, num_points: int, max_grasps: int) -> dict[str, torch.Tensor]:
    """Inverse of :func:`pack_context`: returns the four context tensors by feature name."""
    expected = environment_state_dim(num_points, max_grasps)
    if packed.shape[-1] != expected:
        raise ValueError(
            f"environment_state has length {packed.shape[-1]}, expected {expected} "
            f"for num_points={num_points}, max_grasps={max_grasps}"
        )
    lead = packed.shape[:-1]
    n6, n, m9 = num_points * 6, num_points, max_grasps * GRASP_DIM
    return {
        POINT_CLOUD: packed[..., :n6].reshape(*lead, num_points, 6),
        POINT_CLOUD_MASK: packed[..., n6 : n6 + n],
        GRASPS: packed[..., n6 + n : n6 + n + m9].reshape(*lead, max_grasps, GRASP_DIM),
        GRASPS_MASK: packed[..., n6 + n + m9 :],
    }


def observation_from_env(obs: dict) -> dict[str, torch.Tensor]:
    """``GraspClutter-v1`` observation (``state_dict`` or ``pointcloud`` mode) -> policy inputs.

    Returns the dataset's ``observation.*`` keys, batched ``(B, ...)``, float32.
    """
    extra, agent = obs["extra"], obs["agent"]
    state = torch.cat([extra["tcp_pose"], extra["tcp_twist"], agent["qpos"][..., :7], agent["qvel"][..., :7]], -1)
    return {
        STATE: state.float(),
        POINT_CLOUD: extra["point_cloud"].float(),
        POINT_CLOUD_MASK: extra["point_cloud_mask"].float(),
        GRASPS: extra["grasps"].float(),
        GRASPS_MASK: extra["grasps_mask"].float(),
    }


def pregrasp_poses(grasp_poses: torch.Tensor) -> torch.Tensor:
    """Grasp poses ``(..., 4, 4)`` moved ``PREGRASP_DISTANCE`` back along their own z (approach) axis."""
    return se3.translate_along_z(grasp_poses, -PREGRASP_DISTANCE)
