"""``lerobot-rollout --strategy.type=gated_dagger``: LeRobot's DAgger where the O.O.D. gate, and not only a key,
hands control to the teleoperator; the CBF step filters every action, the policy's and the teleoperator's.

Episode by episode (``--strategy.num_episodes``, each at most ``--dataset.episode_time_s``, or until a
``suture_sim`` scene ends): the policy drives; each of its actions is held back until the gate
(:class:`~.rollout_gate.RolloutGate`: the ensemble's own, or STAC for any chunking policy, plus the camera
watchdog) has read the prediction, and on its first O.O.D. decision that action is dropped, the policy paused
and the teleoperator acts from that control step on until the episode ends (the env path's enforced gate hands
over at the same step). LeRobot's keys still work (``pause_resume``, ``correction``, Esc), with LeRobot's smooth handovers.
Every frame is recorded with LeRobot's ``intervention`` label and the gate's ``ood_score``, ``ood_threshold``
and ``ood_decision``; between episodes LeRobot's "Reset the environment" phase runs
(``--dataset.reset_time_s``). With ``--teleop.type=suture_scripted`` the scripted surgeon stand-in corrects.

The CBF (``suture_cbf``, :mod:`.cbf_step`) is appended to the robot action pipeline that ``lerobot-rollout`` built
(``--strategy.cbf.enabled=false`` leaves it out).
"""

from __future__ import annotations

import logging
import time
from dataclasses import dataclass, field

import numpy as np
import torch
from lerobot.datasets.io_utils import write_info
from lerobot.processor import RobotProcessorPipeline
from lerobot.rollout.configs import DAggerStrategyConfig, RolloutStrategyConfig
from lerobot.rollout.strategies.dagger import DAggerPhase, DAggerStrategy
from lerobot.utils.constants import ACTION, OBS_STR
from lerobot.utils.feature_utils import build_dataset_frame
from lerobot.utils.robot_utils import precise_sleep
from lerobot.utils.utils import log_say

from lerobot_suture.lerobot_shim import DAggerInternals, episode, merge_after_executed_actions
from lerobot_suture.safety.camera_watchdog import CameraWatchdogConfig
from lerobot_suture.safety.cbf_config import CBFConfig
from lerobot_suture.safety.wound import GraspModel

from .cbf_step import SutureCBFStep
from .rollout_gate import GATE_KINDS, GateReading, RolloutGate

logger = logging.getLogger(__name__)

GATE_FEATURES = {
    "ood_score": {"dtype": "float32", "shape": (1,), "names": None},
    "ood_threshold": {"dtype": "float32", "shape": (1,), "names": None},
    "ood_decision": {"dtype": "bool", "shape": (1,), "names": None},
}
"""Per frame: the gate's last score, its threshold (NaN without one) and its (latched) O.O.D. decision."""


MIN_EPISODE_FRAMES = 2
"""The fewest frames an episode is saved with (LeRobot's streaming video encoder needs two for its statistics)."""


def restart_engine(engine) -> None:
    """LeRobot's inference engine started afresh for a new scene: policy, processors and queue reset.

    The real-time engine's thread is joined, so a chunk still being predicted for the last scene never joins
    the new scene's queue; and it holds no observation until the new scene's first. Reset and resumed only, it
    would predict the new scene's first chunk from the last scene's final frame (its latest observation). Its
    new queue merges each chunk after the actions actually executed meanwhile
    (:class:`lerobot_suture.lerobot_shim.ExecutedActionQueue`).
    """
    engine.stop()
    engine.start()
    merge_after_executed_actions(engine)
    engine.reset()


