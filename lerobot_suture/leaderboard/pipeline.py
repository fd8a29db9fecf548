"""``lerobot-suture leaderboard``: LeRobot's policies and the ensemble on every task, the same test seeds for all.

For each task (``tasks.TASKS``) and each policy (:data:`POLICIES`: LeRobot's own ``act`` and ``diffusion``,
``ensemble_member`` and ``ensemble_diffusion``) it takes a trained checkpoint (``--checkpoints=TASK:POLICY=DIR``)
or makes one from nothing: records the task's dataset recipe (:data:`TASK_RECIPES`) into ``output_dir/data``,
trains the policy's CPU preset on it with the real ``lerobot-train`` (the same training episodes and the same
number of steps for every policy: the task's ensemble preset's), and calibrates the gates of the ensemble and
of its member. Then it evaluates every policy on every condition of its task
(:mod:`lerobot_suture.leaderboard.cells`) and writes ``leaderboard.json``, ``leaderboard.md`` and
``leaderboard.png`` into ``results_dir``.

This module holds the run's config and each stage (record, train, calibrate, and each cell's evaluation);
:mod:`.run` submits them as Ray tasks (:mod:`lerobot_suture.leaderboard.ray_stages`): on this machine by
default, on a cluster with ``--ray_address``. Every finished cell is written at once to ``output_dir/cells/TASK/POLICY/CONDITION.json``
and not run again: an interrupted run, or one whose node died, resumes where it stopped (with the same
flags). Each stage's time lands in the board's ``timings``.

A user's checkpoint joins with ``--policy.path=DIR --policy_name=NAME --tasks=[TASK]``: it is evaluated
on the same cells and its row is added to the board already in ``results_dir`` (nothing is trained).
"""

from __future__ import annotations

import json
import uuid
from dataclasses import dataclass, field
from pathlib import Path

from lerobot_suture.leaderboard import cells
from lerobot_suture.pipelines.stages import code_commit
from lerobot_suture.runtime.config import PolicyPathConfig
from lerobot_suture.sim.shifts import MAGNITUDES, SHIFTS, Shift
from lerobot_suture.sim.tasks import TASK_NAMES, task_spec

REPO_ROOT = Path(__file__).resolve().parents[2]
PRESETS = REPO_ROOT / "policies" / "presets"
TASK_RECIPES = {
    "insertion": (REPO_ROOT / "recipes" / "suture_expert_servo.yaml", PRESETS / "reference.json"),
    "pickup": (REPO_ROOT / "recipes" / "suture_pickup.yaml", PRESETS / "pickup.json"),
    "extraction": (REPO_ROOT / "recipes" / "suture_extraction.yaml", PRESETS / "extraction.json"),
    "running_suture": (REPO_ROOT / "recipes" / "suture_running.yaml", PRESETS / "running_suture.json"),
}
"""Each task's dataset recipe and its ensemble preset (whose dataset episodes and steps every policy uses)."""
POLICIES = ("act", "diffusion", "ensemble_member", "ensemble_diffusion")
POLICY_PRESETS = {"act": PRESETS / "act.json", "diffusion": PRESETS / "diffusion.json"}
"""LeRobot's own policies' CPU presets; the rows of :data:`GATED` train with the task's own preset."""
PRESET_SEED = 1000
"""The training seed of every preset (``seed`` in ``policies/presets/*.json``): the board's rows train with it."""
GATED = {"ensemble_member": ["--policy.n_members=1"], "ensemble_diffusion": []}
"""The rows with a gate to calibrate, trained from the task's ensemble preset with these flags:
``ensemble_member`` is the ensemble's member recipe as a single policy (the same target, backbone and K
samples), so the difference between the two rows is the ensemble's."""


def default_shifts() -> list[str]:
    """Every shift at its smaller magnitude (inside the randomized recipe's range where it has one); the
    larger ones join with ``--shifts`` (:func:`lerobot_suture.sim.shifts.default_shifts` lists both)."""
    return [Shift(name, MAGNITUDES[name][0]).label for name in SHIFTS]


