"""``lerobot-suture benchmark-ood``: the failure detectors side by side, on the same rollouts.

The policy is rolled out once per part, with its gate reporting only (``GateMode.REPORT``) and the
features every detector reads captured at each prediction (:meth:`enable_feature_capture`: the members'
samples, their observation embeddings, further chunks of member 0), without changing its actions:

    fit               nominal, validation seeds     what the learned detectors (Mahalanobis, RND) fit
    calibration       nominal, validation seeds     each detector's per-episode threshold at ``alpha``
    nominal           nominal, test seeds           the negatives: AUROC, false alarms
    <four scenarios>  the paper's, test seeds       the positives (the experiments' seeds)
    <shifts>          nominal under a shift of      each at its magnitude (``lerobot_suture.sim.shifts``):
                      appearance, sensing,          does the detector flag the runs that fail and spare
                      geometry or dynamics          those that succeed?

Each part is saved under ``parts/`` when it is done and reused on the next run with the same settings, so
an interrupted benchmark resumes at the part it was in. The parts do not depend on the detectors: adding
one rescores the saved rollouts. Every detector is then fitted on ``fit``, thresholded on
``calibration`` with the conformal per-episode quantile the gate uses, and scored on the test parts.
Writes ``detectors.md`` (tables), ``detectors.json`` (every number), ``detector_<name>.png`` (score
traces per scenario against the nominal ones, with the threshold) and ``shifts.png`` (the policy's success
and each detector's flags per shift). With ``--dataset_root`` of a dataset recorded under appearance
randomization, the fit and calibration parts are rolled out under its appearance ranges (the training
distribution), as ``lerobot-suture calibrate`` does.

Each detector also reports where its nominal alarms fall: before ``approach_steps`` (while the needle is
carried to the throw, where a policy trained on two demonstrated approaches has to choose one) or after.
"""

from __future__ import annotations

import json
import logging
from dataclasses import asdict, dataclass, field
from pathlib import Path

import numpy as np
from tqdm import tqdm

from lerobot_suture.detectors import DETECTOR_NAMES
from lerobot_suture.experiments.report import json_default
from lerobot_suture.runtime.calibration import dataset_appearance
from lerobot_suture.runtime.config import RolloutCommandConfig
from lerobot_suture.runtime.policy import GateMode, env_kwargs_for_policy, reporting_runner
from lerobot_suture.runtime.rollout import EpisodeLog, StepLog, make_scenario_env, rollout_seeds
from lerobot_suture.runtime.seeds import episode_seeds
from lerobot_suture.safety.ood.calibration import min_calibration_episodes
from lerobot_suture.sim.shifts import SHIFTS, Shift, default_shifts
from lerobot_suture_studies.benchmark_ood_report import plot_detector, plot_shifts, render_tables
from lerobot_suture_studies.benchmark_ood_scoring import SCENARIOS, evaluate_detector

logger = logging.getLogger(__name__)

PARTS_DIR = "parts"
SHIFT_GROUP = 100  # test-seed group of the first shift part, apart from the scenarios' groups


