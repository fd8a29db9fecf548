"""Which gate watches a loaded policy, read the same way by every episode loop: the env path's rollouts, the STAC
calibration and the robot path's ``gated_dagger``.

- ``ensemble`` (:class:`PolicyGates`): an ``ensemble_diffusion`` policy holds the gate itself, one
  :class:`~lerobot_suture.safety.ood.gate.OODGate` per env of its batch, fed with its members' covariance score
  (``policy.ood_status(row)``); an enforced gate makes the policy hold its pose.
- ``stac`` (:class:`StacGates`): any policy that predicts chunks (ACT, diffusion, ...). Each chunk it predicts is
  captured and scored against the one before, one :class:`~lerobot_suture.safety.ood.gate.ChunkGate` per env.
  It reports; it does not act on the policy.
- ``none`` (:class:`SilentGates`): no gate.
- :class:`StageGates`: a gate per stage of the running suture over either's scores: the high level
  (:mod:`lerobot_suture.sim.subtasks`) names each env's subtask from its measured pose, and each segment is tested
  against its subtask's threshold (:mod:`lerobot_suture.safety.ood.stage_gate`), and, with budgets, each segment's
  length against its subtask's time budget. A flag releases control for the rest of its segment.

Each has ``reset(rows)`` at the start of a batch of episodes, ``observe(row, observation)`` once per control step
and row with the observation the step acts from, ``status(row)`` after the policy has acted (the keys of
:func:`~lerobot_suture.safety.ood.gate.silent_status`), ``rearm(row)`` when a surgeon hands control back (the
policy starts afresh), ``context(row)`` for the step's log, and ``close()``.
"""

from __future__ import annotations

from pathlib import Path

import numpy as np

from lerobot_suture.safety.ood.calibration_file import STAC_CALIBRATION_FILE, StacCalibration
from lerobot_suture.safety.ood.chunk_consistency import ChunkCapture, ChunkConsistencyMonitor, chunk_source
from lerobot_suture.safety.ood.gate import ChunkGate, silent_status
from lerobot_suture.safety.ood.stage_gate import StageBudgets, StageGate, StageThresholds
from lerobot_suture.sim.state_layout import registered_marks
from lerobot_suture.sim.subtasks import SubtaskRules, SubtaskRulesConfig
from lerobot_suture.sim.wound_marks import MARKS_KEY

GATE_KINDS = ("auto", "ensemble", "stac", "none")


class SilentGates:
    """No gate: NaN scores, never O.O.D."""

    kind = "none"

    def reset(self, rows: int) -> None:
        pass

    def observe(self, row: int, observation: dict) -> None:
        pass

    def status(self, row: int) -> dict:
        return silent_status()

    def rearm(self, row: int) -> None:
        pass

    def context(self, row: int) -> dict:
        """What the gates know of the task's state, for the step's log (the subtask and throw, for stages)."""
        return {}

    def close(self) -> None:
        pass


class PolicyGates(SilentGates):
    """The gates a policy holds itself (``ood_status``); silent for a policy without one (ACT, diffusion)."""

    kind = "ensemble"

    def __init__(self, policy):
        self.policy = policy

    def status(self, row: int) -> dict:
        ood_status = getattr(self.policy, "ood_status", None)
        return ood_status(row) if callable(ood_status) else silent_status()


class ReportingGates(PolicyGates):
    """An uncalibrated ensemble's own gate: it reports every prediction's score and never flags, so the rollouts
    it records calibrate it (``lerobot-suture calibrate --rollouts``)."""

    kind = "ensemble, uncalibrated (reports scores only)"


class StacGates(SilentGates):
    """STAC on the chunks ``policy`` predicts, one gate per row of its batch.

    Args:
        policy: a LeRobot policy that predicts chunks; its chunk method is wrapped until :meth:`close`.
        calibration: the STAC calibration, or None to record scores only (while calibrating).
        bandwidth: the kernel's bandwidth without a calibration (normalized action units).

    Raises:
        ValueError: the calibration was fitted with another ``n_action_steps`` than the policy runs.
        TypeError: the policy predicts no chunks.
    """

    kind = "stac"

    def __init__(self, policy, calibration: StacCalibration | None = None, bandwidth: float = 0.5):
        owner, method, self._start = chunk_source(policy)
        self._shift = int(getattr(policy.config, "n_action_steps", 1))
        if calibration is not None and self._shift != calibration.n_action_steps:
            raise ValueError(
                f"The STAC calibration was fitted with n_action_steps={calibration.n_action_steps}; the policy runs "
                f"{self._shift}, so successive chunks overlap differently. Run `lerobot-suture calibrate-stac` "
                "again with these settings."
            )
        self.calibration = calibration
        self._bandwidth = calibration.bandwidth if calibration is not None else float(bandwidth)
        self._capture = ChunkCapture(owner, method)
        self.reset(1)

    def reset(self, rows: int) -> None:
        self.gates = [self._gate() for _ in range(rows)]
        self._seen = self._capture.chunks
        self._fresh = [False] * rows

    def rearm(self, row: int) -> None:
        self.gates[row] = self._gate()  # the policy starts afresh: no previous chunk to compare with

    def _gate(self) -> ChunkGate:
        return ChunkGate(ChunkConsistencyMonitor(self._shift, self._start, self._bandwidth), self.calibration)

    def status(self, row: int) -> dict:
        if self._capture.chunks > self._seen:  # a new chunk since the last status: score it for every row
            self._seen = self._capture.chunks
            chunk = np.asarray(self._capture.last)
            for index, gate in enumerate(self.gates):
                gate.update(chunk[index] if chunk.ndim == 3 else chunk)
            self._fresh = [True] * len(self.gates)
        gate, new = self.gates[row].gate, self._fresh[row]
        self._fresh[row] = False
        return {
            "score": gate.last_score,
            "threshold": gate.threshold,
            "decision": gate.decision,
            "released": False,
            "flagged": gate.released,
            "new_prediction": new,
        }

    def close(self) -> None:
        self._capture.release()


