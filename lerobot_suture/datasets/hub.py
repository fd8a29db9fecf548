"""Publish a recorded dataset on the Hugging Face Hub with ``LeRobotDataset.push_to_hub``.

``lerobot-suture record --push_to_hub=true`` pushes when the recording is done;
``lerobot-suture push --repo_id=USER/NAME --root=DIR`` pushes a dataset recorded earlier. Both check
first, without touching the dataset, that a push can work: the Hub is not switched off
(``HF_HUB_OFFLINE``), a token exists (``hf auth login`` or ``HF_TOKEN``), the Hub accepts it and its
owner may write to the repo's namespace. A push that fails on the way raises :class:`HubPushError`
with the command to retry; the local dataset is only ever read.
"""

from __future__ import annotations

import logging
from dataclasses import dataclass
from pathlib import Path

from lerobot_suture.datasets import metadata

logger = logging.getLogger(__name__)

_RETRY = (
    "The local dataset at {root} is intact; push it later with "
    "`lerobot-suture push --repo_id={repo_id} --root={root}`."
)


def validate_repo_id(repo_id: str) -> None:
    """Check ``repo_id`` is ``USER/NAME`` as the Hugging Face Hub accepts it; no network.

    Raises:
        ValueError: naming what is wrong and the form expected.
    """
    if not repo_id:
        raise ValueError(
            "`repo_id` is required: pass --repo_id=USER/NAME (your Hugging Face user or organisation and "
            "a dataset name, e.g. --repo_id=alice/suture_expert)."
        )
    parts = repo_id.split("/")
    if len(parts) != 2 or not all(parts):
        raise ValueError(
            f"`repo_id` must be USER/NAME with exactly one '/', e.g. alice/suture_expert. Got {repo_id!r}."
        )
    from huggingface_hub.utils import HFValidationError
    from huggingface_hub.utils import validate_repo_id as hf_validate

    try:
        hf_validate(repo_id)
    except HFValidationError as exc:
        raise ValueError(
            f"`repo_id` {repo_id!r} is not a valid Hugging Face repo id: use letters, digits, '-', '_' "
            f"and '.', at most 96 characters, no '--' or '..'. ({exc})"
        ) from exc


class HubPushError(RuntimeError):
    """The dataset cannot be pushed to the Hub (no token, no network, no permission, upload failed)."""

    exit_status = 1  # the command's exit status: the input was fine, the push was not


def _hub_offline() -> bool:
    from huggingface_hub import constants

    return bool(constants.HF_HUB_OFFLINE)


def check_hub_access(repo_id: str) -> str:
    """Check, before any work, that ``repo_id`` can be pushed to; returns the token owner's name.

    One network call (``whoami``). Raises:
        HubPushError: offline mode, no token, a rejected token, an unreachable Hub, or a namespace
            the token's owner cannot write to; the message says how to fix it.
    """
    from huggingface_hub import HfApi, get_token
    from huggingface_hub.errors import HfHubHTTPError

    if _hub_offline():
        raise HubPushError(
            "HF_HUB_OFFLINE is set, so nothing can be pushed to the Hugging Face Hub: unset it to push "
            "(or record with --push_to_hub=false and push later with `lerobot-suture push`)."
        )
    token = get_token()
    if not token:
        raise HubPushError(
            "No Hugging Face token: log in with `hf auth login` (or set HF_TOKEN to a token with write "
            "access, https://huggingface.co/settings/tokens), then push again."
        )
    try:
        who = HfApi().whoami(token=token)
    except HfHubHTTPError as exc:
        status = getattr(getattr(exc, "response", None), "status_code", None)
        if status in (401, 403):
            raise HubPushError(
                f"The Hugging Face Hub rejected the token (HTTP {status}): log in again with "
                "`hf auth login` (or set HF_TOKEN to a valid token with write access)."
            ) from exc
        raise HubPushError(f"The Hugging Face Hub answered with an error: {exc}") from exc
    except Exception as exc:  # noqa: BLE001 - httpx/OS errors: every connection failure reads the same
        raise HubPushError(
            f"Cannot reach the Hugging Face Hub ({type(exc).__name__}: {exc}). Check the network (or a "
            "proxy, HF_ENDPOINT) and push again."
        ) from exc
    name = who.get("name", "")
    namespaces = {name} | {org.get("name") for org in who.get("orgs", [])}
    namespace = repo_id.split("/")[0]
    if namespace not in namespaces:
        raise HubPushError(
            f"The token belongs to {name!r}, who cannot write to {namespace!r}: use "
            f"--repo_id={name}/{repo_id.split('/')[-1]} (or a token of {namespace!r})."
        )
    return name


def push_dataset(repo_id: str, root: str | Path, private: bool = False) -> str:
    """Push the finished dataset at ``root`` to ``repo_id`` (files, card, tags, version tag).

    Args:
        repo_id: ``USER/NAME`` on the Hub.
        root: the dataset's root directory.
        private: create the repository as private (true) or public (false).

    Returns:
        The dataset's Hub URL.

    Raises:
        HubPushError: see :func:`check_hub_access`, or the upload failed.
        RuntimeError: the dataset's recording is unfinished (resume it first).
    """
    from lerobot_suture.datasets.card import LICENSE, TAGS, card_kwargs
    from lerobot_suture.datasets.video import resolve_video_backend

    validate_repo_id(repo_id)
    root = Path(root)
    metadata.read_episode_log(root)
    if metadata.read_checkpoint(root) is not None:
        raise RuntimeError(
            f"The recording into {root} is unfinished (it is running, or was killed): finish it with "
            "`lerobot-suture record --resume=true ...` before pushing."
        )
    check_hub_access(repo_id)

    from lerobot.datasets.lerobot_dataset import LeRobotDataset

    dataset = LeRobotDataset(repo_id, root=root, video_backend=resolve_video_backend())
    kwargs = {k: v for k, v in card_kwargs(root).items() if k != "license"}
    logger.info(
        "Pushing %s (%d episodes) to https://huggingface.co/datasets/%s", root, dataset.num_episodes, repo_id
    )
    try:
        dataset.push_to_hub(tags=list(TAGS), license=LICENSE, private=private, **kwargs)
    except Exception as exc:
        raise HubPushError(
            f"Pushing to {repo_id} failed ({type(exc).__name__}: {exc}). "
            + _RETRY.format(root=root, repo_id=repo_id)
        ) from exc
    url = f"https://huggingface.co/datasets/{repo_id}"
    logger.info("Pushed: %s", url)
    return url


@dataclass
class PushConfig:
    """Flags of ``lerobot-suture push``.

    Args:
        repo_id: ``USER/NAME`` on the Hugging Face Hub.
        root: the dataset's root directory; None: ``$HF_LEROBOT_HOME/<repo_id>``.
        private: create the repository as private (true) or public (false).
    """

    repo_id: str = ""  # USER/NAME on the Hugging Face Hub (required)
    root: str | None = None  # dataset directory (default: $HF_LEROBOT_HOME/<repo_id>)
    private: bool = False  # create the Hub repository as private

    def __post_init__(self):
        validate_repo_id(self.repo_id)
