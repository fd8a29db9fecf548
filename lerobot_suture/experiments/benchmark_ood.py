"""``lerobot-suture benchmark-ood``: the failure detectors side by side, on the same rollouts.

The policy is rolled out once per part, with its gate reporting only (``ood.enforce`` off) and the
features every detector reads captured at each prediction (:meth:`enable_feature_capture`: the members'
samples, their observation embeddings, further chunks of member 0), without changing its actions:

    fit               nominal, validation seeds     what the learned detectors (Mahalanobis, RND) fit
    calibration       nominal, validation seeds     each detector's per-episode threshold at ``alpha``
    nominal           nominal, test seeds           the negatives: AUROC, false alarms
    <four scenarios>  the paper's, test seeds       the positives (the experiments' seeds)

Each part is saved under ``parts/`` when it is done and reused on the next run with the same settings, so
an interrupted benchmark resumes at the part it was in. The parts do not depend on the detectors: adding
one rescores the saved rollouts. Every detector is then fitted on ``fit``, thresholded on
``calibration`` with the conformal per-episode quantile the gate uses, and scored on the test parts.
Writes ``detectors.md`` (tables), ``detectors.json`` (every number) and ``detector_<name>.png`` (score
traces per scenario against the nominal ones, with the threshold).
"""

from __future__ import annotations

import json
import logging
import math
import time
from dataclasses import asdict, dataclass, field, replace
from pathlib import Path

import draccus
import numpy as np
from tqdm import tqdm

from lerobot_suture.calibrate import PolicyPathConfig
from lerobot_suture.detectors import DETECTOR_NAMES, PredictionFeatures, make_detector, timed_scores
from lerobot_suture.experiments import metrics
from lerobot_suture.experiments.runner import EXPERIMENTS, episode_seeds, json_default, ood_metrics
from lerobot_suture.rollout import EpisodeLog, StepLog, make_scenario_env, rollout_seeds
from lerobot_suture.safety.ood.calibration import conformal_episode_threshold, min_calibration_episodes

logger = logging.getLogger(__name__)

PARTS_DIR = "parts"
SCENARIOS = tuple(scenario for _, scenario, _ in EXPERIMENTS)


@dataclass
class BenchmarkOODConfig:
    """Args:
    policy: ``--policy.path=DIR``, a trained ensemble (no calibration needed).
    output_dir: where ``detectors.md``, ``detectors.json``, the figures and ``parts/`` go.
    validation_seed: base seed of the fit and calibration parts (apart from recording, calibration and
        score-study seeds).
    test_seed: base seed of the nominal and scenario parts (the experiments' test seeds).
    fit_episodes: nominal episodes the learned detectors are fitted on, >= 1.
    calibration_episodes: nominal episodes each threshold is fitted on (>= (1 - alpha) / alpha).
    nominal_episodes: nominal test episodes (negatives), >= 1.
    runs_per_scenario: runs of each of the four scenarios, >= 1.
    alpha: per-episode false-alarm rate each threshold is fitted for, in (0, 0.5).
    single_member_samples: chunks member 0 draws on its own per prediction for the aleatoric-only
        detector, >= 2; 0 reads member 0's own chunks of the ensemble prediction instead (no extra cost;
        needs the policy's ``uncertainty_samples_per_member`` >= 2).
    detectors: which detectors to compare (all by default).
    batch_envs: envs run in lockstep with one batched policy call per step, >= 1.
    device: torch device of the policy.
    """

    policy: PolicyPathConfig = field(default_factory=PolicyPathConfig)
    output_dir: Path = Path("outputs/benchmark_ood")
    validation_seed: int = 1_700_000
    test_seed: int = 2_000_000
    fit_episodes: int = 20
    calibration_episodes: int = 40
    nominal_episodes: int = 40
    runs_per_scenario: int = 12
    alpha: float = 0.05
    single_member_samples: int = 0
    detectors: list[str] = field(default_factory=lambda: list(DETECTOR_NAMES))
    batch_envs: int = 8
    device: str = "cpu"

    def __post_init__(self):
        if self.policy.path is None:
            raise ValueError("`--policy.path` is required: a trained ensemble's pretrained_model directory.")
        for key in ("fit_episodes", "nominal_episodes", "runs_per_scenario", "batch_envs"):
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
        needed = min_calibration_episodes(self.alpha)
        if self.calibration_episodes < needed:
            raise ValueError(
                f"A per-episode threshold at alpha={self.alpha} needs `calibration_episodes` >= {needed}. "
                f"Got {self.calibration_episodes}; raise it or raise `--alpha`."
            )

    def parts(self) -> list[tuple[str, str, list[int]]]:
        """(part name, scenario, seeds) of every rollout part, in the order they run."""
        parts = [
            ("fit", "nominal", episode_seeds(self.validation_seed, 0, self.fit_episodes)),
            ("calibration", "nominal", episode_seeds(self.validation_seed, 1, self.calibration_episodes)),
            ("nominal", "nominal", episode_seeds(self.test_seed, 0, self.nominal_episodes)),
        ]
        # The experiments' groups: the same test seeds as `lerobot-suture experiments`.
        return parts + [
            (scenario, scenario, episode_seeds(self.test_seed, group, self.runs_per_scenario))
            for group, scenario in enumerate(SCENARIOS, start=2)
        ]