class StageGates(SilentGates):
    """A gate per stage over ``base``'s scores (see the module docstring).

    Args:
        base: the gates whose scores are tested (the policy's own, or STAC), reporting only.
        thresholds: each subtask's threshold, or None to record scores only (while calibrating).
        rules: the high level's thresholds.
        budgets: each subtask's time budget (control steps), or None.
    """

    kind = "stage"

    def __init__(
        self,
        base: SilentGates,
        thresholds: StageThresholds | None,
        rules: SubtaskRulesConfig | None = None,
        budgets: StageBudgets | None = None,
    ):
        self.base, self.thresholds, self.rules_config, self.budgets = base, thresholds, rules, budgets
        self.reset(1)

    def reset(self, rows: int) -> None:
        self.base.reset(rows)
        self.rules = [SubtaskRules(self.rules_config) for _ in range(rows)]
        self.gates = [StageGate(self.thresholds, self.budgets) for _ in range(rows)]
        self._started = [False] * rows

    def observe(self, row: int, observation: dict) -> None:
        self.base.observe(row, observation)
        rules, pose = self.rules[row], observation["agent_pos"]
        marks = registered_marks(observation.get(MARKS_KEY))
        subtask, throw = rules.update(pose, marks) if self._started[row] else rules.reset(pose)
        self._started[row] = True
        self.gates[row].enter(subtask, throw)
        self.gates[row].tick()

    def status(self, row: int) -> dict:
        status, gate = self.base.status(row), self.gates[row]
        if status["new_prediction"]:
            gate.update(status["score"])
        return {
            **status,
            "threshold": gate.threshold(gate.segment[0]),
            "decision": gate.gate.decision,
            "released": gate.flagged_here,
            "flagged": bool(gate.flags),
        }

    def rearm(self, row: int) -> None:
        self.base.rearm(row)
        self.gates[row].rearm()

    def context(self, row: int) -> dict:
        subtask, throw = self.gates[row].segment
        return {"subtask": subtask, "throw": throw}

    def close(self) -> None:
        self.base.close()


def policy_gates(policy, kind: str = "auto", policy_dir: str | Path | None = None) -> SilentGates:
    """The gates for ``policy``: ``auto`` picks ``ensemble`` for a calibrated ensemble, else ``stac`` when a STAC
    calibration lies in ``policy_dir``, else ``none``; an ensemble without either reports its scores and never
    flags (its rollouts then calibrate it: ``lerobot-suture calibrate --rollouts``).

    Raises:
        ValueError: an unknown ``kind``, or ``ensemble`` for a policy without a calibrated gate.
        FileNotFoundError: ``stac`` without a STAC calibration (the message says how to make one).
    """
    if kind not in GATE_KINDS:
        raise ValueError(f"`gate` must be one of {GATE_KINDS}. Got {kind!r}.")
    scores = callable(getattr(policy, "ood_status", None))
    ensemble = scores and getattr(policy, "ood_calibration", None)
    if kind == "auto":
        has_stac = policy_dir is not None and (Path(policy_dir) / STAC_CALIBRATION_FILE).is_file()
        if scores and not ensemble and not has_stac:
            return ReportingGates(policy)
        kind = "ensemble" if ensemble else "stac" if has_stac else "none"
    if kind == "ensemble":
        if not ensemble:
            raise ValueError(
                "`gate=ensemble` needs an ensemble_diffusion policy with a calibrated gate: run "
                "`lerobot-suture calibrate --policy.path=DIR` first, or use `gate=stac` for other policies."
            )
        return PolicyGates(policy)
    if kind == "stac":
        if policy_dir is None:
            raise FileNotFoundError(
                f"`gate=stac` needs the policy's directory to read {STAC_CALIBRATION_FILE}."
            )
        return StacGates(policy, StacCalibration.load(policy_dir))
    return SilentGates()