@dataclass
class LeaderboardConfig:
    """Args:
    tasks: the tasks to rank on (default: every task of the env; with ``--policy.path``, name the task(s)
        the checkpoint was trained for).
    policies: which of :data:`POLICIES` to train or take.
    checkpoints: ``TASK:POLICY=DIR`` trained checkpoints to take instead of training (e.g.
        ``insertion:act=outputs/act/train/checkpoints/last/pretrained_model``).
    policy: ``--policy.path=DIR``: a user's checkpoint to add to the board already in ``results_dir``
        (only it is evaluated; nothing is trained); ``--policy.num_inference_steps=S`` /
        ``--policy.uncertainty_samples_per_member=K`` run it with those approximations.
    policy_name: the row's name for ``--policy.path`` (default: the policy's type, with ``S=`` / ``K=``
        when approximated).
    episodes: episodes a cell, >= 1 (50: the LIBERO protocol's count per task).
    shifts: distribution shifts run in the nominal scene, ``NAME@MAGNITUDE`` (default: every shift at its
        smaller magnitude); ``[]`` for the scenarios only. A run that trains or takes the board's policies
        sets the board's shifts, which its summary averages over; a joining row's further shifts add lines
        to its table.
    seed: base of the test seeds (disjoint from recording, calibration and the other commands' seeds).
    batch_envs: envs run in lockstep with one batched policy call, >= 1 (a seed gives the same episode at
        any value).
    ray_address: the Ray cluster to run the stages on (``HOST:PORT`` of its head, or ``auto``); default: a
        Ray instance on this machine, one cell per core. Every node must see ``output_dir`` at the same path.
    train_cpus: cores a training stage reserves (lerobot-train's torch threads and data loader), >= 1.
    cells_per_gpu: with a CUDA ``device``, the cells (and calibrations) that share one GPU, >= 1.
    output_dir: datasets, checkpoints and finished cells (resumable).
    results_dir: where ``leaderboard.json``, ``leaderboard.md`` and ``leaderboard.png`` go.
    device: torch device for calibration and evaluation (training takes the presets').
    train_seeds: further training seeds: each row of ``seeded_rows`` is trained again from each (the board's
        rows train with :data:`PRESET_SEED`), and evaluated on nominal and the task's scenarios only; the board
        gives each such cell's mean and range over the seeds.
    tune: instead of the board, tune each family of ``policies`` on insertion: its configurations
        (:data:`lerobot_suture.leaderboard.tuning.CONFIGURATIONS`) trained like the board's rows and scored on
        validation seeds; writes ``tuning.json``, ``tuning.md`` and each family's chosen preset.
    seeded_rows: ``TASK:POLICY`` rows trained from ``train_seeds`` (default: every policy on insertion, and on
        each other task the two best rows already on the board in ``results_dir``, so run the board first).
    toy: the same pipeline at toy scale (4 recorded episodes, 4 training steps, 2 calibration episodes):
        a smoke test whose figures mean nothing.
    """

    tasks: list[str] | None = None
    policies: list[str] = field(default_factory=lambda: list(POLICIES))
    checkpoints: list[str] = field(default_factory=list)
    policy: PolicyPathConfig = field(default_factory=PolicyPathConfig)
    policy_name: str | None = None
    episodes: int = 50
    shifts: list[str] = field(default_factory=default_shifts)
    seed: int = 7_000_000
    batch_envs: int = 8
    ray_address: str | None = None
    train_cpus: int = 2
    cells_per_gpu: int = 4
    output_dir: Path = Path("outputs/leaderboard")
    results_dir: Path = Path("docs/results/leaderboard")
    device: str = "cpu"
    toy: bool = False
    tune: bool = False
    train_seeds: list[int] = field(default_factory=list)
    seeded_rows: list[str] | None = None

    def __post_init__(self):
        if self.tasks is None:
            if self.policy.path is not None:
                raise ValueError(
                    "`--policy.path` needs `--tasks`: the task(s) the checkpoint was trained for, e.g. "
                    "--tasks='[insertion]'."
                )
            self.tasks = list(TASK_NAMES)
        unknown = sorted(set(self.tasks) - set(TASK_NAMES))
        if unknown or not self.tasks:
            raise ValueError(f"`tasks` must be a non-empty list of {list(TASK_NAMES)}. Got {self.tasks}.")
        unknown = sorted(set(self.policies) - set(POLICIES))
        if unknown:
            raise ValueError(f"`policies` must be among {list(POLICIES)}. Got {unknown}.")
        if min(self.episodes, self.batch_envs, self.train_cpus, self.cells_per_gpu) < 1:
            raise ValueError(
                "`episodes`, `batch_envs`, `train_cpus` and `cells_per_gpu` must be >= 1. Got "
                f"{self.episodes}, {self.batch_envs}, {self.train_cpus}, {self.cells_per_gpu}."
            )
        # Ray's workers do not share this process's working directory.
        self.output_dir = Path(self.output_dir).resolve()
        self.results_dir = Path(self.results_dir).resolve()
        self.shifts = [Shift.parse(s).label for s in self.shifts]  # raises on an unknown shift
        self.taken = parse_checkpoints(self.checkpoints)
        if len(set(self.train_seeds)) != len(self.train_seeds) or PRESET_SEED in self.train_seeds:
            raise ValueError(
                f"`train_seeds` are further training seeds: distinct, and not the presets' own {PRESET_SEED}, "
                f"which trains the board's rows. Got {self.train_seeds}."
            )
        if self.tune and (self.policy.path is not None or self.train_seeds):
            raise ValueError(
                "`tune` trains the families' configurations; pass no --policy.path or --train_seeds."
            )
        if self.train_seeds and self.policy.path is not None:
            raise ValueError(
                "`train_seeds` train the board's rows again; a `--policy.path` row joins as trained."
            )
        for entry in self.seeded_rows or []:
            task, colon, policy = entry.partition(":")
            if not colon or task not in self.tasks or policy not in self.policies:
                raise ValueError(
                    f"`seeded_rows` entries are TASK:POLICY with TASK in --tasks {self.tasks} and POLICY in "
                    f"--policies {self.policies}. Got {entry!r}."
                )
        if self.policy.overrides and self.policy.path is None:
            raise ValueError(
                "`--policy.num_inference_steps` / `--policy.uncertainty_samples_per_member` apply to the "
                "checkpoint of `--policy.path`: pass it (the trained rows run as trained)."
            )
        if self.policy.path is not None and not (Path(self.policy.path) / "config.json").is_file():
            raise FileNotFoundError(
                f"No trained policy at {self.policy.path} (no config.json): pass the pretrained_model directory "
                "of a lerobot-train checkpoint."
            )

    @property
    def cell_gpus(self) -> float:
        """The share of a GPU a cell or a calibration holds: 1 / ``cells_per_gpu`` with a CUDA device, else 0."""
        return 1 / self.cells_per_gpu if self.device.startswith("cuda") else 0