@RolloutStrategyConfig.register_subclass("gated_dagger")
@dataclass
class GatedDAggerStrategyConfig(DAggerStrategyConfig):
    """LeRobot's DAgger configuration (keys, smooth handover, uploads) plus the gate and the CBF.

    Args:
        gate: ``auto`` (the ensemble's gate for a calibrated ``ensemble_diffusion``, else STAC when the policy has
            a ``stac_calibration.json``, else the camera watchdog alone), ``ensemble``, ``stac`` or ``none``.
        camera_watchdog: flag a frozen or dropped endoscope frame (``watchdog.*`` tunes it).
        cbf: the ``suture_cbf`` step's filter (``--strategy.cbf.enabled=false``: no CBF step).
        grasp: the grasp model the CBF step uses where the arm reports none.
        cbf_latency_steps: the latency (control steps, observation plus command) the CBF step declares for the
            arm; None: the arm's own declaration (``suture_sim``: its faults' latencies), else 0.
        record_autonomous: record the policy's frames too (default here), not only the corrections.
        smooth_handover: LeRobot's smooth handover (off by default here: the suture teleoperators take control
            from the arm's measured pose, so there is no jump to smooth, and the slide would move the arm
            between recorded frames).
    """

    gate: str = "auto"
    camera_watchdog: bool = True
    watchdog: CameraWatchdogConfig = field(default_factory=CameraWatchdogConfig)
    cbf: CBFConfig = field(default_factory=lambda: CBFConfig(enabled=True))
    grasp: GraspModel = field(default_factory=GraspModel)
    cbf_latency_steps: int | None = None
    record_autonomous: bool = True
    smooth_handover: bool = False

    def __post_init__(self):
        super().__post_init__()
        if self.gate not in GATE_KINDS:
            raise ValueError(f"`gate` must be one of {GATE_KINDS}. Got {self.gate!r}.")


def add_gate_features(dataset) -> None:
    """Give a new rollout dataset the gate's features (LeRobot created it with ``intervention`` only).

    Raises:
        ValueError: the dataset already holds episodes without them (``--resume`` of another strategy's data).
    """
    missing = {k: v for k, v in GATE_FEATURES.items() if k not in dataset.meta.features}
    if not missing:
        return
    if dataset.meta.total_episodes > 0:
        raise ValueError(
            f"The dataset at {dataset.root} has episodes without the gate's features {sorted(missing)}; record "
            "gated DAgger into a new --dataset.repo_id."
        )
    dataset.meta.info.features.update(missing)
    write_info(dataset.meta.info, dataset.meta.root)
    dataset.clear_episode_buffer(delete_images=False)


def next_policy_action(obs_processed: dict, ctx, interpolator) -> dict | None:
    """The policy's next action as a robot action dict, not yet sent (``send_next_action`` without the send)."""
    if interpolator.needs_new_action():
        obs_frame = build_dataset_frame(ctx.data.dataset_features, obs_processed, prefix=OBS_STR)
        action_tensor = ctx.policy.inference.get_action(obs_frame)
        if action_tensor is not None:
            interpolator.add(action_tensor.cpu())
    interp = interpolator.get()
    if interp is None:
        return None
    return {key: interp[i].item() for i, key in enumerate(ctx.data.ordered_action_keys)}


def declared_latency(robot) -> int:
    """The control steps of latency ``robot`` declares (observation plus command): ``suture_sim``'s faults, or 0
    for an arm that declares none."""
    faults = getattr(getattr(robot, "config", None), "faults", None)
    if faults is None:
        return 0
    return int(faults.observation_latency) + int(faults.command_latency)


def with_cbf_step(pipeline: RobotProcessorPipeline, step: SutureCBFStep) -> RobotProcessorPipeline:
    """The robot action pipeline with ``step`` appended."""
    return RobotProcessorPipeline(
        steps=[*pipeline.steps, step],
        name=pipeline.name,
        to_transition=pipeline.to_transition,
        to_output=pipeline.to_output,
    )


