"""`lerobot-eval` on the suture env, every way it runs.

- The real command with `--eval.batch_size=2 --eval.use_async_envs=true`: the ensemble in async workers,
  the CBF on in every worker, the O.O.D. gate enforced and reporting, videos, and counts that add up.
- The core-count default batch size of a machine with more cores than this one.
- LeRobot's own `eval_policy` over sync and async vector envs of batch sizes 1, 2 and 4, driven by the
  scripted expert's actions: an episode that succeeds in a worker counts as a success, one that fails as a
  failure, each in its own place.
- The gate in async workers holds exactly the batch elements it released.
- On a dataset recorded by `lerobot-suture record`: `lerobot-train` evaluating the ensemble in async envs
  every N steps, and `lerobot-eval` of LeRobot's own `diffusion` policy trained on it.
"""

from __future__ import annotations

import json
import os
import shutil
import subprocess
import sys
from dataclasses import dataclass
from pathlib import Path

import numpy as np
import pytest
import torch
from lerobot.configs.policies import PreTrainedConfig
from lerobot.envs.factory import make_env, make_env_config
from lerobot.policies.factory import make_pre_post_processors
from lerobot.policies.pretrained import PreTrainedPolicy
from lerobot.scripts.lerobot_eval import eval_policy
from lerobot.utils.constants import ACTION, OBS_STATE
from lerobot.utils.import_utils import register_third_party_plugins
from lerobot_policy_ensemble_diffusion import EnsembleDiffusionPolicy
from policy_builders import tiny_policy_cli_args

from lerobot_suture.datasets.record import record
from lerobot_suture.datasets.record_config import RecordConfig
from lerobot_suture.datasets.video import resolve_video_backend
from lerobot_suture.expert import ScriptedExpert, iter_expert_steps
from lerobot_suture.safety.ood.calibration import fit_calibration
from lerobot_suture.safety.ood.calibration_file import save_calibration
from lerobot_suture.sim.suture_env import SutureEnv

BIN = Path(sys.executable).parent
LEROBOT_EVAL = str(BIN / "lerobot-eval")

register_third_party_plugins()  # the in-repo env plugin must be there: a missing one is a failure, not a skip


def _environ() -> dict:
    return {**os.environ, "HF_HUB_OFFLINE": "1", "MUJOCO_GL": os.environ.get("MUJOCO_GL", "egl")}


def _calibrated_copy(policy_dir: Path, dest: Path, threshold: float) -> Path:
    """A copy of the saved policy whose gate threshold sits at `threshold` (a score model N(t, tiny))."""
    shutil.copytree(policy_dir, dest)
    scores = threshold * (1 + 1e-3 * np.random.default_rng(0).standard_normal(200))
    config = json.loads((dest / "config.json").read_text())
    filename = config.get("ood", {}).get("calibration_file", "ood_calibration.json")
    save_calibration(fit_calibration(np.abs(scores), model="normal"), dest, filename=filename)
    return dest


def run_lerobot_eval(args: list[str], out: Path, cpu_count: int | None = None) -> tuple[dict, str]:
    """The real `lerobot-eval` (its console script; with `cpu_count`, its `main` on a machine reporting
    that many cores). Returns eval_info.json and the log."""
    if cpu_count is None:
        command = [LEROBOT_EVAL]
    else:
        prelude = (
            f"import os, sys; os.cpu_count = lambda: {cpu_count}; "
            "from lerobot.scripts.lerobot_eval import main; sys.argv[0] = 'lerobot-eval'; main()"
        )
        command = [sys.executable, "-c", prelude]
    result = subprocess.run(
        [*command, "--policy.device=cpu", "--env.type=suture", f"--output_dir={out}", *args],
        env=_environ(),
        capture_output=True,
        text=True,
        timeout=900,
    )
    log = result.stdout + result.stderr
    assert result.returncode == 0, log[-6000:]
    return json.loads((out / "eval_info.json").read_text()), log


