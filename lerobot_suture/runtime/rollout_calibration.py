"""The scores of rollouts recorded on the robot path, to fit an ensemble's gate on: ``lerobot-suture calibrate --rollouts=ROOT``.

The env path's calibration (:mod:`.calibration`) runs the policy itself, one prediction per chunk, as LeRobot's
sync engine does. Its real-time chunking engine predicts at another cadence: back to back, each chunk inpainted
after the actions still committed, and scored over the steps after them. Its scores follow another distribution,
so a gate deployed under it is calibrated on nominal rollouts made under it:
``lerobot-rollout --strategy.type=gated_dagger --inference.type=rtc`` records every frame's ``ood_score``.

Record them with the calibration file about to be written named and absent
(``--policy.ood.calibration_file=ood_calibration_rtc.json``): the policy then reports its scores and the gate never
hands over, so every episode's largest score is known. An episode that was handed over anyway (a key, the
camera watchdog, a gate of an older calibration) is kept with the largest score before the handover, a lower
bound of its own; the fit refuses when such a bound decides the threshold.
"""

from __future__ import annotations

import math
from pathlib import Path

import numpy as np

from lerobot_suture.safety.ood.calibration import CalibrationMode, conformal_episode_threshold

RECORDED_COLUMNS = ("episode_index", "ood_score", "intervention")


def _flat(column) -> np.ndarray:
    """A parquet column of scalars or one-element lists as a flat float array."""
    return np.array([np.asarray(value, dtype=float).reshape(-1)[0] for value in column], dtype=float)


def recorded_frames(root: Path) -> dict[str, np.ndarray]:
    """The episode index, ``ood_score`` and ``intervention`` of every frame of the LeRobotDataset at ``root``.

    Raises:
        FileNotFoundError: ``root`` holds no LeRobotDataset frames.
        ValueError: its frames carry no gate scores (it was not recorded by ``gated_dagger``).
    """
    import pandas as pd

    files = sorted(Path(root).glob("data/*/*.parquet"))
    if not files:
        raise FileNotFoundError(
            f"No LeRobotDataset frames under {root} (data/*/*.parquet). Name the `--dataset.root` of a "
            "`lerobot-rollout --strategy.type=gated_dagger` recording."
        )
    frames = pd.concat([pd.read_parquet(file) for file in files], ignore_index=True)
    missing = [name for name in RECORDED_COLUMNS if name not in frames.columns]
    if missing:
        raise ValueError(
            f"The frames under {root} have no {missing}: record the rollouts with "
            "`lerobot-rollout --strategy.type=gated_dagger`, which labels every frame with the gate's score."
        )
    order = np.argsort(frames["index"].to_numpy()) if "index" in frames.columns else np.arange(len(frames))
    return {name: _flat(frames[name].to_numpy()[order]) for name in RECORDED_COLUMNS}


def episode_predictions(
    episode_index: np.ndarray, score: np.ndarray, intervention: np.ndarray
) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """Per-prediction scores and their episode ids, and per episode whether it was handed over.

    A frame carries the last prediction's score until the next one arrives, so a prediction is a change of the
    score along an episode's frames (NaN: none yet). Frames from the first intervention on belong to the surgeon;
    that first one still carries the score that made the gate hand over, so it is kept.

    Returns:
        scores (P,), episode ids (P,) numbered 0..E-1 in recording order, handed_over (E,) bools.
    """
    scores, ids, handed_over = [], [], []
    for number, episode in enumerate(dict.fromkeys(episode_index.astype(int).tolist())):
        rows = np.flatnonzero(episode_index == episode)
        taken = np.flatnonzero(intervention[rows] > 0.5)
        handed_over.append(taken.size > 0)
        if taken.size:
            rows = rows[: taken[0] + 1]
        previous = math.nan
        for value in score[rows]:
            if math.isfinite(value) and value != previous:
                scores.append(value)
                ids.append(number)
            previous = value
    return np.asarray(scores), np.asarray(ids, dtype=int), np.asarray(handed_over, dtype=bool)


def check_bounds_do_not_decide(maxima: np.ndarray, handed_over: np.ndarray, alpha: float) -> float:
    """The per-episode threshold on ``maxima``, once no handed-over episode's bound can move it.

    A handed-over episode's true maximum is at least its recorded one: the threshold (an order statistic) holds
    whatever those maxima are if every such bound lies above it.

    Raises:
        ValueError: a handed-over episode's bound is at or below the threshold.
    """
    threshold = conformal_episode_threshold(maxima, alpha)
    undecided = int(np.sum(handed_over & (maxima <= threshold)))
    if undecided:
        raise ValueError(
            f"{undecided} of the {maxima.size} episodes were handed over with their largest score so far at or below "
            f"the threshold ({threshold:.4g}), so their own largest score, and the threshold, are unknown. Record "
            "the rollouts with the gate reporting only: name the calibration file about to be written, absent, "
            "with `--policy.ood.calibration_file=NAME`."
        )
    return threshold


def rollout_scores(root: Path, mode: str, alpha: float) -> tuple[np.ndarray, np.ndarray, dict]:
    """The per-prediction scores and episode ids of the rollouts recorded at ``root``, for the calibrate command
    to fit at ``alpha`` (``mode`` ``per_episode`` only: a frame records the last score, not when it was
    predicted), and what the report says of them. The rollouts are taken to be the calibrated policy's, with its
    score settings as they are now: a frame does not say.

    Raises:
        ValueError: another mode, an episode without a score, or a handed-over episode that decides the
            threshold (:func:`check_bounds_do_not_decide`).
    """
    if mode != CalibrationMode.PER_EPISODE:
        raise ValueError(
            f"Rollouts calibrate the per-episode gate only (`--mode=per_episode`). Got mode={mode!r}."
        )
    frames = recorded_frames(root)
    scores, ids, handed_over = episode_predictions(
        frames["episode_index"], frames["ood_score"], frames["intervention"]
    )
    episodes = handed_over.size
    scored = np.unique(ids).size
    if scored < episodes:
        raise ValueError(
            f"{episodes - scored} of the {episodes} episodes under {root} carry no gate score: the policy that "
            "recorded them has no gate of its own, or ran with `--strategy.gate=none` (record an ensemble_diffusion "
            "policy with the `auto` gate)."
        )
    maxima = np.full(episodes, -np.inf)
    np.maximum.at(maxima, ids, scores)
    check_bounds_do_not_decide(maxima, handed_over, alpha)
    recorded = {
        "rollouts": str(root),
        "episodes": int(episodes),
        "handed_over_episodes": int(handed_over.sum()),
        "episode_maxima": [float(m) for m in maxima],
    }
    return scores, ids, recorded