@dataclass
class BenchmarkOODConfig(RolloutCommandConfig):
    """Args (and those of :class:`~lerobot_suture.runtime.config.RolloutCommandConfig`; the policy is a
    trained ensemble, no calibration needed):
    output_dir: where ``detectors.md``, ``detectors.json``, the figures and ``parts/`` go.
    validation_seed: base seed of the fit and calibration parts (apart from recording, calibration and
        score-study seeds).
    test_seed: base seed of the nominal and scenario parts (the experiments' test seeds).
    fit_episodes: nominal episodes the learned detectors are fitted on, >= 1.
    calibration_episodes: nominal episodes each threshold is fitted on (>= (1 - alpha) / alpha).
    nominal_episodes: nominal test episodes (negatives), >= 1.
    runs_per_scenario: runs of each of the four scenarios, >= 1.
    shifts: shifts run in the nominal scenario, each ``NAME@MAGNITUDE`` (``lerobot_suture.sim.shifts``;
        default: every shift at two magnitudes); ``[]`` for the paper's scenarios only.
    runs_per_shift: runs under each shift, >= 1.
    dataset_root: the policy's training dataset; when it was recorded with appearance randomization, the
        fit and calibration parts use its appearance ranges.
    approach_steps: control steps from the start counted as the approach, where two demonstrated
        strategies split (the two-sided recipe's detour and approach take about this long).
    alpha: per-episode false-alarm rate each threshold is fitted for, in (0, 0.5).
    single_member_samples: chunks member 0 draws on its own per prediction for the aleatoric-only
        detector, >= 2; 0 reads member 0's own chunks of the ensemble prediction instead (no extra cost;
        needs the policy's ``uncertainty_samples_per_member`` >= 2).
    detectors: which detectors to compare (all by default).
    """

    output_dir: Path = Path("outputs/benchmark_ood")
    validation_seed: int = 1_700_000
    test_seed: int = 2_000_000
    fit_episodes: int = 20
    calibration_episodes: int = 40
    nominal_episodes: int = 40
    runs_per_scenario: int = 12
    shifts: list[str] = field(default_factory=lambda: [s.label for s in default_shifts()])
    runs_per_shift: int = 10
    dataset_root: Path | None = None
    approach_steps: int = 20
    alpha: float = 0.05
    single_member_samples: int = 0
    detectors: list[str] = field(default_factory=lambda: list(DETECTOR_NAMES))

    def __post_init__(self):
        super().__post_init__()
        if self.workers != 1:
            raise ValueError(
                f"`workers` must be 1 here (the detectors read every prediction's features in this process). Got {self.workers}."
            )
        for key in ("fit_episodes", "nominal_episodes", "runs_per_scenario", "runs_per_shift"):
            if getattr(self, key) < 1:
                raise ValueError(f"`{key}` must be >= 1. Got {getattr(self, key)}.")
        if self.single_member_samples < 0 or self.single_member_samples == 1:
            raise ValueError(
                f"`single_member_samples` must be 0 (member 0's own chunks) or >= 2. Got "
                f"{self.single_member_samples}."
            )
        unknown = [d for d in self.detectors if d not in DETECTOR_NAMES]
        if unknown or not self.detectors:
            raise ValueError(f"`detectors` must name some of {list(DETECTOR_NAMES)}. Got {self.detectors}.")
        parsed = [Shift.parse(s) for s in self.shifts]  # raises on an unknown name or magnitude
        labels = [s.label for s in parsed]
        if len(set(labels)) != len(labels):
            raise ValueError(f"`shifts` lists a shift twice: {labels}.")
        self.shifts = labels
        if self.approach_steps < 1:
            raise ValueError(f"`approach_steps` must be >= 1. Got {self.approach_steps}.")
        needed = min_calibration_episodes(self.alpha)
        if self.calibration_episodes < needed:
            raise ValueError(
                f"A per-episode threshold at alpha={self.alpha} needs `calibration_episodes` >= {needed}. "
                f"Got {self.calibration_episodes}; raise it or raise `--alpha`."
            )

    def parts(self) -> list[tuple[str, str, list[int], Shift | None]]:
        """(part name, scenario, seeds, shift) of every rollout part, in the order they run."""
        parts = [
            ("fit", "nominal", episode_seeds(self.validation_seed, 0, self.fit_episodes), None),
            (
                "calibration",
                "nominal",
                episode_seeds(self.validation_seed, 1, self.calibration_episodes),
                None,
            ),
            ("nominal", "nominal", episode_seeds(self.test_seed, 0, self.nominal_episodes), None),
        ]
        # The experiments' groups: the same test seeds as `lerobot-suture experiments`.
        parts += [
            (scenario, scenario, episode_seeds(self.test_seed, group, self.runs_per_scenario), None)
            for group, scenario in enumerate(SCENARIOS, start=2)
        ]
        # Every magnitude of a shift on the same seeds (the magnitudes differ, not the scenes), and a
        # family's seeds the same whichever shifts are listed.
        for label in self.shifts:
            shift = Shift.parse(label)
            seeds = episode_seeds(self.test_seed, SHIFT_GROUP + SHIFTS.index(shift.name), self.runs_per_shift)
            parts.append((label, "nominal", seeds, shift))
        return parts


def _numpy(tensor) -> np.ndarray:
    return tensor.detach().float().cpu().numpy()


# ---- capture ------------------------------------------------------------------------------------------


