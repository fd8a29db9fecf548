"""Where the robot plugin relies on LeRobot beyond its public API, checked against the installed LeRobot.

The seams: ``rollout_seam.py`` rebinds ``create_strategy`` where ``lerobot-rollout`` imported it;
``gated_dagger.py`` subclasses ``DAggerStrategy`` and uses its protected members (the events, the engine, the
interpolator, the phase transitions, the observation hand-off, the push flag and the episode lock);
``rtc_queue.py`` overrides how the real-time engine's ``ActionQueue`` counts the actions executed during an
inference; and ``episode_cues.py`` resets the simulated arm's scene on ``log_say``'s announcements. Each is checked here, and
the version they were written against is pinned: on another LeRobot, this file fails first and says what to
check.
"""

from __future__ import annotations

import inspect
from importlib.metadata import version
from importlib.util import find_spec
from pathlib import Path

import pytest

SEAMS_WRITTEN_FOR = "0.6.1"


def test_lerobot_is_the_version_the_seams_were_written_for():
    installed = version("lerobot")
    assert installed == SEAMS_WRITTEN_FOR, (
        f"LeRobot {installed} is installed; the robot plugin's seams into LeRobot were written for "
        f"{SEAMS_WRITTEN_FOR}. Check each against LeRobot {installed} (the other tests of this file name them: "
        "rollout_seam.py, gated_dagger.py's use of DAggerStrategy, rtc_queue.py, episode_cues.py's "
        "announcements), then set "
        "SEAMS_WRITTEN_FOR here."
    )


def _source(module: str) -> str:
    """A module's source, read without importing it: LeRobot's scripts import its keyboard listener, which
    settles pynput's backend for the whole process (the surgeon's tests pick the headless one first)."""
    return Path(find_spec(module).origin).read_text()


def test_the_strategy_factory_is_where_rollout_seam_rebinds_it():
    from lerobot.rollout.strategies import factory
    from lerobot_robot_suture import rollout_seam

    for name in rollout_seam._MODULES:
        if name == "lerobot.scripts.lerobot_rollout":
            assert "create_strategy" in _source(name), f"{name} no longer calls create_strategy"
            continue
        module = __import__(name, fromlist=["create_strategy"])
        assert hasattr(module, "create_strategy"), f"{name} no longer holds create_strategy"
    assert hasattr(factory.create_strategy, "lerobot_create_strategy"), (
        "the plugin's factory is not installed"
    )


@pytest.mark.parametrize(
    "member",
    ["_events", "_engine", "_interpolator", "_needs_push", "_episode_lock"],
)
def test_dagger_strategy_still_holds_the_members_gated_dagger_uses(member):
    from lerobot.rollout.strategies import core, dagger

    source = inspect.getsource(dagger.DAggerStrategy) + inspect.getsource(core.RolloutStrategy)
    assert f"self.{member} = " in source, (
        f"DAggerStrategy no longer sets self.{member}, which gated_dagger uses"
    )


@pytest.mark.parametrize(
    "method, parameters",
    [
        (
            "_apply_transition",
            ["self", "old_phase", "new_phase", "engine", "interpolator", "ctx", "prev_action"],
        ),
        ("_process_observation_and_notify", ["self", "processors", "obs_raw"]),
    ],
)
def test_dagger_strategy_s_methods_take_what_gated_dagger_passes(method, parameters):
    from lerobot.rollout.strategies.dagger import DAggerStrategy

    assert hasattr(DAggerStrategy, method), f"DAggerStrategy has no {method}, which gated_dagger calls"
    assert list(inspect.signature(getattr(DAggerStrategy, method)).parameters) == parameters


def test_dagger_events_and_the_engines_answer_what_gated_dagger_calls():
    from lerobot.rollout.inference.base import InferenceEngine
    from lerobot.rollout.strategies.dagger import DAggerEvents, DAggerPhase

    events = DAggerEvents()
    assert events.phase is DAggerPhase.AUTONOMOUS and events.consume_transition() is None
    assert hasattr(events, "stop_recording") and callable(events.reset)
    for method in ("start", "stop", "reset", "pause", "resume", "notify_observation", "get_action"):
        assert callable(getattr(InferenceEngine, method, None)), f"InferenceEngine has no {method}"


def test_lerobot_still_announces_the_episodes_the_simulated_arm_resets_on():
    from lerobot_robot_suture.episode_cues import RECORDING_EPISODE, RESET_THE_ENVIRONMENT

    for module in ("lerobot.scripts.lerobot_record", "lerobot.rollout.strategies.episodic"):
        source = _source(module)
        assert 'log_say(f"Recording episode {dataset.num_episodes}"' in source, module
        assert f'log_say("{RESET_THE_ENVIRONMENT}"' in source, module
    assert RECORDING_EPISODE.match("Recording episode 3").group(1) == "3"


def test_the_action_queue_still_resolves_its_delay_where_rtc_queue_overrides_it():
    from lerobot.policies.rtc import ActionQueue
    from lerobot.rollout.inference import rtc

    parameters = list(inspect.signature(ActionQueue._check_and_resolve_delays).parameters)
    assert parameters == ["self", "real_delay", "action_index_before_inference"]
    assert "self._check_and_resolve_delays(real_delay, action_index_before_inference)" in inspect.getsource(
        ActionQueue.merge
    )
    assert "self._action_queue = ActionQueue(" in inspect.getsource(rtc.RTCInferenceEngine.start)
