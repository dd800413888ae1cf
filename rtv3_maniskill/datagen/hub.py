"""Sharing a dataset this project made on the Hugging Face Hub (``--push-to-hub REPO_ID``).

The push is LeRobot's (``LeRobotDataset.push_to_hub``: the dataset folder, its card and the codebase
version tag); the card says what the data is: the task, the command that made it and the layout of
every feature (the flattened ones included, see ``rtv3_maniskill.features.FLAT_LAYOUTS``).
"""

from __future__ import annotations

import re
import shlex
import sys
from pathlib import Path

from rtv3_maniskill import ENV_ID

_REPO_ID = re.compile(r"[A-Za-z0-9][\w.-]*/[\w.-]+")


class HubPushError(RuntimeError):
    """The push failed; the message says why and that the local dataset is kept."""


def check_repo_id(repo_id: str) -> str:
    """``repo_id`` if it has the Hub's ``owner/name`` form; a ``ValueError`` naming it otherwise."""
    if not _REPO_ID.fullmatch(str(repo_id)):
        raise ValueError(f"--push-to-hub {repo_id!r} is not a Hub repo id (expected OWNER/NAME)")
    return str(repo_id)


def dataset_description(kind: str, command: str | None = None) -> str:
    """The card's description: what the episodes are, the ManiSkill task, the command that made them."""
    command = command or shlex.join(["rtv3", *sys.argv[1:]])
    return (
        f"{kind} in the ManiSkill3 task `{ENV_ID}` (a Franka Panda reaching a grasp candidate's pre-grasp in a "
        "cluttered table scene), made with rtv3-maniskill, the open implementation of Robot Trajectron V3 "
        "(RT-V3) shared control.\n\n"
        f"Made with:\n\n```bash\n{command}\n```\n\n"
        "Flattened features (`observation.point_cloud`, `observation.grasps`, `observation.state_history`) "
        "are row-major; their `names` in `meta/info.json` give the rows and channels, and "
        "`rtv3_maniskill.features.unflatten_batch` restores them."
    )


def push_dataset(root: Path, repo_id: str, kind: str, command: str | None = None, private: bool = False) -> str:
    """Push the LeRobot dataset in ``root`` to the Hub dataset repo ``repo_id``; returns the repo id.

    Raises:
        ValueError: ``repo_id`` is not ``OWNER/NAME``.
        HubPushError: the Hub cannot be reached (offline) or refused the push; the dataset in ``root`` is
            kept and the message says how to push it later.
    """
    from huggingface_hub.errors import HfHubHTTPError, OfflineModeIsEnabled
    from lerobot.datasets.lerobot_dataset import LeRobotDataset

    check_repo_id(repo_id)
    dataset = LeRobotDataset(repo_id, root=Path(root))
    try:
        dataset.push_to_hub(tags=["rtv3", "maniskill", "shared-control", "grasping"], private=private,
                            dataset_description=dataset_description(kind, command))
    except (OfflineModeIsEnabled, HfHubHTTPError, OSError) as err:
        first = str(err).strip().splitlines()[0] if str(err).strip() else ""
        raise HubPushError(f"could not push {root} to the Hub repo {repo_id} ({type(err).__name__}: {first}); the "
                           "dataset is kept there: log in (`hf auth login`), go online (HF_HUB_OFFLINE unset) and run "
                           "the same command again with --push-to-hub") from None
    return repo_id
