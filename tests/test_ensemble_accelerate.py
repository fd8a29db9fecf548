"""Data-parallel training: `accelerate launch` runs the real `lerobot-train` on two processes.

`accelerate launch --multi_gpu --num_processes=2 lerobot-train ... --policy.device=cpu` starts two processes
(accelerate's torchrun launcher), and lerobot-train's `Accelerator(cpu=True)` joins them over gloo and wraps
the policy in DistributedDataParallel: the path of N GPUs, on this CPU machine. (`accelerate launch --cpu
--num_processes=2` starts one process only: accelerate needs mpirun for more than one CPU process.)

One run of 4 steps carries what DDP could break: randomized priors (frozen parameters), the needle-keypoint
heads (parameters beside the members), bootstrap resampling, per-member loss logging. `record_rank_weights.py`
runs the unchanged console script and writes each process's weights, since lerobot-train saves rank 0's only.
"""

import json
import os
import socket
import subprocess
import sys
from pathlib import Path

import pytest
import torch
from lerobot_policy_ensemble_diffusion import EnsembleDiffusionPolicy
from policy_builders import make_synthetic_dataset, tiny_policy_cli_args
from safetensors.torch import load_file

BIN = Path(sys.executable).parent
RECORDER = Path(__file__).with_name("record_rank_weights.py")
REPO_ID = "local/ensemble_ddp_test"
N_PROCESSES, BATCH_SIZE, STEPS = 2, 2, 4


def _environ() -> dict:
    return {
        **os.environ,
        "HF_HUB_OFFLINE": "1",
        "HF_DATASETS_OFFLINE": "1",
        "TOKENIZERS_PARALLELISM": "false",
        "MUJOCO_GL": os.environ.get("MUJOCO_GL", "egl"),
        "OMP_NUM_THREADS": "1",  # one thread per process: the processes share the cores
    }


def _run(args: list[str], cwd: Path) -> str:
    result = subprocess.run(args, cwd=cwd, env=_environ(), capture_output=True, text=True, timeout=600)
    output = result.stdout + result.stderr
    assert result.returncode == 0, output[-6000:]
    return output


def _free_port() -> int:
    # Other test runs on this machine may hold accelerate's default port (29500).
    with socket.socket() as s:
        s.bind(("127.0.0.1", 0))
        return s.getsockname()[1]


@pytest.fixture(scope="module")
def trained(tmp_path_factory) -> dict:
    """`accelerate launch --multi_gpu --num_processes=2 lerobot-train`, 4 steps on a synthetic dataset."""
    work = tmp_path_factory.mktemp("ddp")
    make_synthetic_dataset(
        work / "data", repo_id=REPO_ID, n_episodes=3, episode_length=30, needle_keypoints=True
    )
    weights = work / "weights"
    weights.mkdir()
    out = work / "run"
    log = _run(
        [
            str(BIN / "accelerate"),
            "launch",
            "--multi_gpu",
            f"--num_processes={N_PROCESSES}",
            "--num_machines=1",
            "--mixed_precision=no",
            "--dynamo_backend=no",
            f"--main_process_port={_free_port()}",
            str(RECORDER),
            str(weights),
            str(BIN / "lerobot-train"),
            *tiny_policy_cli_args(),
            "--policy.crop_ratio=1.0",
            "--policy.num_inference_steps=3",
            "--policy.prior_scale=1.0",
            "--policy.needle_keypoints_weight=1.0",
            "--policy.bootstrap=true",
            f"--dataset.repo_id={REPO_ID}",
            f"--dataset.root={work / 'data'}",
            f"--output_dir={out}",
            f"--steps={STEPS}",
            f"--batch_size={BATCH_SIZE}",
            "--num_workers=0",
            "--log_freq=1",
            f"--save_freq={STEPS}",
        ],
        cwd=work,
    )
    ranks = [
        {stage: load_file(str(weights / f"rank{k}_{stage}.safetensors")) for stage in ("prepared", "final")}
        for k in range(N_PROCESSES)
    ]
    return {
        "log": log,
        "ranks": ranks,
        "checkpoint": out / "checkpoints" / f"{STEPS:06d}" / "pretrained_model",
        "work": work,
    }


def _member(state: dict, n: int) -> dict:
    prefix = f"members.{n}."
    return {k.removeprefix(prefix): v for k, v in state.items() if k.startswith(prefix)}


def _assert_members_distinct(state: dict) -> None:
    """Every weight matrix / kernel of member 0 differs from member 1's (1-D norm parameters start equal)."""
    m0, m1 = _member(state, 0), _member(state, 1)
    assert m0.keys() == m1.keys()
    weights = [k for k in m0 if k.endswith("weight") and m0[k].ndim >= 2]
    assert len(weights) > 20
    same = [k for k in weights if torch.equal(m0[k], m1[k])]
    assert not same, f"members 0 and 1 share {same[:5]}"


def test_two_processes_train_one_global_batch(trained):
    log = trained["log"]
    assert f"Effective batch size: {BATCH_SIZE} x {N_PROCESSES} = {BATCH_SIZE * N_PROCESSES}" in log
    # Per-member and auxiliary losses, averaged over the processes by lerobot's metrics tracker.
    for name in ("loss_member_0:", "loss_member_1:", "loss_needle_keypoints:"):
        assert log.count(name) == STEPS, name
    assert (trained["checkpoint"] / "model.safetensors").is_file()


def test_processes_hold_the_same_weights(trained):
    """DDP broadcasts rank 0's initial weights and averages every gradient: the processes never drift."""
    ranks = trained["ranks"]
    for stage in ("prepared", "final"):
        a, b = ranks[0][stage], ranks[1][stage]
        assert a.keys() == b.keys()
        differ = [k for k in a if not torch.equal(a[k], b[k])]
        assert not differ, f"{stage}: ranks differ in {differ[:5]}"


def test_members_stay_distinct_priors_frozen_heads_trained(trained):
    prepared, final = trained["ranks"][0]["prepared"], trained["ranks"][0]["final"]
    _assert_members_distinct(prepared)
    _assert_members_distinct(final)

    priors = [k for k in final if ".unet.prior." in k]
    assert len(priors) == 2 * 6  # two members, three layers, weight and bias
    assert all(torch.equal(prepared[k], final[k]) for k in priors)
    unet = [k for k in final if ".unet.unet." in k]
    assert sum(not torch.equal(prepared[k], final[k]) for k in unet) > len(unet) // 2
    heads = [k for k in final if k.startswith("needle_heads.")]
    assert len(heads) == 4 and all(not torch.equal(prepared[k], final[k]) for k in heads)


def test_checkpoint_holds_the_trained_weights(trained):
    policy = EnsembleDiffusionPolicy.from_pretrained(trained["checkpoint"])
    assert policy.config.n_members == 2 and policy.config.prior_scale == 1.0
    state, final = policy.state_dict(), trained["ranks"][0]["final"]
    assert state.keys() == final.keys()
    for key, value in final.items():
        torch.testing.assert_close(state[key], value, rtol=0, atol=0)
    _assert_members_distinct(state)


def test_lerobot_eval_runs_the_checkpoint(trained):
    out = trained["work"] / "eval"
    _run(
        [
            str(BIN / "lerobot-eval"),
            f"--policy.path={trained['checkpoint']}",
            "--env.type=suture",
            "--env.episode_length=3",
            "--eval.n_episodes=1",
            "--eval.batch_size=1",
            "--policy.device=cpu",
            f"--output_dir={out}",
        ],
        cwd=trained["work"],
    )
    info = json.loads((out / "eval_info.json").read_text())
    assert info["overall"]["n_episodes"] == 1