class CapturingRunner:
    """Wraps a :class:`~lerobot_suture.runtime.policy.PolicyRunner` for the rollout functions and keeps, at
    each new prediction, every env's features; :meth:`take` hands them out per episode."""

    def __init__(self, runner, single_member_samples: int, seed: int = 0):
        if runner.gate is not GateMode.REPORT:
            raise ValueError("The benchmark runs the gate in reporting mode: pass a GateMode.REPORT runner.")
        self.runner, self.policy = runner, runner.policy
        self.policy.enable_feature_capture(single_member_samples, seed)
        self.action_start = self.policy.config.n_obs_steps - 1
        self._batch: list[tuple[int, dict[str, np.ndarray]]] = []  # (call index, (B, ...) arrays)
        self._calls = 0
        self.batches: list[list[tuple[int, dict[str, np.ndarray]]]] = []

    def reset(self, seeds=None) -> None:
        self._close_batch()
        self.runner.reset(seeds=seeds)

    def act_batch(self, observations: list[dict], tasks=None) -> np.ndarray:
        actions = self.runner.act_batch(observations, tasks)
        if self.policy.ood_status(0)["new_prediction"]:
            features = self.policy.last_features
            samples = self.policy.last_prediction.normalized.samples  # (B, N, K, T, A)
            single = features.get("single_member_samples", samples[:, 0])  # (B, K', T, A)
            self._batch.append(
                (
                    self._calls,
                    {
                        "samples": _numpy(samples),
                        "embedding": _numpy(features["embedding"]),  # (B, N, G)
                        "single_member_samples": _numpy(single),
                    },
                )
            )
        self._calls += 1
        return actions

    def _close_batch(self) -> None:
        if self._batch:
            self.batches.append(self._batch)
        self._batch, self._calls = [], 0

    def take(self, logs: list[EpisodeLog]) -> dict[str, np.ndarray]:
        """The predictions of ``logs`` (the rollouts since the last ``take``, in order) as flat arrays:
        ``episode`` (P,), ``step`` (P,), and each feature (P, ...). An episode that ended early keeps its
        row of the batch; its predictions are those made before its last step."""
        self._close_batch()
        batches, self.batches = self.batches, []
        rows = [(b, r) for b, batch in enumerate(batches) for r in range(batch[0][1]["samples"].shape[0])]
        if len(rows) != len(logs):
            raise ValueError(f"{len(logs)} episodes were logged but {len(rows)} were captured.")
        out: dict[str, list] = {"episode": [], "step": [], "samples": [], "embedding": [], "single": []}
        for e, (log, (b, r)) in enumerate(zip(logs, rows, strict=True)):
            for step, arrays in batches[b]:
                if step >= len(log.steps):
                    break
                out["episode"].append(e)
                out["step"].append(step)
                out["samples"].append(arrays["samples"][r])
                out["embedding"].append(arrays["embedding"][r])
                out["single"].append(arrays["single_member_samples"][r])
        return {k: np.asarray(v) for k, v in out.items()}


# ---- parts --------------------------------------------------------------------------------------------


def _log_from_dict(d: dict) -> EpisodeLog:
    return EpisodeLog(**{**d, "steps": [StepLog(**s) for s in d["steps"]]})


def load_part(directory: Path, name: str, meta: dict) -> tuple[list[EpisodeLog], dict] | None:
    """A saved part, or None when it is missing or was run with other settings."""
    meta_path, arrays_path = directory / f"{name}.json", directory / f"{name}.npz"
    if not (meta_path.exists() and arrays_path.exists()):
        return None
    saved = json.loads(meta_path.read_text())
    if saved["meta"] != meta:
        logger.info("Part %s was run with other settings; running it again.", name)
        return None
    with np.load(arrays_path) as arrays:
        captured = {k: arrays[k] for k in arrays.files}
    return [_log_from_dict(d) for d in saved["logs"]], captured


def save_part(directory: Path, name: str, meta: dict, logs: list[EpisodeLog], captured: dict) -> None:
    """Arrays first, then the JSON that marks the part done (a crash in between leaves it to rerun)."""
    directory.mkdir(parents=True, exist_ok=True)
    np.savez_compressed(directory / f"{name}.npz", **captured)
    tmp = directory / f"{name}.json.tmp"
    tmp.write_text(json.dumps({"meta": meta, "logs": [asdict(log) for log in logs]}, default=json_default))
    tmp.replace(directory / f"{name}.json")


# ---- the command --------------------------------------------------------------------------------------


def policy_fingerprint(directory: Path) -> dict[str, list[int]]:
    """Size and modification time of each file of a policy directory: a policy retrained or recalibrated
    in place no longer matches the saved parts, which are then run again."""
    return {
        f.name: [f.stat().st_size, f.stat().st_mtime_ns] for f in sorted(directory.iterdir()) if f.is_file()
    }


