"""Loading RT-V3 checkpoints: the one loader every command, benchmark and script uses."""

from __future__ import annotations

from pathlib import Path
from typing import Any

SHIPPED_CHECKPOINT = Path(__file__).resolve().parents[2] / "checkpoints" / "rtv3_grasp_clutter"
"""The checkpoint shipped with the package (``config.json`` + ``model.safetensors``)."""


def load_policy(path: str | Path | None = None, device: str = "cpu") -> Any:
    """An ``RTV3Policy`` from a checkpoint folder, in eval mode on ``device``.

    Args:
        path: a ``pretrained_model`` folder written by ``lerobot-train`` or
            ``RTV3Policy.save_pretrained``; None = :data:`SHIPPED_CHECKPOINT`.
        device: ``"cpu"`` (default) or e.g. ``"cuda"``.
    Raises:
        FileNotFoundError: no checkpoint there; the message names the missing files and says
            how to get one.
    """
    folder = Path(path).expanduser() if path is not None else SHIPPED_CHECKPOINT
    missing = [name for name in ("config.json", "model.safetensors") if not (folder / name).is_file()]
    if missing:
        where = "the shipped checkpoint" if path is None else "--policy.path"
        raise FileNotFoundError(
            f"no RT-V3 checkpoint at {folder} ({where}; missing {', '.join(missing)}). Train one with "
            "`lerobot-train --policy.type=rtv3 ...` and pass its pretrained_model folder with --policy.path DIR.")
    from rtv3_maniskill.policies.rtv3.modeling_rtv3 import RTV3Policy  # loads LeRobot (~6 s)

    policy = RTV3Policy.from_pretrained(str(folder))
    policy.config.device = device
    return policy.to(device).eval()
