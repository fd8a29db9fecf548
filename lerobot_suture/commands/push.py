"""``lerobot-suture push --repo_id=USER/NAME``: a dataset recorded with ``lerobot-suture record`` pushed to
the Hugging Face Hub (:mod:`lerobot_suture.datasets.hub`)."""

from __future__ import annotations

from pathlib import Path

import draccus

from lerobot_suture.datasets.hub import PushConfig, push_dataset


def main(argv: list[str] | None = None) -> None:
    cfg = draccus.parse(config_class=PushConfig, args=argv, prog="lerobot-suture push", exit_on_error=False)
    if cfg.root is None:
        from lerobot.utils.constants import HF_LEROBOT_HOME

        root = Path(HF_LEROBOT_HOME) / cfg.repo_id
    else:
        root = Path(cfg.root).expanduser()
    print(push_dataset(cfg.repo_id, root, private=cfg.private))
