"""Test session setup: headless rendering and no network, before anything imports MuJoCo or the Hub."""

import os

os.environ.setdefault("MUJOCO_GL", "egl")
os.environ.setdefault("PYOPENGL_PLATFORM", os.environ["MUJOCO_GL"])
os.environ["HF_HUB_OFFLINE"] = "1"
os.environ.setdefault("WANDB_MODE", "disabled")

import lerobot_suture  # noqa: E402,F401  - registers the env ids