# ---- capture ------------------------------------------------------------------------------------------


class CapturingRunner:
    """Wraps a :class:`~lerobot_suture.policy_runner.PolicyRunner` for the rollout functions and keeps, at
    each new prediction, every env's features; :meth:`take` hands them out per episode."""

    def __init__(self, runner, single_member_samples: int, seed: int = 0):
        if runner.policy.config.ood.enforce:
            raise ValueError("The benchmark runs the gate in reporting mode: set `ood.enforce` to false.")
        self.runner, self.policy = runner, runner.policy
        self.policy.enable_feature_capture(single_member_samples, seed)
        self.action_start = self.policy.config.n_obs_steps - 1
        self._batch: list[tuple[int, dict[str, np.ndarray]]] = []  # (call index, (B, ...) arrays)
        self._calls = 0
        self.batches: list[list[tuple[int, dict[str, np.ndarray]]]] = []

    def reset(self) -> None:
        self._close_batch()
        self.runner.reset()

    def act_batch(self, observations: list[dict]) -> np.ndarray:
        actions = self.runner.act_batch(observations)
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


def _numpy(tensor) -> np.ndarray:
    return tensor.detach().float().cpu().numpy()


def prediction_features(captured: dict[str, np.ndarray], action_start: int) -> list[PredictionFeatures]:
    """One :class:`PredictionFeatures` per captured prediction, each linked to its episode's previous one."""
    out = []
    for i in range(len(captured["episode"])):
        first = i == 0 or captured["episode"][i - 1] != captured["episode"][i]
        out.append(
            PredictionFeatures(
                samples=captured["samples"][i],
                action_start=action_start,
                embedding=captured["embedding"][i],
                single_member_samples=captured["single"][i],
                previous_samples=None if first else captured["samples"][i - 1],
                shift=None if first else int(captured["step"][i] - captured["step"][i - 1]),
            )
        )
    return out


def hold_scores(pred_steps: np.ndarray, pred_scores: np.ndarray, n_steps: int) -> np.ndarray:
    """Per control step, the score of the latest prediction at or before it (as the gate holds it):
    (n_steps,) from predictions made at ``pred_steps`` (P,), ascending, the first at step 0."""
    if len(pred_steps) == 0 or pred_steps[0] != 0:
        raise ValueError("An episode's first prediction is made at its first control step.")
    index = np.searchsorted(pred_steps, np.arange(n_steps), side="right") - 1  # (n_steps,)
    return np.asarray(pred_scores, dtype=np.float64)[index]


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


# ---- scoring and metrics ------------------------------------------------------------------------------