class GatedDAggerStrategy(DAggerStrategy):
    """See the module docstring."""

    config: GatedDAggerStrategyConfig

    def setup(self, ctx) -> None:
        super().setup(ctx)
        self.dagger = DAggerInternals(self)
        self.cbf_step = None
        if self.config.cbf.enabled:
            latency = self.config.cbf_latency_steps
            if latency is None:
                latency = declared_latency(ctx.hardware.robot_wrapper.inner)
            self.cbf_step = SutureCBFStep(cbf=self.config.cbf, grasp=self.config.grasp, latency_steps=latency)
            processors = ctx.processors
            processors.robot_action_processor = with_cbf_step(
                processors.robot_action_processor, self.cbf_step
            )
        watchdog = self.config.watchdog if self.config.camera_watchdog else None
        self.gate = RolloutGate(
            ctx.policy.policy, self.config.gate, ctx.runtime.cfg.policy.pretrained_path, watchdog
        )
        add_gate_features(ctx.data.dataset)
        self.handovers: list[int | None] = []
        """Per recorded episode: the frame at which the gate handed control over (None: it did not)."""
        logger.info("Gated DAgger: gate %s, CBF %s", self.gate.kind, "on" if self.cbf_step else "off")

    def run(self, ctx) -> None:
        cfg = ctx.runtime.cfg
        dataset = ctx.data.dataset
        start = time.perf_counter()
        for _ in range(self.config.num_episodes):
            if self.dagger.events.stop_recording.is_set() or ctx.runtime.shutdown_event.is_set():
                break
            if cfg.duration > 0 and time.perf_counter() - start >= cfg.duration:
                break
            log_say(f"Recording episode {dataset.num_episodes}", cfg.play_sounds)
            with episode(ctx.hardware.robot_wrapper, dataset.num_episodes):
                handover = self._run_episode(ctx)
            frames = dataset.writer.episode_buffer["size"] if dataset.has_pending_frames() else 0
            if dataset.meta.video_keys and 0 < frames < MIN_EPISODE_FRAMES:
                # LeRobot's streaming video encoder gives no statistics for such an episode, and the dataset's
                # metadata cannot then hold it beside the others.
                logger.warning(
                    "Episode %d has %d frame(s), fewer than the %d a video episode needs: discarded, and the "
                    "next episode takes its place (suture_sim plays the scene again). A longer "
                    "--dataset.episode_time_s avoids this.",
                    dataset.num_episodes,
                    frames,
                    MIN_EPISODE_FRAMES,
                )
                dataset.clear_episode_buffer()
            elif frames > 0:
                with self.dagger.episode_lock:
                    dataset.save_episode()
                self.dagger.request_push()
                self.handovers.append(handover)
                logger.info("Episode %d saved (handover at frame %s)", dataset.num_episodes - 1, handover)
            if len(self.handovers) < self.config.num_episodes and cfg.dataset.reset_time_s > 0:
                log_say("Reset the environment", cfg.play_sounds)
                self._hold_for(ctx, cfg.dataset.reset_time_s)

    def teardown(self, ctx) -> None:
        if getattr(self, "gate", None) is not None:
            self.gate.close()
        super().teardown(ctx)

    # ------------------------------------------------------------------
    def _run_episode(self, ctx) -> int | None:
        """One episode: the policy until the gate (or a key) hands over, then the teleoperator."""
        cfg, dagger = ctx.runtime.cfg, self.dagger
        events, engine, interpolator = dagger.events, dagger.engine, dagger.interpolator
        robot = ctx.hardware.robot_wrapper
        control_interval = interpolator.get_control_interval(cfg.fps)
        task = cfg.dataset.single_task if cfg.dataset else cfg.task
        restart_engine(engine)
        interpolator.reset()
        events.reset()
        self.gate.reset()
        scene_seed = getattr(robot.inner, "scene_seed", None)
        if scene_seed is not None:
            # The simulated arm's scene: the policy's noise seeded as the env path's runs of that seed are.
            torch.manual_seed(int(scene_seed))
        engine.resume()
        if self.cbf_step is not None:
            self.cbf_step.reset()
        reading = GateReading(float("nan"), float("nan"), False, False, False)
        last_action, handover, frame_index = None, None, 0
        episode_start = time.perf_counter()
        while not (events.stop_recording.is_set() or ctx.runtime.shutdown_event.is_set()):
            loop_start = time.perf_counter()
            if loop_start - episode_start >= cfg.dataset.episode_time_s or getattr(
                robot.inner, "scene_over", False
            ):
                break
            obs = robot.get_observation()
            transition = events.consume_transition()
            if transition is not None:
                if transition[1] is DAggerPhase.AUTONOMOUS:
                    # Handed back: the engine resumes from the arm as it is now, not as it was when the
                    # surgeon took over (the last observation it was handed).
                    engine.notify_observation(ctx.processors.robot_observation_processor(obs))
                dagger.apply_transition(*transition, ctx, last_action)
            if events.phase == DAggerPhase.AUTONOMOUS:
                obs_processed = dagger.process_observation_and_notify(ctx.processors, obs)
                action = next_policy_action(obs_processed, ctx, interpolator)
                # The gate reads the prediction before it reaches the arm: a chunk it flags is never executed,
                # as with the ensemble's enforced gate on the env path. The real-time chunking engine's policy
                # reads its gate before its chunk joins the queue, so an action taken from a flagged chunk meets
                # the flag here; the gate is read at every step, with or without a new action, so that the
                # handover comes within a control period of the flag.
                reading = self.gate.read(obs)
                if reading.decision:
                    handover = frame_index
                    flagged_at = getattr(ctx.policy.policy, "ood_flagged_at", None)
                    after_ms = (
                        (time.perf_counter() - flagged_at) * 1e3
                        if flagged_at is not None and flagged_at >= episode_start
                        else float("nan")
                    )
                    logger.info(
                        "Gate: O.O.D. (score %.4g, threshold %.4g, camera stale %s): handing over, "
                        "%.1f ms after the policy's gate flagged",
                        reading.score,
                        reading.threshold,
                        reading.camera_stale,
                        after_ms,
                    )
                    self._hand_over(ctx, last_action)
                elif action is not None:  # None: the real-time engine's first chunk has not arrived
                    last_action = ctx.processors.robot_action_processor((action, obs))
                    robot.send_action(last_action)
                    self._record(ctx, obs_processed, action, task, False, reading)
                    frame_index += 1
                    if self._tissue_beyond_bounds():
                        handover = frame_index
                        logger.info("CBF: the tissue moves beyond its declared bounds: handing over")
                        self._hand_over(ctx, last_action)
            if events.phase == DAggerPhase.CORRECTING:
                obs_processed = ctx.processors.robot_observation_processor(obs)
                teleop_action = ctx.processors.teleop_action_processor(
                    (ctx.hardware.teleop.get_action(), obs)
                )
                last_action = ctx.processors.robot_action_processor((teleop_action, obs))
                robot.send_action(last_action)
                if handover is None:
                    handover = frame_index
                self._record(ctx, obs_processed, teleop_action, task, True, reading)
                frame_index += 1
            elif events.phase == DAggerPhase.PAUSED and last_action:
                robot.send_action(last_action)
            if (sleep := control_interval - (time.perf_counter() - loop_start)) > 0:
                precise_sleep(sleep)
        engine.pause()
        return handover

    def _tissue_beyond_bounds(self) -> bool:
        """The CBF step found the wound moving faster, or accelerating harder, than it was declared to cover."""
        result = None if self.cbf_step is None else self.cbf_step.last_result
        return result is not None and result.motion_exceeded

    def _hand_over(self, ctx, last_action) -> None:
        """The gate's decision does what LeRobot's pause and correction keys do, at once."""
        dagger = self.dagger
        dagger.apply_transition(DAggerPhase.AUTONOMOUS, DAggerPhase.PAUSED, ctx, last_action)
        dagger.apply_transition(DAggerPhase.PAUSED, DAggerPhase.CORRECTING, ctx, last_action)
        dagger.events.phase = DAggerPhase.CORRECTING

    def _record(self, ctx, obs_processed, action, task, intervention: bool, reading: GateReading) -> None:
        features = ctx.data.dataset_features
        frame = {
            **build_dataset_frame(features, obs_processed, prefix=OBS_STR),
            **build_dataset_frame(features, action, prefix=ACTION),
            "task": task,
            "intervention": np.array([intervention], dtype=bool),
            "ood_score": np.array([reading.score], dtype=np.float32),
            "ood_threshold": np.array([reading.threshold], dtype=np.float32),
            "ood_decision": np.array([reading.decision], dtype=bool),
        }
        ctx.data.dataset.add_frame(frame)

    def _hold_for(self, ctx, seconds: float) -> None:
        """LeRobot's reset phase: the arm holds while the scene is reset (a person's job on a real arm)."""
        end = time.perf_counter() + seconds
        while time.perf_counter() < end and not ctx.runtime.shutdown_event.is_set():
            precise_sleep(min(0.05, max(end - time.perf_counter(), 0.0)))