def calibrate_stage(task: str, policy: str) -> str:
    """The key of the calibration of ``policy``'s gate on ``task`` (the ensemble's keeps its first name,
    ``calibrate TASK``, so that boards timed before the member's row read the same)."""
    return f"calibrate {task}" + ("" if policy == "ensemble_diffusion" else f" {policy}")


def parse_checkpoints(entries: list[str]) -> dict[tuple[str, str], Path]:
    """``TASK:POLICY=DIR`` entries as {(task, policy): DIR}; a ValueError names a malformed one."""
    out = {}
    for entry in entries:
        key, sep, path = entry.partition("=")
        task, colon, policy = key.partition(":")
        if not (sep and colon and path) or task not in TASK_NAMES or policy not in POLICIES:
            raise ValueError(
                f"`checkpoints` entries are TASK:POLICY=DIR with TASK in {list(TASK_NAMES)} and POLICY in "
                f"{list(POLICIES)}. Got {entry!r}."
            )
        if not (Path(path) / "config.json").is_file():
            raise FileNotFoundError(f"`checkpoints` entry {entry!r}: no config.json in {path}.")
        out[(task, policy)] = Path(path)
    return out


def train_policy(
    cfg: LeaderboardConfig,
    task: str,
    policy: str,
    dataset_root: Path,
    seed: int | None = None,
    configuration: str | None = None,
    flags: tuple[str, ...] = (),
) -> Path:
    """``lerobot-train`` of ``policy``'s preset on the task's dataset (resumable); its pretrained directory.
    ``seed``: a further training seed (None: the preset's own); ``configuration``: a tuning candidate's name,
    whose ``flags`` go on top of the preset."""
    from lerobot_suture.datasets.split import train_episodes
    from lerobot_suture.datasets.video import resolve_video_backend
    from lerobot_suture.runtime.training import run_lerobot_train

    task_preset = TASK_RECIPES[task][1]
    reference = json.loads(task_preset.read_text())
    preset = task_preset if policy in GATED else POLICY_PRESETS[policy]
    steps = 4 if cfg.toy else int(reference["steps"])
    episodes = train_episodes(dataset_root) if cfg.toy else reference["dataset"]["episodes"]
    fresh = [
        f"--config_path={preset}",
        f"--dataset.repo_id={reference['dataset']['repo_id']}",
        f"--dataset.episodes=[{','.join(str(e) for e in episodes)}]",
        f"--job_name={task}_{policy}" + ("" if seed is None else f"_seed{seed}"),
        *GATED.get(policy, []),
        *([] if seed is None else [f"--seed={seed}"]),
        *flags,
    ]
    if cfg.toy:
        fresh += ["--batch_size=4", "--num_workers=0", "--log_freq=1"]
    common = [
        f"--dataset.root={dataset_root}",
        f"--dataset.video_backend={resolve_video_backend()}",
        f"--save_freq={2 if cfg.toy else reference['save_freq']}",
    ]
    name = policy if configuration is None else f"{policy}~{configuration}"
    out = cfg.output_dir / "train" / task / (name if seed is None else f"{name}_seed{seed}")
    return run_lerobot_train(out, fresh, steps, common)


