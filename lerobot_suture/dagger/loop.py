"""``lerobot-suture dagger``: learning from the surgeon, gated by the policy's uncertainty, against two baselines.

Round 0 evaluates the given policy (a copy in ``round_0/policy``, its gate recalibrated as every later
round's is, so all rounds are gated alike). Then each round ``r = 1..R``, for each arm (``gated`` first: its
surgeon's frames set the others' budget), into ``<output_dir>/<arm>/round_<r>/``:

1. ``collect``: roll out the arm's current policy in the four scenarios on the round's fresh seeds and keep
   the arm's new labelled frames (:mod:`~lerobot_suture.dagger.collect`) in ``new_data/``; ``collect.json``;
2. ``aggregate``: the demonstrations' training split and every new dataset of the arm so far, merged, with
   the original normalization (:mod:`~lerobot_suture.dagger.aggregate`), in ``dataset/``;
3. ``train``: fine-tune the previous round's policy with the real ``lerobot-train`` (resumed after a
   kill) in ``train/``;
4. ``calibrate``: refit the gate on nominal validation seeds (``lerobot-suture calibrate``'s fit);
5. ``evaluate``: the fixed test seeds, gate enforced, surgeon taking over (``eval.json``).

Every stage is skipped when its result is there, so a killed run resumes where it stopped; ``stages.json``
lists what each invocation ran and skipped, and each stage's wall time (s). At the end the table
(``dagger.md``, ``dagger.json``) and the figure (``dagger.png``, :mod:`~lerobot_suture.dagger.report`).
"""

from __future__ import annotations

import dataclasses
import logging
import shutil
import time
from collections.abc import Callable
from datetime import UTC, datetime
from pathlib import Path

from tqdm import tqdm

from lerobot_suture.dagger import aggregate as agg
from lerobot_suture.dagger import collect as col
from lerobot_suture.dagger.config import BC, GATED, SCENARIOS, DaggerConfig
from lerobot_suture.dagger.evaluate import evaluate, evaluation_seeds
from lerobot_suture.datasets.metadata import read_episode_log, read_json, write_json_atomic
from lerobot_suture.runtime.config import PolicyPathConfig
from lerobot_suture.runtime.policy import calibration_file, copy_policy
from lerobot_suture.runtime.seeds import episode_seeds

logger = logging.getLogger(__name__)

STAGES = ("collect", "aggregate", "train", "calibrate", "evaluate")
SETTINGS_FILE = "dagger_config.json"
_SETTINGS = (
    "collect_episodes",
    "test_episodes",
    "frames_per_round",
    "watch",
    "finetune_steps",
    "new_data_repeats",
    "lr",
    "warmup_steps",
    "batch_size",
    "calibration_episodes",
    "holdout_episodes",
    "calibration_mode",
    "alpha",
    "seed",
    "test_seed",
    "toy",
)
"""The settings a resumed run must share with the one it resumes (its stages were done with them)."""


class Journal:
    """What each invocation ran and skipped, and each stage's wall time (s) summed over invocations."""

    def __init__(self, path: Path, total: int):
        self.path = path
        self.record = read_json(path) if path.is_file() else {"invocations": [], "seconds": {}}
        self.ran: list[str] = []
        self.skipped: list[str] = []
        self.record["invocations"].append(
            {
                "started": datetime.now(UTC).isoformat(timespec="seconds"),
                "ran": self.ran,
                "skipped": self.skipped,
            }
        )
        self.progress = tqdm(total=total, desc="dagger stages", unit="stage")

    def stage(self, key: str, done: Callable[[], bool], run: Callable[[], object]) -> None:
        """Run ``run`` unless ``done()``; either way one stage further."""
        if done():
            self.skipped.append(key)
        else:
            logger.info("dagger: %s", key)
            started = time.perf_counter()
            run()
            seconds = self.record["seconds"]
            seconds[key] = round(seconds.get(key, 0.0) + time.perf_counter() - started, 1)
            self.ran.append(key)
        write_json_atomic(self.path, self.record)
        self.progress.update(1)


def _check_settings(cfg: DaggerConfig) -> None:
    """Write the run's settings, or check them against those of the run being resumed."""
    path = cfg.output_dir / SETTINGS_FILE
    settings = {
        "policy": str(Path(cfg.policy.path).resolve()),
        "dataset_root": str(Path(cfg.dataset_root).resolve()),
        **{name: _setting(getattr(cfg, name)) for name in _SETTINGS},
    }
    if path.is_file():
        # A setting the saved run predates (a flag added since) had its default there.
        defaults = {
            f.name: _setting(f.default if f.default_factory is dataclasses.MISSING else f.default_factory())
            for f in dataclasses.fields(DaggerConfig)
            if f.name in _SETTINGS
        }
        before = {**defaults, **read_json(path)}
        changed = {k: (before.get(k), v) for k, v in settings.items() if before.get(k) != v}
        if changed:
            raise ValueError(
                f"{cfg.output_dir} holds a run with other settings ({changed}: was, now); resume it with the "
                "same flags (rounds, arms, device and batch_envs may change) or use a new `--output_dir`."
            )
    write_json_atomic(path, settings)


