"""Reading and validating RT-V3 batches (keys and shapes from ``rtv3_maniskill/features.py``).

Accepted layouts per key (B = batch, T = history, N points, M grasps):

* ``observation.state``: ``(B, T, 27)`` history, ``(B, 27)`` or ``(27,)`` single step;
  ``observation.state_history`` ``(B, T, 27)`` or as datasets store it, flat ``(B, T * 27)``;
* context, either the four keys ``observation.point_cloud`` ``(B[, T], N, 6)``,
  ``observation.point_cloud_mask`` ``(B[, T], N)``, ``observation.grasps`` ``(B[, T], M, 9)``,
  ``observation.grasps_mask`` ``(B[, T], M)`` (batch dim optional when B = 1; the cloud and the
  grasps also flat, ``(B[, T], N * 6)`` / ``(B[, T], M * 9)``, as datasets store them), or the packed
  ``observation.environment_state`` ``(B[, T], D)`` (``features.pack_context``). With a time
  axis only the last frame is used: the scene is static (paper Sec. IV).
"""

from __future__ import annotations

from dataclasses import dataclass, replace

import torch

from rtv3_maniskill import features
from rtv3_maniskill.policies.rtv3.constants import GRASP_SUBSET_MIN

ENV_STATE = features.ENV_STATE


@dataclass
class SceneContext:
    """Static scene context of one frame, world frame.

    Attributes:
        point_cloud: ``(B, N, 6)`` xyz (m) + rgb. point_mask: ``(B, N)`` bool, True = real point.
        grasps: ``(B, M, 9)`` position, quaternion wxyz, width, score. grasp_mask: ``(B, M)`` bool.
    """

    point_cloud: torch.Tensor
    point_mask: torch.Tensor
    grasps: torch.Tensor
    grasp_mask: torch.Tensor

    @property
    def batch_size(self) -> int:
        return self.point_cloud.shape[0]


@dataclass
class RTV3Inputs:
    """Everything the model reads: ``states (B, T, 27)`` history (last = current) + scene context."""

    states: torch.Tensor
    context: SceneContext


def check_finite(key: str, value: torch.Tensor) -> None:
    """Raise ``ValueError`` naming ``key`` if ``value`` holds NaN or inf."""
    if value.is_floating_point() and not bool(torch.isfinite(value).all()):
        raise ValueError(f"'{key}' contains NaN or inf values")


def _as_tensor(key: str, value) -> torch.Tensor:
    if not isinstance(value, torch.Tensor):
        raise TypeError(f"'{key}' must be a torch.Tensor, got {type(value).__name__}")
    return value


def _single_frame(key: str, value: torch.Tensor, frame_ndim: int, tail: tuple[int | None, ...]) -> torch.Tensor:
    """Bring ``value`` to ``(B, *frame_shape)``: add a batch dim or take the last time step."""
    if value.ndim == frame_ndim:
        value = value[None]
    elif value.ndim == frame_ndim + 2:
        value = value[:, -1]
    elif value.ndim != frame_ndim + 1:
        raise ValueError(
            f"'{key}' has shape {tuple(value.shape)}; expected (B, {', '.join(str(t or '?') for t in tail)}) "
            f"or with a time axis (B, T, ...)"
        )
    for dim, want in zip(value.shape[1:], tail):
        if want is not None and dim != want:
            raise ValueError(f"'{key}' has shape {tuple(value.shape)}; trailing dims must be {tail}")
    return value