def score_part(detector, logs: list[EpisodeLog], captured: dict, action_start: int) -> tuple[list, float]:
    """Per episode of a part, its held per-step scores; and the detector's seconds per prediction."""
    scores, seconds = timed_scores(detector, prediction_features(captured, action_start))
    out = []
    for e, log in enumerate(logs):
        mine = captured["episode"] == e
        out.append(hold_scores(captured["step"][mine], scores[mine], len(log.steps)))
    return out, seconds


def with_detector(log: EpisodeLog, scores: np.ndarray, threshold: float) -> EpisodeLog:
    """``log`` with the detector's scores and its latched per-episode alarms (running max > threshold)."""
    alarms = np.fmax.accumulate(scores) > threshold
    steps = [
        replace(s, score=float(x), ood=bool(a), threshold=threshold)
        for s, x, a in zip(log.steps, scores, alarms, strict=True)
    ]
    return replace(log, steps=steps)


def _failure_step(log: EpisodeLog) -> int | None:
    return None if log.success else len(log.steps) - 1


def scenario_metrics(nominal: list[EpisodeLog], runs: list[EpisodeLog]) -> dict:
    """The experiments' O.O.D. metrics plus false alarms before the onset and failure prediction."""
    m = ood_metrics(nominal, runs)
    early = [
        log.first_alarm_step is not None and (log.onset_step is None or log.first_alarm_step < log.onset_step)
        for log in runs
    ]
    m["false_alarm_before_onset_per_episode"] = float(np.mean(early)) if runs else math.nan
    episodes = nominal + runs
    m["failure_prediction_balanced_accuracy"] = metrics.failure_prediction_balanced_accuracy(
        [log.first_alarm_step for log in episodes], [_failure_step(log) for log in episodes]
    )
    m["failed_runs"] = sum(not log.success for log in runs)
    return m


def evaluate_detector(
    name: str, parts: dict[str, tuple[list[EpisodeLog], dict]], action_start: int, alpha: float
) -> dict:
    """One detector: fitted on ``fit``, thresholded on ``calibration`` at per-episode level ``alpha``,
    measured on the test parts."""
    detector = make_detector(name)
    fit_logs, fit_captured = parts["fit"]
    start = time.perf_counter()
    detector.fit(prediction_features(fit_captured, action_start))
    fit_seconds = time.perf_counter() - start
    calibration, _ = score_part(detector, *parts["calibration"], action_start)
    threshold = conformal_episode_threshold([s.max() for s in calibration], alpha)
    seconds, predictions, control_steps = 0.0, 0, 0
    scored: dict[str, list[EpisodeLog]] = {}
    for part in ("nominal", *SCENARIOS):
        logs, captured = parts[part]
        per_episode, per_call = score_part(detector, logs, captured, action_start)
        seconds += per_call * len(captured["episode"])
        predictions += len(captured["episode"])
        control_steps += sum(len(log.steps) for log in logs)
        scored[part] = [with_detector(log, s, threshold) for log, s in zip(logs, per_episode, strict=True)]
    nominal = scored["nominal"]
    result = {
        "threshold": threshold,
        "false_alarms": metrics.alarm_rates([[s.ood for s in log.steps] for log in nominal]),
        "cost": {
            "ms_per_prediction": 1e3 * seconds / max(predictions, 1),
            # The score is computed at new predictions only and held in between.
            "ms_per_control_step": 1e3 * seconds / max(control_steps, 1),
            "fit_s": fit_seconds,
        },
        "scenarios": {s: scenario_metrics(nominal, scored[s]) for s in SCENARIOS},
    }
    result["mean_auroc"] = _mean([m["auroc"] for m in result["scenarios"].values()])
    result["mean_auroc_common_steps"] = _mean([m["auroc_common_steps"] for m in result["scenarios"].values()])
    result["traces"] = {
        part: [
            {"scores": log.scores.tolist(), "onset": log.onset_step, "success": log.success} for log in logs
        ]
        for part, logs in scored.items()
    }
    return result