def _setting(value):
    """A setting as ``dagger_config.json`` holds it (a nested config as a dict)."""
    return dataclasses.asdict(value) if dataclasses.is_dataclass(value) else value


def _policy_config(policy_dir: Path):
    from lerobot.configs.policies import PreTrainedConfig
    from lerobot.utils.import_utils import register_third_party_plugins

    register_third_party_plugins()
    return PreTrainedConfig.from_pretrained(policy_dir)


class DaggerRun:
    """The rounds of one ``lerobot-suture dagger`` invocation (see the module docstring)."""

    def __init__(self, cfg: DaggerConfig):
        from lerobot_suture.datasets.features import IMAGE_KEY
        from lerobot_suture.expert import ExpertConfig
        from lerobot_suture.runtime.policy import env_kwargs_for_policy

        self.cfg = cfg
        self.out = Path(cfg.output_dir)
        log = read_episode_log(cfg.dataset_root)
        self.repo_id = log["repo_id"]
        recorded = log["env_kwargs"]
        env_kwargs = env_kwargs_for_policy(_policy_config(Path(cfg.policy.path)))
        env_kwargs.update({k: recorded[k] for k in ("grasp", "appearance") if recorded.get(k)})
        info = read_json(Path(cfg.dataset_root) / "meta" / "info.json")
        self.env_kwargs = env_kwargs
        self.expert_config = ExpertConfig(**log["expert"]["config"])
        self.steps_after_success = int(log.get("steps_after_success", 0))
        self.video = info["features"].get(IMAGE_KEY, {}).get("dtype") == "video"
        self.test_seeds = evaluation_seeds(cfg.test_seed, cfg.test_episodes)
        self.demonstrations = self.out / "demonstrations"
        self.round0 = self.out / "round_0"
        total = 4 + len(cfg.arm_list) * cfg.rounds * len(STAGES)
        self.journal = Journal(self.out / "stages.json", total)

    # ---- stages shared by the arms

    def prepare(self) -> Path:
        """The labelled training demonstrations and round 0 (the given policy, recalibrated, evaluated)."""
        self.journal.stage(
            "demonstrations",
            self.demonstrations.is_dir,
            lambda: agg.training_demonstrations(
                Path(self.cfg.dataset_root), self.repo_id, self.demonstrations
            ),
        )
        policy = self.round0 / "policy"
        self.journal.stage(
            "round_0/copy", policy.is_dir, lambda: copy_policy(Path(self.cfg.policy.path), policy)
        )
        self._calibrate_and_evaluate("round_0", policy, self.round0)
        return policy

    def _calibrate_and_evaluate(self, key: str, policy: Path, out: Path) -> None:
        self.journal.stage(
            f"{key}/calibrate", lambda: calibration_file(policy).is_file(), lambda: self.calibrate(policy)
        )
        self.journal.stage(
            f"{key}/evaluate", (out / "eval.json").is_file, lambda: self.evaluate(policy, out, key)
        )

    def calibrate(self, policy: Path) -> None:
        from lerobot_suture.runtime.calibration import CalibrateConfig, run_calibration

        cfg = self.cfg
        run_calibration(
            CalibrateConfig(
                policy=PolicyPathConfig(path=policy),
                dataset_root=Path(cfg.dataset_root),
                calibration_episodes=cfg.calibration_episodes,
                holdout_episodes=cfg.holdout_episodes,
                mode=cfg.calibration_mode,
                alpha=cfg.alpha,
                batch_envs=cfg.batch_envs,
                workers=cfg.workers,
                device=cfg.device,
            )
        )

    def evaluate(self, policy: Path, out: Path, key: str) -> None:
        cfg = self.cfg
        result = evaluate(
            policy, self.env_kwargs, self.test_seeds, cfg.batch_envs, cfg.workers, cfg.device, key
        )
        write_json_atomic(out / "eval.json", result, compact=True)

    # ---- one round of one arm

    def round_dir(self, arm: str, round_: int) -> Path:
        return self.out / arm / f"round_{round_}"

    def spec(self, round_: int) -> col.CollectSpec:
        """The round's collection: fresh seeds per scenario, the same for every arm."""
        seeds = {
            scenario: episode_seeds(
                self.cfg.seed, (round_ - 1) * len(SCENARIOS) + group, self.cfg.collect_episodes
            )
            for group, scenario in enumerate(SCENARIOS)
        }
        return col.CollectSpec(
            self.env_kwargs, seeds, self.expert_config, self.steps_after_success, self.video, self.cfg.watch
        )

    def budget(self, round_: int) -> int:
        """New labelled frames per round for the ungated and bc arms."""
        if self.cfg.frames_per_round is not None:
            return self.cfg.frames_per_round
        return int(read_json(self.round_dir(GATED, round_) / "collect.json")["new_frames"])

    def collect(self, arm: str, round_: int, policy: Path) -> None:
        from lerobot_suture.runtime.policy import GateMode, PolicyRunner

        out = self.round_dir(arm, round_)
        shutil.rmtree(out / "new_data", ignore_errors=True)  # a write a kill interrupted
        spec = self.spec(round_)
        budget = None if arm == GATED else self.budget(round_)
        if arm == BC:
            episodes, runs = col.collect_bc(spec, budget)
        else:
            # The gated arm's collection hands over; the ungated arm's policy keeps control throughout.
            runner = PolicyRunner.from_pretrained(policy, GateMode.of(arm == GATED), self.cfg.device)
            if arm == GATED:
                episodes, runs = col.collect_gated(runner, spec)
            else:
                episodes, runs = col.collect_ungated(runner, spec, budget, self.cfg.seed + round_)
        written = col.write_episodes(
            episodes, out / "new_data", f"local/dagger_{arm}_round_{round_}_new", spec
        )
        available = sum(r["steps"] for r in runs if arm != BC or r["success"])
        if budget is not None and available < budget:
            logger.warning(
                "%s round %d: %d labelled frames for a budget of %d", arm, round_, available, budget
            )
        record = {
            "arm": arm,
            "round": round_,
            "new_frames": col.frame_count(episodes),
            "budget": budget,
            "available_frames": available if arm != GATED else col.frame_count(episodes),
            "new_data": str(written) if written else None,
            "labels": col.label_counts(episodes),
            "seeds": spec.seeds,
            "runs": runs,
        }
        write_json_atomic(out / "collect.json", record, compact=True)

    def aggregate(self, arm: str, round_: int, stats: dict) -> None:
        roots = [self.round_dir(arm, k) / "new_data" for k in range(1, round_ + 1)]
        agg.aggregate(
            self.demonstrations,
            [root for root in roots if root.is_dir()],
            self.round_dir(arm, round_) / "dataset",
            f"local/dagger_{arm}_round_{round_}",
            stats,
            repeats=self.cfg.new_data_repeats,
        )

    def train(self, arm: str, round_: int, policy: Path) -> Path:
        from lerobot_suture.datasets.video import resolve_video_backend
        from lerobot_suture.runtime.training import run_lerobot_train

        cfg = self.cfg
        out = self.round_dir(arm, round_)
        fresh = [
            f"--policy.path={policy}",
            f"--dataset.repo_id=local/dagger_{arm}_round_{round_}",
            "--policy.push_to_hub=false",
            f"--policy.device={cfg.device}",
            f"--policy.optimizer_lr={cfg.lr}",
            f"--policy.scheduler_warmup_steps={cfg.warmup_steps}",
            f"--batch_size={cfg.batch_size}",
            f"--seed={cfg.seed + round_}",
            f"--job_name=dagger_{arm}_round_{round_}",
            f"--num_workers={0 if cfg.toy else 1}",
            f"--log_freq={1 if cfg.toy else 50}",
            "--wandb.enable=false",
        ]
        common = [
            f"--dataset.root={out / 'dataset'}",
            f"--dataset.video_backend={resolve_video_backend()}",
            f"--save_freq={max(1, cfg.finetune_steps // 4)}",
        ]
        return run_lerobot_train(out / "train", fresh, cfg.finetune_steps, common)

    def trained(self, arm: str, round_: int) -> bool:
        from lerobot_suture.runtime.training import checkpoint_step

        last = self.round_dir(arm, round_) / "train" / "checkpoints" / "last"
        return last.is_dir() and checkpoint_step(last) >= self.cfg.finetune_steps

    def run_round(self, arm: str, round_: int, policy: Path, stats: dict) -> Path:
        """The five stages of one round of one arm; returns its policy."""
        out = self.round_dir(arm, round_)
        key = f"{arm}/round_{round_}"
        new_policy = out / "train" / "checkpoints" / "last" / "pretrained_model"
        stage = self.journal.stage
        stage(f"{key}/collect", (out / "collect.json").is_file, lambda: self.collect(arm, round_, policy))
        stage(f"{key}/aggregate", (out / "dataset").is_dir, lambda: self.aggregate(arm, round_, stats))
        stage(f"{key}/train", lambda: self.trained(arm, round_), lambda: self.train(arm, round_, policy))
        self._calibrate_and_evaluate(key, new_policy, out)
        return new_policy

    def run(self) -> dict:
        from lerobot_suture.dagger.report import write_report

        policy0 = self.prepare()
        stats = agg.policy_normalizer_stats(policy0)  # the original demonstrations' normalization, kept
        policies = dict.fromkeys(self.cfg.arm_list, policy0)
        for round_ in range(1, self.cfg.rounds + 1):
            for arm in self.cfg.arm_list:
                policies[arm] = self.run_round(arm, round_, policies[arm], stats)
        self.journal.progress.close()
        table = write_report(self.out, self.cfg.arm_list, self.cfg.rounds, toy=self.cfg.toy)
        return {"ran": self.journal.ran, "skipped": self.journal.skipped, "table": table}


def run_dagger(cfg: DaggerConfig) -> dict:
    """Run (or resume) the loop; returns what ran, what was skipped and the markdown table."""
    Path(cfg.output_dir).mkdir(parents=True, exist_ok=True)
    _check_settings(cfg)
    return DaggerRun(cfg).run()