def row_name(policy_type: str, overrides: dict) -> str:
    """A row's default name: the policy type, and the inference approximations it runs with, if any."""
    short = {"num_inference_steps": "S", "uncertainty_samples_per_member": "K"}
    return policy_type + "".join(f" {short[k]}={v}" for k, v in sorted(overrides.items()))


def cell_path(cfg: LeaderboardConfig, task: str, name: str, condition: str) -> Path:
    """Where the cell of row ``name`` on ``condition`` of ``task`` is written."""
    return cfg.output_dir / "cells" / task / name / f"{condition.replace(':', '_')}.json"


def finished_cell(path: Path, overrides: dict) -> dict | None:
    """The cell at ``path`` if it was run with the same policy ``overrides``; None otherwise."""
    if path.is_file():
        saved = json.loads(path.read_text())
        if saved.get("policy_overrides", {}) == overrides:
            return saved
    return None


_RUNNER: dict = {}  # inside a worker: the last policy loaded, by (directory, its files, device, overrides)


def _runner(policy_dir: Path, device: str, overrides: dict):
    """The policy in ``policy_dir``, loaded once per worker while its files stay the same (a calibration
    written since loads it afresh)."""
    from lerobot_suture.runtime.policy import GateMode, PolicyRunner
    from lerobot_suture.runtime.workers import directory_state

    key = (str(policy_dir), directory_state(str(policy_dir)), device, tuple(sorted(overrides.items())))
    if _RUNNER.get("key") != key:
        _RUNNER.clear()
        _RUNNER.update(
            key=key, runner=PolicyRunner.from_pretrained(policy_dir, GateMode.REPORT, device, overrides)
        )
    return _RUNNER["runner"]


def evaluate_cell(
    cfg: LeaderboardConfig, task: str, name: str, policy_dir: Path, overrides: dict, condition: str, *after
) -> dict:
    """Row ``name``'s cell on ``condition`` of ``task``, written whole to :func:`cell_path` (read back when
    already there). ``after``: the stages it waits for (a calibration)."""
    from lerobot_suture.runtime.policy import env_kwargs_for_policy

    path = cell_path(cfg, task, name, condition)
    cell = finished_cell(path, overrides)
    if cell is not None:
        return cell
    runner = _runner(policy_dir, cfg.device, overrides)
    seeds = cells.condition_seeds(cfg.seed, task, condition, cfg.episodes)
    env_kwargs = env_kwargs_for_policy(runner.policy.config)
    cell = cells.summarize_cell(
        *cells.cell_episodes(runner, env_kwargs, task, condition, seeds, cfg.batch_envs),
        throws=task_spec(task).throws,
    )
    cell["policy_path"] = str(policy_dir)
    cell["code_commit"] = code_commit()
    if overrides:
        cell["policy_overrides"] = overrides
    path.parent.mkdir(parents=True, exist_ok=True)
    tmp = path.with_name(f"{path.stem}.{uuid.uuid4().hex}.tmp")  # a retried stage never shares it
    tmp.write_text(json.dumps(cell, separators=(",", ":")))
    tmp.replace(path)  # a cell is on disk whole or not at all
    return cell
