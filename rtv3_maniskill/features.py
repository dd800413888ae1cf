"""Names, shapes and frames of everything the dataset stores and the policy reads.

One schema for the ManiSkill task's observations, the LeRobot dataset and the RT-V3
policy. All arrays float32 unless noted. World frame = the ManiSkill scene frame
(z up, table top at z = 0). Twists are body-frame ``[v (m/s), w (rad/s)]``.
"""

from __future__ import annotations

import torch

FPS = 20
"""Control and logging rate (NOTES.md): dt = 0.05 s."""
DT = 1.0 / FPS
HISTORY_STEPS = 8
"""T: past steps including the current one."""
HORIZON_STEPS = 12
"""H: future steps predicted."""

DEFAULT_NUM_POINTS = 2048
DEFAULT_MAX_GRASPS = 64

STATE = "observation.state"
"""``(27,)`` [ee position (3, world, m), ee quaternion wxyz (4, world),
ee body twist (6), arm joint positions (7, rad), arm joint velocities (7, rad/s)]."""
STATE_DIM = 27
STATE_HISTORY = "observation.state_history"
"""``(T, 27)`` the last T states (oldest first, the current one last), the first state repeated
before the episode start. Stored by the dataset so that training reads one row per sample
instead of a T-frame window of every ``observation.*`` key (point clouds included)."""
POINT_CLOUD = "observation.point_cloud"
"""``(N, 6)`` xyz (world, m) + rgb in [0, 1]; rows where the mask is 0 are zeros."""
POINT_CLOUD_MASK = "observation.point_cloud_mask"
"""``(N,)`` 1.0 for a real point, 0.0 for padding."""
GRASPS = "observation.grasps"
"""``(M, 9)`` grasp candidates: TCP position (3, world, m), quaternion wxyz (4, world),
gripper width (1, m), score (1, in [0, 1]). Rows where the mask is 0 are zeros."""
GRASP_DIM = 9
GRASPS_MASK = "observation.grasps_mask"
"""``(M,)`` 1.0 for a real candidate, 0.0 for padding."""
ACTION = "action"
"""``(6,)`` end-effector body twist [v, w] realised over this step: log(T_t^-1 T_{t+1}) / dt."""
TARGET_GRASP = "target_grasp_index"
"""``(1,)`` int64 index into the grasp set of the episode's target (privileged)."""

# Slices of observation.state
EE_POS = slice(0, 3)
EE_QUAT = slice(3, 7)
EE_TWIST = slice(7, 13)
ARM_QPOS = slice(13, 20)
ARM_QVEL = slice(20, 27)


def environment_state_dim(num_points: int, max_grasps: int) -> int:
    """Length of the flat ``observation.environment_state`` vector (see :func:`pack_context`)."""
    return num_points * 7 + max_grasps * (GRASP_DIM + 1)


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