def run_benchmark(cfg: BenchmarkOODConfig) -> dict:
    cfg.output_dir.mkdir(parents=True, exist_ok=True)
    base = reporting_runner(
        cfg.policy.path,
        cfg.device,
        needs="enable_feature_capture",
        needed_for="the benchmark needs an ensemble_diffusion policy, whose members' samples and embeddings "
        "the detectors read.",
        overrides=cfg.policy.overrides,
    )
    k = base.policy.config.uncertainty_samples_per_member
    if cfg.single_member_samples == 0 and k < 2 and "single_member_spread" in cfg.detectors:
        raise ValueError(
            f"The policy draws {k} chunk per member, too few for one member's spread: pass "
            "`--single_member_samples=8` (member 0 then draws 8 more) or leave out `single_member_spread`."
        )
    runner = CapturingRunner(base, cfg.single_member_samples)
    env_kwargs = env_kwargs_for_policy(base.policy.config)
    training_look = dataset_appearance(cfg.dataset_root)
    parts_dir = cfg.output_dir / PARTS_DIR
    parts = {}
    for name, scenario, seeds, shift in cfg.parts():
        kwargs = {**env_kwargs, **training_look} if name in ("fit", "calibration") else env_kwargs
        # What the rollouts depend on; a part saved under other settings is run again.
        meta = {
            "policy_path": str(Path(cfg.policy.path).resolve()),
            "policy_files": policy_fingerprint(Path(cfg.policy.path)),
            "scenario": scenario,
            "seeds": seeds,
            "batch_envs": cfg.batch_envs,
            "single_member_samples": cfg.single_member_samples,
            "device": cfg.device,
        }
        if cfg.policy.overrides:  # absent as trained: parts saved before overrides existed still match
            meta["policy_overrides"] = cfg.policy.overrides
        if "appearance" in kwargs:  # absent otherwise: parts saved before appearance existed still match
            meta["appearance"] = kwargs["appearance"]
        if shift is not None:
            meta["shift"] = shift.label
        loaded = load_part(parts_dir, name, meta)
        if loaded is None:
            logs = rollout_seeds(
                lambda scenario=scenario, kwargs=kwargs, shift=shift: make_scenario_env(
                    kwargs, scenario, shift=shift
                ),
                runner,
                seeds,
                cfg.batch_envs,
                desc=f"{name} ({scenario})",
            )
            captured = runner.take(logs)
            save_part(parts_dir, name, meta, logs, captured)
            loaded = (logs, captured)
        else:
            logger.info("Part %s: reusing %d saved episodes.", name, len(loaded[0]))
        parts[name] = loaded
    action_start = base.policy.config.n_obs_steps - 1
    state = base.policy.config.robot_state_feature
    state_dim = None if state is None else int(state.shape[0])
    per_detector = {}
    for name in tqdm(cfg.detectors, desc="detectors", unit="detector"):
        try:
            per_detector[name] = evaluate_detector(
                name, parts, action_start, cfg.alpha, cfg.shifts, cfg.approach_steps, state_dim
            )
        except ValueError as exc:  # one detector failing costs its row, not the rollouts
            logger.warning("Detector %s: %s", name, exc)
            per_detector[name] = {"error": str(exc)}
    figures = {}
    for name, result in per_detector.items():
        if "error" not in result:
            figures[name] = plot_detector(name, result, cfg.output_dir / f"detector_{name}.png").name
    if cfg.shifts and any("error" not in r for r in per_detector.values()):
        figures["shifts"] = plot_shifts(per_detector, cfg.shifts, cfg.output_dir / "shifts.png").name
    result = {
        "policy_path": str(cfg.policy.path),
        "alpha": cfg.alpha,
        "dataset_root": None if cfg.dataset_root is None else str(cfg.dataset_root),
        "training_appearance": training_look.get("appearance"),
        "shifts": cfg.shifts,
        "approach_steps": cfg.approach_steps,
        "validation_seed": cfg.validation_seed,
        "test_seed": cfg.test_seed,
        "episodes": {name: len(logs) for name, (logs, _) in parts.items()},
        "policy_success_rate": {
            name: float(np.mean([log.success for log in logs])) for name, (logs, _) in parts.items()
        },
        "figures": figures,
        "detectors": {
            name: {k: v for k, v in r.items() if k != "traces"} for name, r in per_detector.items()
        },
    }
    (cfg.output_dir / "detectors.json").write_text(
        json.dumps(result, separators=(",", ":"), default=json_default)
    )
    (cfg.output_dir / "detectors.md").write_text(render_tables(result))
    return result
