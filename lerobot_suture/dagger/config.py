"""Flags of ``lerobot-suture dagger`` (:class:`DaggerConfig`, validated at construction), its arms and sizes."""

from __future__ import annotations

import math
from dataclasses import dataclass, field
from pathlib import Path
from typing import ClassVar

from lerobot_suture.dagger.watch import WatchConfig
from lerobot_suture.runtime.config import RolloutCommandConfig
from lerobot_suture.safety.ood.calibration import min_calibration_episodes

GATED, UNGATED, BC = "gated", "ungated", "bc"
ARMS = (GATED, UNGATED, BC)
"""The arms: surgeon frames after the gate's handover (gated), the expert's label at every state the policy
visits (ungated DAgger), new whole demonstrations (bc, plain behaviour cloning)."""
SCENARIOS = ("nominal", "phantom_moved_after_insertion", "camera_moved", "phantom_servo")
"""Where data is collected and the policies are tested; ``nominal`` first (false alarms, AUROC baseline)."""
CALIBRATION_MODES = ("per_episode", "per_prediction")

TOY_SIZES = {
    "collect_episodes": 1,
    "test_episodes": 1,
    "finetune_steps": 2,
    "batch_size": 2,
    "calibration_episodes": 2,
    "holdout_episodes": 1,
    "calibration_mode": "per_prediction",
    "batch_envs": 2,
}
"""What ``--toy=true`` sets: a whole loop in minutes, for a smoke test (its numbers mean nothing)."""


