"""Loading RT-V3 checkpoints: the one loader every command, benchmark and script uses.

A checkpoint is a local ``pretrained_model`` folder (``config.json`` + ``model.safetensors``) or a
Hugging Face Hub repo id (``owner/name``), resolved through ``huggingface_hub`` into its cache, so
a policy pushed with ``push_to_hub`` works everywhere a folder does, offline too once cached
(``HF_HUB_OFFLINE=1``).
"""

from __future__ import annotations

import re
from pathlib import Path
from typing import Any

SHIPPED_CHECKPOINT = Path(__file__).resolve().parents[2] / "checkpoints" / "rtv3_grasp_clutter"
"""The checkpoint shipped with the package (``config.json`` + ``model.safetensors``)."""
CHECKPOINT_FILES = ("config.json", "model.safetensors")
_REPO_ID = re.compile(r"[A-Za-z0-9][\w.-]*/[\w.-]+")


class CheckpointError(FileNotFoundError, ValueError):
    """A checkpoint cannot be found or read; the message names the file or repo and what to do (caught
    as ``FileNotFoundError`` or ``ValueError``)."""


def _from_hub(repo_id: str) -> Path:
    # Lazy: only a Hub repo id needs the Hub client (a PyTorch-only machine may lack it).
    from huggingface_hub import snapshot_download
    from huggingface_hub.errors import (
        HfHubHTTPError,
        LocalEntryNotFoundError,
        RepositoryNotFoundError,
    )

    try:
        return Path(snapshot_download(repo_id, allow_patterns=[*CHECKPOINT_FILES, "*.md", "*.json"]))
    except RepositoryNotFoundError:
        raise CheckpointError(f"--policy.path {repo_id!r} is neither a local folder nor a model repo on the Hugging "
                              "Face Hub (check the name, or log in with `hf auth login` for a private repo)") from None
    except LocalEntryNotFoundError:
        raise CheckpointError(f"--policy.path {repo_id!r} is not a local folder and is not in the Hugging Face cache, "
                              "and the Hub cannot be reached (offline, or HF_HUB_OFFLINE=1): download it once where "
                              f"there is a network (`hf download {repo_id}`) or pass a local pretrained_model "
                              "folder") from None
    except (HfHubHTTPError, OSError) as err:
        raise CheckpointError(f"--policy.path {repo_id!r}: the Hub download failed ({type(err).__name__}: "
                              f"{str(err).splitlines()[0] if str(err) else ''})") from None


def resolve_checkpoint(path: str | Path | None = None) -> Path:
    """The local folder of a checkpoint: ``path`` itself, the shipped one (None), or the cached
    snapshot of a Hub repo id. Raises :class:`CheckpointError` (naming what is missing) otherwise."""
    if path is None:
        folder = SHIPPED_CHECKPOINT
    else:
        folder = Path(path).expanduser()
        if not folder.exists() and _REPO_ID.fullmatch(str(path)):
            folder = _from_hub(str(path))
    where = "the shipped checkpoint" if path is None else "--policy.path"
    if not folder.is_dir():
        raise CheckpointError(f"no RT-V3 checkpoint at {folder} ({where}: no such folder). Train one with "
                              "`lerobot-train --policy.type=rtv3 ...` and pass its pretrained_model folder (or a Hub "
                              "repo id) with --policy.path")
    missing = [name for name in CHECKPOINT_FILES if not (folder / name).is_file()]
    if missing:
        raise CheckpointError(
            f"no RT-V3 checkpoint at {folder} ({where}; missing {', '.join(missing)}). Train one with "
            "`lerobot-train --policy.type=rtv3 ...` and pass its pretrained_model folder with --policy.path DIR.")
    return folder


def _first_line(err: BaseException) -> str:
    text = str(err).strip()
    return f"{type(err).__name__}: {text.splitlines()[0][:300] if text else ''}"


def load_policy(path: str | Path | None = None, device: str = "cpu") -> Any:
    """An ``RTV3Policy`` from a checkpoint, in eval mode on ``device``.

    Args:
        path: a ``pretrained_model`` folder written by ``lerobot-train`` or
            ``RTV3Policy.save_pretrained``, or a Hub repo id; None = :data:`SHIPPED_CHECKPOINT`.
        device: ``"cpu"`` (default) or e.g. ``"cuda"``.
    Raises:
        CheckpointError: no checkpoint there, or its ``config.json`` / ``model.safetensors`` cannot be
            read (the message names the file).
    """
    folder = resolve_checkpoint(path)
    # Lazy: these load LeRobot, which resolving a checkpoint (and training without LeRobot) must not.
    from lerobot.configs.policies import PreTrainedConfig

    from rtv3_maniskill.policies.rtv3.configuration_rtv3 import RTV3Config
    from rtv3_maniskill.policies.rtv3.modeling_rtv3 import RTV3Policy

    try:
        config = PreTrainedConfig.from_pretrained(str(folder))
    except Exception as err:  # noqa: BLE001  (draccus and json errors of every kind)
        raise CheckpointError(f"{folder / 'config.json'} is not a readable RT-V3 config ({_first_line(err)}); "
                              "it must be the config.json written with the checkpoint's weights") from None
    if not isinstance(config, RTV3Config):
        raise CheckpointError(f"{folder / 'config.json'} is a {type(config).__name__}, not an RT-V3 config "
                              "(type 'rtv3')")
    try:
        policy = RTV3Policy.from_pretrained(str(folder), config=config)
    except Exception as err:  # noqa: BLE001  (safetensors header errors, shape mismatches)
        raise CheckpointError(f"{folder / 'model.safetensors'} cannot be loaded ({_first_line(err)}); it is "
                              "truncated, corrupt or made for another config.json: copy the checkpoint again") from None
    policy.config.device = device
    return policy.to(device).eval()