def env_state_size_message(length: int, num_points: int, max_grasps: int) -> str:
    """Why a packed ``observation.environment_state`` of ``length`` values does not fit a policy
    with ``num_points`` / ``max_grasps``, naming the sizes and the ``lerobot-eval`` flags to fix."""
    expected = features.environment_state_dim(num_points, max_grasps)
    per_point, per_grasp = 7, features.GRASP_DIM + 1
    guesses = []
    if (length - max_grasps * per_grasp) % per_point == 0 and length > max_grasps * per_grasp:
        guesses.append(f"a point cloud of {(length - max_grasps * per_grasp) // per_point} points "
                       f"(--env.num_points) instead of the policy's num_points={num_points}")
    if (length - num_points * per_point) % per_grasp == 0 and length > num_points * per_point:
        guesses.append(f"a grasp set of {(length - num_points * per_point) // per_grasp} candidates "
                       f"(--env.max_grasps) instead of the policy's max_grasps={max_grasps}")
    hint = f"; the env sends {' or '.join(guesses)}" if guesses else ""
    return (
        f"'{ENV_STATE}' (the packed point cloud '{features.POINT_CLOUD}' + grasps '{features.GRASPS}') has "
        f"{length} values per frame but this policy reads {expected} = {num_points} points x {per_point} "
        f"+ {max_grasps} grasps x {per_grasp}{hint}. Make the env match the policy: "
        f"--env.num_points={num_points} --env.max_grasps={max_grasps}"
    )


def read_context(batch: dict[str, torch.Tensor], num_points: int, max_grasps: int) -> SceneContext:
    """Scene context of the current frame from either the four context keys or the packed vector."""
    if features.POINT_CLOUD in batch:
        missing = [k for k in (features.POINT_CLOUD_MASK, features.GRASPS, features.GRASPS_MASK) if k not in batch]
        if missing:
            raise KeyError(f"batch has '{features.POINT_CLOUD}' but lacks {missing}")
        # A dataset stores the point cloud and the grasps flat (features.STORED_FLAT): unflatten.
        pc = _as_tensor(features.POINT_CLOUD, batch[features.POINT_CLOUD])
        pc = _single_frame(features.POINT_CLOUD, features.unflatten(features.POINT_CLOUD, pc), 2, (None, 6))
        pc_mask = _single_frame(features.POINT_CLOUD_MASK,
                                _as_tensor(features.POINT_CLOUD_MASK, batch[features.POINT_CLOUD_MASK]), 1,
                                (pc.shape[1],))
        grasps = _as_tensor(features.GRASPS, batch[features.GRASPS])
        grasps = _single_frame(features.GRASPS, features.unflatten(features.GRASPS, grasps), 2,
                               (None, features.GRASP_DIM))
        g_mask = _single_frame(features.GRASPS_MASK, _as_tensor(features.GRASPS_MASK, batch[features.GRASPS_MASK]), 1,
                               (grasps.shape[1],))
        for key, value in ((features.POINT_CLOUD, pc), (features.POINT_CLOUD_MASK, pc_mask), (features.GRASPS, grasps),
                           (features.GRASPS_MASK, g_mask)):
            check_finite(key, value)
        sizes = {pc.shape[0], pc_mask.shape[0], grasps.shape[0], g_mask.shape[0]}
        if len(sizes) != 1:
            raise ValueError(f"context keys disagree on the batch size: {sorted(sizes)}")
    elif ENV_STATE in batch:
        dim = features.environment_state_dim(num_points, max_grasps)
        packed = _as_tensor(ENV_STATE, batch[ENV_STATE])
        if packed.ndim and packed.shape[-1] != dim:
            raise ValueError(env_state_size_message(int(packed.shape[-1]), num_points, max_grasps))
        packed = _single_frame(ENV_STATE, packed, 1, (dim,))
        check_finite(ENV_STATE, packed)
        unpacked = features.unpack_context(packed, num_points, max_grasps)
        pc, pc_mask = unpacked[features.POINT_CLOUD], unpacked[features.POINT_CLOUD_MASK]
        grasps, g_mask = unpacked[features.GRASPS], unpacked[features.GRASPS_MASK]
    else:
        raise KeyError(
            f"batch has no scene context: give '{features.POINT_CLOUD}', '{features.POINT_CLOUD_MASK}', "
            f"'{features.GRASPS}', "
            f"'{features.GRASPS_MASK}' or the packed '{ENV_STATE}'"
        )
    return SceneContext(pc, pc_mask > 0.5, grasps, g_mask > 0.5)