def _mean(values: list[float]) -> float:
    finite = [v for v in values if v is not None and not math.isnan(v)]
    return float(np.mean(finite)) if finite else math.nan


# ---- the command --------------------------------------------------------------------------------------


def policy_fingerprint(directory: Path) -> dict[str, list[int]]:
    """Size and modification time of each file of a policy directory: a policy retrained or recalibrated
    in place no longer matches the saved parts, which are then run again."""
    return {
        f.name: [f.stat().st_size, f.stat().st_mtime_ns] for f in sorted(directory.iterdir()) if f.is_file()
    }


def run_benchmark(cfg: BenchmarkOODConfig) -> dict:
    from lerobot_suture.policy_runner import env_kwargs_for_policy, reporting_runner

    cfg.output_dir.mkdir(parents=True, exist_ok=True)
    base = reporting_runner(
        cfg.policy.path,
        cfg.device,
        needs="enable_feature_capture",
        needed_for="the benchmark needs an ensemble_diffusion policy, whose members' samples and embeddings "
        "the detectors read.",
    )
    k = base.policy.config.uncertainty_samples_per_member
    if cfg.single_member_samples == 0 and k < 2 and "single_member_spread" in cfg.detectors:
        raise ValueError(
            f"The policy draws {k} chunk per member, too few for one member's spread: pass "
            "`--single_member_samples=8` (member 0 then draws 8 more) or leave out `single_member_spread`."
        )
    runner = CapturingRunner(base, cfg.single_member_samples)
    env_kwargs = env_kwargs_for_policy(base.policy.config)
    parts_dir = cfg.output_dir / PARTS_DIR
    parts = {}
    for name, scenario, seeds in cfg.parts():
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
        loaded = load_part(parts_dir, name, meta)
        if loaded is None:
            logs = rollout_seeds(
                lambda scenario=scenario: make_scenario_env(env_kwargs, scenario),
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
    per_detector = {}
    for name in tqdm(cfg.detectors, desc="detectors", unit="detector"):
        try:
            per_detector[name] = evaluate_detector(name, parts, action_start, cfg.alpha)
        except ValueError as exc:  # one detector failing costs its row, not the rollouts
            logger.warning("Detector %s: %s", name, exc)
            per_detector[name] = {"error": str(exc)}
    figures = {}
    for name, result in per_detector.items():
        if "error" not in result:
            figures[name] = plot_detector(name, result, cfg.output_dir / f"detector_{name}.png").name
    result = {
        "policy_path": str(cfg.policy.path),
        "alpha": cfg.alpha,
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
    (cfg.output_dir / "detectors.json").write_text(json.dumps(result, indent=2, default=json_default))
    (cfg.output_dir / "detectors.md").write_text(render_tables(result))
    return result


def _fmt(x, digits: int = 3) -> str:
    return "n/a" if x is None or (isinstance(x, float) and math.isnan(x)) else f"{x:.{digits}f}"


def _delay(summary: dict) -> str:
    return "none" if not summary["n"] else f"{summary['median']:.0f} ({summary['n']})"


def render_tables(result: dict) -> str:
    """``detectors.md``: a summary row per detector, then one detectors x metrics table per scenario."""
    episodes = result["episodes"]
    lines = [
        f"# Failure detectors: {result['policy_path']}",
        "",
        f"Fitted on {episodes['fit']} nominal episodes and thresholded on {episodes['calibration']} more "
        f"(validation seeds from {result['validation_seed']}; per-episode conformal threshold at alpha = "
        f"{result['alpha']}); measured on {episodes['nominal']} nominal episodes and the paper's four "
        f"scenarios (test seeds from {result['test_seed']}). Cost: the detector's own scoring time, on top of "
        "the policy's inference (the score is computed at each new prediction and held in between).",
        "",
        "| detector | false alarms / nominal episode | mean AUROC | mean AUROC (common steps) "
        "| ms / prediction | ms / control step | fit (s) |",
        "|---|---|---|---|---|---|---|",
    ]
    detectors = result["detectors"]
    for name, r in detectors.items():
        if "error" in r:
            lines.append(f"| {name} | failed: {r['error']} | | | | | |")
            continue
        c = r["cost"]
        lines.append(
            f"| {name} | {_fmt(r['false_alarms']['per_episode'], 2)} | {_fmt(r['mean_auroc'])} | "
            f"{_fmt(r['mean_auroc_common_steps'])} | {_fmt(c['ms_per_prediction'], 2)} | "
            f"{_fmt(c['ms_per_control_step'], 3)} | {_fmt(c['fit_s'], 2)} |"
        )
    for scenario in SCENARIOS:
        lines += [
            "",
            f"## {scenario} ({episodes[scenario]} runs, policy success "
            f"{_fmt(result['policy_success_rate'][scenario], 2)})",
            "",
            "| detector | AUROC | AUROC (common steps) | TPR at threshold | false alarms before onset / episode "
            "| median delay, steps (detected) | failure-prediction balanced accuracy |",
            "|---|---|---|---|---|---|---|",
        ]
        for name, r in detectors.items():
            if "error" in r:
                continue
            m = r["scenarios"][scenario]
            lines.append(
                f"| {name} | {_fmt(m['auroc'])} | {_fmt(m['auroc_common_steps'])} | "
                f"{_fmt(m['tpr_at_threshold'], 2)} | {_fmt(m['false_alarm_before_onset_per_episode'], 2)} | "
                f"{_delay(m['detection_delay_steps'])} | {_fmt(m['failure_prediction_balanced_accuracy'])} |"
            )
    return "\n".join(lines) + "\n"


def plot_detector(name: str, result: dict, path: Path) -> Path:
    """One panel per scenario: the detector's held scores over control steps, nominal test episodes in
    grey, scenario runs in colour (red: failed, blue: succeeded), onsets as dots, the threshold dashed."""
    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    traces = result["traces"]
    fig, axes = plt.subplots(2, 2, figsize=(10, 6.5), sharey=True)
    for ax, scenario in zip(axes.flat, SCENARIOS, strict=True):
        for run in traces["nominal"]:
            ax.plot(run["scores"], color="0.6", lw=0.8, alpha=0.6)
        for run in traces[scenario]:
            colour = "tab:blue" if run["success"] else "tab:red"
            ax.plot(run["scores"], color=colour, lw=1.0)
            if run["onset"] is not None:
                ax.plot(run["onset"], run["scores"][run["onset"]], "o", color=colour, ms=4)
        ax.axhline(result["threshold"], color="k", ls="--", lw=1.0, label="threshold")
        m = result["scenarios"][scenario]
        ax.set_title(
            f"{scenario}: AUROC {_fmt(m['auroc'], 2)}, TPR {_fmt(m['tpr_at_threshold'], 2)}", fontsize=9
        )
        ax.set_xlabel("control step", fontsize=8)
    axes[0, 0].set_ylabel(f"{name} score")
    axes[1, 0].set_ylabel(f"{name} score")
    axes[0, 0].legend(fontsize=7, loc="upper left")
    fig.suptitle(
        f"{name}: grey nominal (test seeds), red failed and blue successful runs, dots at the onset",
        fontsize=10,
    )
    fig.tight_layout()
    fig.savefig(path, dpi=100)
    plt.close(fig)
    return path


def main(argv: list[str] | None = None) -> None:
    cfg = draccus.parse(config_class=BenchmarkOODConfig, args=argv, exit_on_error=False)
    result = run_benchmark(cfg)
    aurocs = {n: r.get("mean_auroc_common_steps", math.nan) for n, r in result["detectors"].items()}
    ranked = sorted(aurocs, key=lambda n: -math.inf if math.isnan(aurocs[n]) else aurocs[n], reverse=True)
    print(
        "Mean AUROC over common steps: "
        + ", ".join(f"{n} {_fmt(aurocs[n])}" for n in ranked)
        + f". Table: {cfg.output_dir / 'detectors.md'}"
    )
