"""Test session setup: headless rendering and no network, before anything imports MuJoCo or the Hub."""

import os

os.environ.setdefault("MUJOCO_GL", "egl")
os.environ.setdefault("PYOPENGL_PLATFORM", os.environ["MUJOCO_GL"])
os.environ["HF_HUB_OFFLINE"] = "1"
os.environ.setdefault("WANDB_MODE", "disabled")
# The tests' models are tiny: one thread per process is fastest, since syncing threads over each small op
# costs more than it saves (many times more on a machine whose cores are busy). Subprocesses inherit it.
os.environ.setdefault("OMP_NUM_THREADS", "1")

from pathlib import Path  # noqa: E402

import pytest  # noqa: E402
from hypothesis import settings  # noqa: E402

import lerobot_suture  # noqa: E402,F401  - registers the env ids

# Property tests draw the same examples on every run, so that a failure reproduces and CI does not fail by chance.
# HYPOTHESIS_PROFILE=explore draws new ones on each run, to search for counterexamples.
settings.register_profile("seeded", derandomize=True, print_blob=True)
settings.register_profile("explore", derandomize=False, print_blob=True)
settings.load_profile(os.environ.get("HYPOTHESIS_PROFILE", "seeded"))


@pytest.fixture(scope="session")
def tiny_policy_dir(tmp_path_factory) -> Path:
    """An untrained tiny ensemble saved as `lerobot-train` saves one: weights, config and processors.

    Its statistics come from the scripted expert, so its actions and hold poses are in the right units.
    """
    from policy_builders import save_untrained_expert_policy

    return save_untrained_expert_policy(
        tmp_path_factory.mktemp("tiny_policy") / "pretrained_model",
        n_members=2,
        num_inference_steps=3,
        noise_scheduler_type="DDIM",
    )


@pytest.hookimpl(tryfirst=True)
def pytest_configure(config: pytest.Config) -> None:
    """pytest-randomly, once installed, loads itself into every run; it shuffles only on request.

    A plain `pytest` keeps the file order and the global seeds as they are, so that a failure reproduces by
    running the same command again. `-p randomly` or `--randomly-seed=N` turns the shuffle (and the
    reseeding of `random` and numpy before every test) on. Runs before pytest-randomly replaces its
    default seed with a drawn one.
    """
    if not config.pluginmanager.hasplugin("randomly"):
        return
    named = {"randomly", "pytest_randomly"} & set(config.option.plugins or ())
    if named or config.getoption("randomly_seed") != "default":
        return
    config.option.randomly_reorganize = False
    config.option.randomly_reset_seed = False