@dataclass
class DaggerConfig(RolloutCommandConfig):
    """``lerobot-suture dagger --policy.path=DIR --dataset_root=DIR --rounds=R --output_dir=DIR``.

    Args:
        policy: ``--policy.path=DIR``, the ensemble every arm starts from (a ``pretrained_model`` directory).
        dataset_root: its demonstrations (a ``lerobot-suture record`` dataset with a train/val split): the
            training split is aggregated with the new data, the validation seeds calibrate the gate.
        output_dir: one folder per arm and round (``<arm>/round_<r>/``), ``round_0/``, and the table
            (``dagger.md``, ``dagger.json``) and figure (``dagger.png``).
        rounds: rounds of collect, aggregate, fine-tune, recalibrate, evaluate, >= 1.
        arms: comma-separated, any of ``gated``, ``ungated``, ``bc``.
        collect_episodes: episodes per scenario and round rolled out to collect new data, >= 1.
        test_episodes: episodes per scenario of every evaluation (the same test seeds for every round and
            arm), >= 1.
        frames_per_round: new labelled frames per round for the ``ungated`` and ``bc`` arms; unset: the
            ``gated`` arm's count that round (so all arms get as many), which needs the ``gated`` arm.
        watch: ``--watch.enabled=true``: in the ``gated`` arm's collection the surgeon stand-in also takes
            over on its own when the policy's commands stray from its own (HG-DAgger's human gating; limits
            ``--watch.position`` (m), ``--watch.angle`` (rad), ``--watch.patience`` (steps), see
            :mod:`~lerobot_suture.dagger.watch`). The evaluations' surgeon still takes over only when the
            gate hands over.
        finetune_steps: ``lerobot-train`` steps per round, from the previous round's policy, >= 1. The
            default keeps three arms' two rounds near 1 h 30 min on a 2-core CPU; with the watching surgeon
            and ``new_data_repeats=10`` it took 2,000 to turn the labels into autonomy (``docs/surgeon.md``).
        new_data_repeats: how many times each new episode enters the fine-tuning data, >= 1. LeRobot samples
            frames uniformly, and the demonstrations outnumber the new frames about ten to one; a repeat
            weighs the new frames more in every batch without labelling more (the arms' frame counts and
            the table count each labelled frame once).
        lr: fine-tuning learning rate (the reference trains at 3e-4), > 0.
        warmup_steps: learning-rate warm-up steps of the fine-tuning, >= 0.
        batch_size: fine-tuning batch size, >= 1.
        calibration_episodes: nominal episodes the gate is recalibrated on each round (the dataset's
            validation seeds first, then fresh ones).
        holdout_episodes: further nominal episodes on which the gate's false-alarm rate is measured, >= 0.
        calibration_mode: ``per_episode`` (needs at least ``(1 - alpha) / alpha`` calibration episodes) or
            ``per_prediction``.
        alpha: significance of the gate's one-sided test, in (0, 0.5).
        seed: base of the collection seeds (fresh every round; the same scenes for every arm in a round).
        test_seed: base of the test seeds (disjoint from recording, calibration and collection seeds).
        batch_envs: envs run in lockstep in calibration and evaluation, >= 1.
        device: torch device of rollouts and training.
        toy: shrink everything (:data:`TOY_SIZES`, set over the flags above) so the loop runs in minutes.
    """

    writes_to_policy: ClassVar[bool] = True

    # Inputs and outputs.
    dataset_root: Path | None = None
    output_dir: Path = Path("outputs/dagger")
    rounds: int = 2
    arms: str = "gated,ungated,bc"
    # Collection and evaluation.
    collect_episodes: int = 6
    test_episodes: int = 10
    frames_per_round: int | None = None
    watch: WatchConfig = field(default_factory=WatchConfig)
    # Fine-tuning.
    finetune_steps: int = 800
    new_data_repeats: int = 1
    lr: float = 1e-4
    warmup_steps: int = 50
    batch_size: int = 16
    # Recalibration.
    calibration_episodes: int = 40
    holdout_episodes: int = 10
    calibration_mode: str = "per_episode"
    alpha: float = 0.05
    # Seeds and execution.
    seed: int = 5_000_000
    test_seed: int = 6_000_000
    toy: bool = False

    def __post_init__(self):
        super().__post_init__()
        if self.dataset_root is None:
            raise ValueError(
                "`--dataset_root` is required: the `lerobot-suture record` dataset the policy was trained on."
            )
        if self.toy:
            for name, value in TOY_SIZES.items():
                setattr(self, name, value)
        if self.rounds < 1:
            raise ValueError(f"`rounds` must be >= 1. Got {self.rounds}.")
        arms = self.arm_list
        unknown = [a for a in arms if a not in ARMS]
        if not arms or unknown or len(set(arms)) != len(arms):
            raise ValueError(
                f"`arms` must be a comma-separated list of distinct arms from {ARMS}, e.g. "
                f"--arms=gated,ungated,bc. Got {self.arms!r}."
            )
        if GATED not in arms and self.frames_per_round is None:
            raise ValueError(
                f"Without the gated arm nothing sets the new frames per round: add it (--arms=gated,{self.arms}) "
                "or set `--frames_per_round`."
            )
        if self.frames_per_round is not None and self.frames_per_round < 0:
            raise ValueError(f"`frames_per_round` must be >= 0. Got {self.frames_per_round}.")
        for name in (
            "collect_episodes",
            "test_episodes",
            "finetune_steps",
            "new_data_repeats",
            "batch_size",
        ):
            if getattr(self, name) < 1:
                raise ValueError(f"`{name}` must be >= 1. Got {getattr(self, name)}.")
        if self.warmup_steps < 0:
            raise ValueError(f"`warmup_steps` must be >= 0. Got {self.warmup_steps}.")
        if not (self.lr > 0 and math.isfinite(self.lr)):
            raise ValueError(f"`lr` must be a finite number > 0. Got {self.lr}.")
        if not 0.0 < self.alpha < 0.5:
            raise ValueError(f"`alpha` must be in (0, 0.5) (a one-sided test). Got {self.alpha}.")
        if self.calibration_mode not in CALIBRATION_MODES:
            raise ValueError(
                f"`calibration_mode` must be one of {CALIBRATION_MODES}. Got {self.calibration_mode!r}."
            )
        if self.calibration_episodes < 1 or self.holdout_episodes < 0:
            raise ValueError(
                "`calibration_episodes` must be >= 1 and `holdout_episodes` >= 0. "
                f"Got {self.calibration_episodes}, {self.holdout_episodes}."
            )
        needed = min_calibration_episodes(self.alpha)
        if self.calibration_mode == "per_episode" and self.calibration_episodes < needed:
            raise ValueError(
                f"`calibration_mode=per_episode` at alpha={self.alpha} needs at least {needed} calibration "
                f"episodes. Got {self.calibration_episodes}; raise `--calibration_episodes` or use "
                "`--calibration_mode=per_prediction`."
            )
        if not 0 <= self.seed < 2**31 or not 0 <= self.test_seed < 2**31:
            raise ValueError(
                f"`seed` and `test_seed` must be in [0, 2**31). Got {self.seed}, {self.test_seed}."
            )
        if not (Path(self.policy.path) / "config.json").is_file():
            raise FileNotFoundError(
                f"No trained policy at {self.policy.path} (no config.json). Pass the `pretrained_model` "
                "directory of a lerobot-train checkpoint, e.g. outputs/train/NAME/checkpoints/last/pretrained_model."
            )
        from lerobot_suture.datasets.metadata import read_episode_log

        log = read_episode_log(self.dataset_root)  # raises, naming the fix, without an episode log
        if not log.get("splits", {}).get("val"):
            raise ValueError(
                f"The dataset at {self.dataset_root} has no validation episodes to calibrate the gate on: "
                "record it with `--val_fraction` > 0."
            )
        if log.get("env_kwargs", {}).get("relative_actions"):
            raise ValueError(
                f"The dataset at {self.dataset_root} holds relative actions (`dx` ... `jaw`), and a round records "
                "the executed absolute targets, so the two cannot be merged into one training set. Run DAgger on "
                "a policy trained on a dataset recorded with absolute actions (`lerobot-suture record` without "
                "`--relative_actions`)."
            )

    @property
    def arm_list(self) -> list[str]:
        """The arms in the order they run (``gated`` first: it sets the others' frame budget)."""
        names = [a.strip() for a in self.arms.split(",") if a.strip()]
        return sorted(names, key=lambda a: ARMS.index(a) if a in ARMS else len(ARMS))