def check_eval_info(info: dict, n_episodes: int, batch_size: int) -> list[bool]:
    """The episode count, per-episode successes and `pc_success` agree; the videos exist. Returns the successes.

    LeRobot renders every env of every batch (up to 10), the discarded tail of the last batch included.
    """
    metrics = info["per_task"][0]["metrics"]
    successes = metrics["successes"]
    assert len(successes) == n_episodes and all(isinstance(s, bool) for s in successes)
    assert len(metrics["sum_rewards"]) == n_episodes
    for aggregate in (info["overall"], info["per_group"]["suture"]):
        assert aggregate["n_episodes"] == n_episodes
        assert aggregate["pc_success"] == pytest.approx(100.0 * np.mean(successes))
    videos = info["overall"]["video_paths"]
    assert len(videos) == min(10, -(-n_episodes // batch_size) * batch_size)
    for path in videos:
        assert Path(path).stat().st_size > 1000, path
    return successes


# ---------------------------------------------------------------------------------------------- the CLI


def test_lerobot_eval_async_batch_2_with_the_cbf_and_the_enforced_gate(tiny_policy_dir, tmp_path):
    policy_dir = _calibrated_copy(tiny_policy_dir, tmp_path / "policy", threshold=1e-12)  # O.O.D. at once
    info, log = run_lerobot_eval(
        [
            f"--policy.path={policy_dir}",
            "--policy.ood.enforce=true",
            "--env.cbf.enabled=true",  # the safety filter wraps the env inside every worker
            "--env.episode_length=4",
            "--eval.n_episodes=3",  # two batches, the second cut to one episode
            "--eval.batch_size=2",
            "--eval.use_async_envs=true",
        ],
        tmp_path / "eval",
    )
    assert "batch_size=2, async=True" in log
    assert check_eval_info(info, n_episodes=3, batch_size=2) == [False] * 3  # an untrained policy, 4 steps
    for env_index in (0, 1):  # the gate reports each batch element it releases
        assert f"O.O.D. gate: env {env_index} flagged at prediction 0" in log
    assert "control released to the surgeon" in log


@pytest.mark.slow  # the async path itself runs by default in the batch-2 test above
def test_lerobot_eval_default_batch_size_on_a_machine_with_more_cores(tiny_policy_dir, tmp_path):
    # 16 cores: LeRobot takes 70% of them, capped by the episode count, and runs them async.
    # The inference approximations are LeRobot's own overrides of the trained config.
    approximations = ["--policy.num_inference_steps=2", "--policy.uncertainty_samples_per_member=3"]
    info, log = run_lerobot_eval(
        [
            f"--policy.path={tiny_policy_dir}",
            *approximations,
            "--env.episode_length=3",
            "--eval.n_episodes=3",
        ],
        tmp_path / "eval",
        cpu_count=16,
    )
    assert "batch_size=3, async=True" in log
    assert "'num_inference_steps': 2" in log and "'uncertainty_samples_per_member': 3" in log
    check_eval_info(info, n_episodes=3, batch_size=3)


# ------------------------------------------------------------------ success counting in the vector envs


@dataclass
class _ReplayConfig(PreTrainedConfig):
    """Config of `_ExpertReplayPolicy` (no features to learn; nothing is trained)."""

    def get_optimizer_preset(self):
        raise NotImplementedError

    def get_scheduler_preset(self):
        return None

    def validate_features(self):
        pass

    @property
    def observation_delta_indices(self):
        return None

    @property
    def action_delta_indices(self):
        return None

    @property
    def reward_delta_indices(self):
        return None


class _ExpertReplayPolicy(PreTrainedPolicy):
    """Plays back the scripted expert's actions for each episode's seed, or holds still on `stall` seeds.

    The env is deterministic given its seed, so the played-back throw succeeds exactly as the expert's did;
    which batch a rollout is follows from LeRobot's seeding (`start_seed + batch * num_envs + i`).
    """

    config_class = _ReplayConfig
    name = "suture_expert_replay"

    def __init__(self, actions: dict[int, np.ndarray], start_seed: int, batch_size: int, stall: set[int]):
        super().__init__(_ReplayConfig(device="cpu"))
        self.actions, self.start_seed, self.batch_size, self.stall = actions, start_seed, batch_size, stall
        self.n_rollouts, self.step = 0, 0

    def get_optim_params(self):
        return {}

    def forward(self, batch):
        raise NotImplementedError

    def predict_action_chunk(self, batch, **kwargs):
        raise NotImplementedError

    def reset(self):
        self.seeds = [self.start_seed + self.n_rollouts * self.batch_size + i for i in range(self.batch_size)]
        self.n_rollouts += 1
        self.step = 0

    def select_action(self, batch, **kwargs):
        rows = []
        for i, seed in enumerate(self.seeds):
            if seed in self.stall:
                rows.append(batch[OBS_STATE][i].numpy())  # hold the measured pose
            else:
                plan = self.actions[seed]
                rows.append(plan[min(self.step, len(plan) - 1)])
        self.step += 1
        return torch.as_tensor(np.stack(rows), dtype=torch.float32)


def _identity(x):
    return x


@pytest.fixture(scope="module")
def expert_actions() -> dict[int, np.ndarray]:
    """The scripted expert's actions for seeds 0-3 (each a successful throw)."""
    env, expert, actions = SutureEnv(obs_type="state"), ScriptedExpert(), {}
    for seed in range(4):
        obs, _ = env.reset(seed=seed)
        steps = list(iter_expert_steps(env, expert, obs))
        assert steps[-1].info["is_success"], seed
        actions[seed] = np.stack([step.action for step in steps])
    env.close()
    return actions


@pytest.mark.parametrize(
    ("batch_size", "use_async"),
    [(1, False), (2, False), (2, True), pytest.param(4, True, marks=pytest.mark.slow)],
    ids=["sync1", "sync2", "async2", "async4"],
)
def test_eval_policy_counts_each_worker_s_success_in_its_place(expert_actions, batch_size, use_async):
    stall = {1}  # the second episode holds still and fails; the others are the expert's throws
    env_cfg = make_env_config("suture", obs_type="state")
    vec = make_env(env_cfg, n_envs=batch_size, use_async_envs=use_async)["suture"][0]
    policy = _ExpertReplayPolicy(expert_actions, start_seed=0, batch_size=batch_size, stall=stall)
    try:
        assert vec.call("task_description")[0].startswith("Insert the curved suture needle")
        result = eval_policy(
            vec, policy, _identity, _identity, _identity, _identity, n_episodes=4, start_seed=0
        )
    finally:
        vec.close()
    per_episode = [episode["success"] for episode in result["per_episode"]]
    assert per_episode == [True, False, True, True]
    assert result["aggregated"]["pc_success"] == pytest.approx(75.0)


# ---------------------------------------------------------------------------- the gate in async workers


def _gated_rollout(policy_dir: Path, batch_size: int) -> tuple[dict, EnsembleDiffusionPolicy]:
    env_cfg = make_env_config("suture", episode_length=6)
    policy = EnsembleDiffusionPolicy.from_pretrained(policy_dir)
    policy.config.ood.enforce = True
    pre, post = make_pre_post_processors(policy.config, pretrained_path=str(policy_dir))
    vec = make_env(env_cfg, n_envs=batch_size, use_async_envs=True)["suture"][0]
    try:
        torch.manual_seed(0)
        result = eval_policy(
            vec,
            policy,
            _identity,
            _identity,
            pre,
            post,
            n_episodes=batch_size,
            start_seed=0,
            return_episode_data=True,
        )
    finally:
        vec.close()
    return result, policy


@pytest.mark.parametrize("threshold", [1e-12, 1e12], ids=["releases", "never_releases"])
def test_the_enforced_gate_holds_exactly_the_released_envs_in_async_workers(
    tiny_policy_dir, tmp_path, threshold
):
    policy_dir = _calibrated_copy(tiny_policy_dir, tmp_path / "policy", threshold=threshold)
    result, policy = _gated_rollout(policy_dir, batch_size=2)
    released = threshold < 1.0
    episodes = result["episodes"]
    for env_index in range(2):
        status = policy.ood_status(env_index)
        assert status["released"] is released and np.isfinite(status["score"])
        rows = episodes["episode_index"] == env_index
        action = episodes[ACTION][rows].numpy()[:-1]  # the last row pads the final observation
        pose = episodes[OBS_STATE][rows].numpy()[:-1]
        # Held: every command is the pose measured when it was sent, so the arm stays where it is.
        held = np.allclose(action, pose, atol=1e-4)
        assert held is released


# ------------------------------------------------------------------- trained on a recorded dataset

RECORDED_REPO_ID = "suture-tests/eval_expert"
RECORDED_IMAGE_SIZE = 32


@pytest.fixture(scope="module")
def recorded(tmp_path_factory) -> Path:
    """Two expert episodes recorded by `lerobot-suture record`'s code, in the env's default layout."""
    root = tmp_path_factory.mktemp("datasets") / "eval_expert"
    record(
        RecordConfig(
            repo_id=RECORDED_REPO_ID,
            root=str(root),
            num_episodes=2,
            image_size=RECORDED_IMAGE_SIZE,
            obs_type="pixels_agent_pos",
        )
    )
    return root


def _lerobot_train(recorded: Path, out: Path, policy_args: list[str], *extra: str) -> str:
    result = subprocess.run(
        [
            str(BIN / "lerobot-train"),
            f"--dataset.repo_id={RECORDED_REPO_ID}",
            f"--dataset.root={recorded}",
            f"--dataset.video_backend={resolve_video_backend()}",
            *policy_args,
            "--batch_size=2",
            "--steps=2",
            "--num_workers=0",
            f"--output_dir={out}",
            *extra,
        ],
        env={**_environ(), "WANDB_MODE": "disabled"},
        capture_output=True,
        text=True,
        timeout=900,
    )
    log = result.stdout + result.stderr
    assert result.returncode == 0, log[-6000:]
    return log


@pytest.mark.slow
def test_lerobot_train_evaluates_the_ensemble_in_async_envs_during_training(recorded, tmp_path):
    out = tmp_path / "train"
    log = _lerobot_train(
        recorded,
        out,
        tiny_policy_cli_args(),
        "--save_checkpoint=false",
        "--env.type=suture",
        f"--env.image_size={RECORDED_IMAGE_SIZE}",
        "--env.episode_length=3",
        "--env_eval_freq=2",
        "--eval.n_episodes=2",
        "--eval.batch_size=2",
        "--eval.use_async_envs=true",
    )
    assert "Eval policy at step 2" in log and "'pc_success': 0.0" in log, log[-4000:]
    videos = sorted((out / "eval").rglob("*.mp4"))
    assert len(videos) == 2 and all(v.stat().st_size > 1000 for v in videos), videos


@pytest.mark.slow
def test_lerobot_eval_runs_lerobot_s_own_diffusion_trained_on_the_recording(recorded, tmp_path):
    train = tmp_path / "train"
    _lerobot_train(
        recorded,
        train,
        [
            "--policy.type=diffusion",
            "--policy.device=cpu",
            "--policy.pretrained_backbone_weights=null",
            "--policy.use_group_norm=true",
            "--policy.push_to_hub=false",
            "--policy.down_dims=[16,32]",
            "--policy.horizon=8",
            "--policy.n_action_steps=4",
            "--policy.n_obs_steps=2",
            "--policy.num_inference_steps=3",
            "--policy.noise_scheduler_type=DDIM",
        ],
    )
    info, log = run_lerobot_eval(
        [
            f"--policy.path={train / 'checkpoints' / 'last' / 'pretrained_model'}",
            f"--env.image_size={RECORDED_IMAGE_SIZE}",
            "--env.episode_length=3",
            "--eval.n_episodes=2",
            "--eval.batch_size=2",
            "--eval.use_async_envs=true",
        ],
        tmp_path / "eval",
    )
    assert "batch_size=2, async=True" in log
    check_eval_info(info, n_episodes=2, batch_size=2)