def read_states(batch: dict[str, torch.Tensor]) -> torch.Tensor:
    """The state history, checked: ``observation.state_history (B, T, 27)`` when the batch has it
    (datasets store it, flat ``(B, T * 27)``), else ``observation.state`` as given:
    ``(B, T, 27)``, ``(B, 27)`` or ``(27,)``."""
    key = features.STATE_HISTORY if features.STATE_HISTORY in batch else features.STATE
    if key not in batch:
        raise KeyError(f"batch lacks '{features.STATE}'")
    states = _as_tensor(key, batch[key])
    if key == features.STATE_HISTORY:  # stored flat (T * 27,) by datasets (features.STORED_FLAT)
        states = features.unflatten(key, states)
        if states.ndim == 2:
            states = states[None]
    if states.ndim not in (1, 2, 3) or states.shape[-1] != features.STATE_DIM:
        raise ValueError(
            f"'{features.STATE}' has shape {tuple(states.shape)}; expected (B, T, {features.STATE_DIM}), "
            f"(B, {features.STATE_DIM}) or ({features.STATE_DIM},)"
        )
    check_finite(features.STATE, states)
    quat_norm = states[..., features.EE_QUAT].norm(dim=-1)
    if bool((quat_norm < 1e-6).any()):
        raise ValueError(f"'{features.STATE}' holds a zero end-effector quaternion (entries 3:7)")
    return states


def read_actions(batch: dict[str, torch.Tensor], batch_size: int, horizon: int) -> tuple[torch.Tensor, torch.Tensor]:
    """``action (B, H, 6)`` and its validity ``(B, H)`` bool from ``action_is_pad`` (all valid if absent)."""
    if features.ACTION not in batch:
        raise KeyError(f"training batch lacks '{features.ACTION}'")
    actions = _as_tensor(features.ACTION, batch[features.ACTION])
    if tuple(actions.shape) != (batch_size, horizon, 6):
        raise ValueError(f"'{features.ACTION}' has shape {tuple(actions.shape)}; expected ({batch_size}, {horizon}, 6)")
    check_finite(features.ACTION, actions)
    pad = batch.get(f"{features.ACTION}_is_pad")
    if pad is None:
        return actions, torch.ones(batch_size, horizon, dtype=torch.bool, device=actions.device)
    if tuple(pad.shape) != (batch_size, horizon):
        raise ValueError(f"'{features.ACTION}_is_pad' has shape {tuple(pad.shape)}; expected ({batch_size}, {horizon})")
    return actions, ~pad.bool()


def subsample_grasps(context: SceneContext, target: torch.Tensor, min_keep: int = GRASP_SUBSET_MIN) -> SceneContext:
    """Training augmentation (docs/PAPER_DETAILS.md): keep a random subset of the valid grasps, always the target.

    The subset size is log-uniform in ``min_keep .. all``, ``floor(exp(U(log min_keep, log(all + 1))))``:
    small sets, where the target is nearly explicit, come far more often than with uniform sizes; they
    are the goal signal that teaches the model to read its grasp context.

    Args:
        target: ``(B,)`` or ``(B, 1)`` index of the target grasp; rows whose target is out of range or
            not a valid grasp are left unchanged.
        min_keep: smallest subset (fewer when a row has fewer valid grasps).
    """
    mask = context.grasp_mask
    batch, count = mask.shape
    target = target.reshape(batch).long().to(mask.device)
    in_range = (target >= 0) & (target < count)
    safe_target = target.clamp(0, max(count - 1, 0))
    usable = in_range & mask.gather(1, safe_target[:, None])[:, 0]
    n_valid = mask.sum(1)
    low = torch.minimum(n_valid, torch.full_like(n_valid, min_keep))
    u = torch.rand(batch, device=mask.device)
    log_low, log_high = low.clamp_min(1).float().log(), (n_valid + 1).float().log()
    keep_n = torch.exp(log_low + u * (log_high - log_low)).floor().long()
    keep_n = torch.minimum(torch.maximum(keep_n, low), n_valid)
    priority = torch.rand(batch, count, device=mask.device)
    priority = priority.masked_fill(~mask, 2.0)
    priority.scatter_(1, safe_target[:, None], -1.0)
    rank = priority.argsort(1).argsort(1)
    subset = (rank < keep_n[:, None]) & mask
    return replace(context, grasp_mask=torch.where(usable[:, None], subset, mask))
