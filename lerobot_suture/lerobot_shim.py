"""Every place where lerobot_suture and its plugins rely on LeRobot beyond its public API, in one module.

Written for LeRobot :data:`LEROBOT_VERSION`. ``tests/test_lerobot_shim.py`` checks each seam below against the
installed LeRobot, and fails first, naming this version, on any other; it also checks that no other module of
the product or its plugins reaches a private member of LeRobot or rebinds one of its names. An upgrade of
LeRobot is this module and that test.

The seams:

1. **Plugin rollout strategies.** Strategy configs are a draccus registry that a plugin extends, but
   ``lerobot.rollout.strategies.factory.create_strategy`` maps a config to its class with a fixed if-chain of
   LeRobot's own types. :func:`route_strategies` puts a ``create_strategy`` in front of it, in the factory
   module and wherever it was already imported by name (``lerobot-rollout`` imports it before it imports
   plugins).
2. **Episode boundaries.** LeRobot's ``Robot`` has no episode hook: a real arm leaves the reset between
   episodes to a person. A simulated arm resets its own scene, so it must know when dataset episode ``N``
   starts and ends. ``lerobot-record`` runs each episode as one ``record_loop(..., dataset=dataset)`` call,
   and the episodic rollout strategy as one ``EpisodicStrategy._policy_loop(...)`` call;
   :func:`install_episode_hooks` wraps both so that a robot that is :class:`EpisodeAware` hears
   ``start_episode(N)`` (``N`` = the dataset's episode count, so a re-recorded episode keeps its index) and
   ``end_episode()``. Nothing reads the text of LeRobot's spoken announcements.
3. **DAgger's members.** ``DAggerStrategy`` keeps its events (which its keyboard and pedal threads set), its
   inference engine, its interpolator, its phase transitions, its push flag and its episode lock private;
   :class:`DAggerInternals` is the one reader of them. A gated strategy cannot reuse DAgger's loop itself:
   that loop sends each action as it predicts it (``send_next_action``), with no point at which a gate could
   hold a flagged action back, and it rotates episodes by time, not by scene.
4. **The real-time queue's delay.** LeRobot's ``ActionQueue.merge`` drops ``ceil(latency / period)`` actions of
   a new chunk as already executed, one more than were whenever the inference does not end on a tick.
   :class:`ExecutedActionQueue` overrides ``_check_and_resolve_delays`` to drop exactly the actions the queue
   handed out meanwhile.
5. **Smaller reaches**: the diffusion model's ``_prepare_global_conditioning`` (the ensemble conditions every
   member's sampler on it), a config's ``_save_pretrained`` (writing a member's ``config.json``), and the
   keyboard teleoperator's ``_on_press`` / ``_on_release`` (a scripted listener plays keys into them).

This module imports nothing of lerobot_suture, so every layer and plugin may import it.
"""

from __future__ import annotations

import functools
import logging
import sys
from collections.abc import Callable, Mapping
from contextlib import contextmanager
from importlib.metadata import version
from typing import Any, Protocol, runtime_checkable

from lerobot.policies.rtc import ActionQueue

logger = logging.getLogger(__name__)

LEROBOT_VERSION = "0.6.1"
"""The LeRobot release every seam of this module was written and checked against."""

STRATEGY_MODULES = (
    "lerobot.rollout.strategies.factory",
    "lerobot.rollout.strategies",
    "lerobot.rollout",
    "lerobot.scripts.lerobot_rollout",
)
"""Where ``create_strategy`` is bound by name once ``lerobot-rollout`` has started."""
RECORD_SCRIPT = "lerobot.scripts.lerobot_record"
EPISODIC_STRATEGY = "lerobot.rollout.strategies.episodic"
_ORIGINAL = "lerobot_original"
"""The attribute under which a wrapper keeps LeRobot's function (installing twice wraps once)."""


@functools.cache
def warn_on_another_lerobot() -> None:
    """Log once that the installed LeRobot is not the one the seams were checked against."""
    installed = version("lerobot")
    if installed != LEROBOT_VERSION:
        logger.warning(
            "LeRobot %s is installed; lerobot_suture's seams into LeRobot (lerobot_suture/lerobot_shim.py) were "
            "checked against %s. Run `pytest tests/test_lerobot_shim.py` to see which still hold.",
            installed,
            LEROBOT_VERSION,
        )


# ---------------------------------------------------------------------------------------------- 1. strategies
def route_strategies(strategies: Mapping[str, Callable[[Any], Any]]) -> None:
    """Make ``lerobot-rollout``'s strategy factory build ``strategies[config.type]`` for these types.

    Every other type goes to LeRobot's own factory. Installing again adds to the types already routed.
    """
    from lerobot.rollout.strategies import factory

    warn_on_another_lerobot()
    current = factory.create_strategy
    lerobot_create = getattr(current, _ORIGINAL, current)
    routed = {**getattr(current, "routed", {}), **strategies}

    def create_strategy(config):
        strategy = routed.get(config.type)
        return strategy(config) if strategy is not None else lerobot_create(config)

    setattr(create_strategy, _ORIGINAL, lerobot_create)
    create_strategy.routed = routed
    for name in STRATEGY_MODULES:
        module = sys.modules.get(name)
        if module is not None and hasattr(module, "create_strategy"):
            module.create_strategy = create_strategy


# ------------------------------------------------------------------------------------------------- 2. episodes
@runtime_checkable
class EpisodeAware(Protocol):
    """A robot that resets its own scene between LeRobot's dataset episodes."""

    def start_episode(self, episode: int) -> None:
        """Dataset episode ``episode`` starts now."""

    def end_episode(self) -> None:
        """The episode that started last has ended (its frames may still be saved or re-recorded)."""


def episode_aware(robot) -> EpisodeAware | None:
    """``robot``, or the robot that ``lerobot-rollout``'s thread-safe wrapper holds, if it is episode-aware."""
    inner = getattr(robot, "inner", robot)
    return inner if isinstance(inner, EpisodeAware) else None


@contextmanager
def episode(robot, index: int):
    """Dataset episode ``index`` on ``robot``: announced to an episode-aware robot at entry, ended at a normal exit."""
    aware = episode_aware(robot)
    if aware is not None:
        aware.start_episode(int(index))
    yield
    if aware is not None:
        aware.end_episode()


def _with_episodes(loop):
    """``loop`` (``record_loop``, or the method ``_policy_loop``) told to an episode-aware robot as one episode
    when it is called with ``robot=`` and ``dataset=`` (both of LeRobot's callers pass them by keyword)."""

    @functools.wraps(loop)
    def wrapper(*args, **kwargs):
        dataset, robot = kwargs.get("dataset"), kwargs.get("robot")
        if dataset is None or robot is None:  # the reset phase, or a call this seam does not know
            return loop(*args, **kwargs)
        with episode(robot, dataset.num_episodes):
            return loop(*args, **kwargs)

    setattr(wrapper, _ORIGINAL, loop)
    return wrapper


def install_episode_hooks() -> None:
    """Wrap the episode loops of ``lerobot-record`` and the episodic strategy that are loaded now (idempotent).

    The wrappers call through unchanged for robots that are not :class:`EpisodeAware`.
    """
    warn_on_another_lerobot()
    for module in list(sys.modules.values()):
        spec = getattr(module, "__spec__", None)
        if spec is None or spec.name != RECORD_SCRIPT:  # also `python -m lerobot.scripts.lerobot_record`
            continue
        loop = getattr(module, "record_loop", None)
        if loop is not None and not hasattr(loop, _ORIGINAL):
            module.record_loop = _with_episodes(loop)
    episodic = sys.modules.get(EPISODIC_STRATEGY)
    if episodic is not None:
        strategy = episodic.EpisodicStrategy
        if not hasattr(strategy._policy_loop, _ORIGINAL):
            strategy._policy_loop = _with_episodes(strategy._policy_loop)


# --------------------------------------------------------------------------------------------------- 3. DAgger
class DAggerInternals:
    """The private members of a ``DAggerStrategy`` (or subclass) that a strategy built on it uses."""

    def __init__(self, strategy):
        self.strategy = strategy

    @property
    def events(self):
        """``DAggerEvents``: the phase and the transitions that LeRobot's keyboard and pedal threads request."""
        return self.strategy._events

    @property
    def engine(self):
        """The inference engine (sync or real-time) that ``setup`` built."""
        return self.strategy._engine

    @property
    def interpolator(self):
        return self.strategy._interpolator

    @property
    def episode_lock(self):
        """Held while an episode is saved, so that a background push never reads a half-written one."""
        return self.strategy._episode_lock

    def request_push(self) -> None:
        """Have the Hub push that ``teardown`` runs (``--dataset.push_to_hub``) include the saved episodes."""
        self.strategy._needs_push.set()

    def apply_transition(self, old_phase, new_phase, ctx, last_action) -> None:
        """DAgger's handling of a phase change (pause or resume the engine, smooth handover)."""
        self.strategy._apply_transition(
            old_phase, new_phase, self.engine, self.interpolator, ctx, last_action
        )

    def process_observation_and_notify(self, processors, observation):
        """The processed observation, handed to the engine (the real-time engine predicts from it)."""
        return self.strategy._process_observation_and_notify(processors, observation)


# --------------------------------------------------------------------------------------------- 4. the RTC queue
class ExecutedActionQueue(ActionQueue):
    """``ActionQueue`` whose merge drops the actions executed during the inference, not the latency's ceiling.

    While a chunk is predicted, the control loop keeps taking actions from the queue; when the chunk arrives,
    it resumes at the first action not yet executed. Its first ``d`` steps are the committed prefix
    (``rtc_inpainting``), so the actions executed meanwhile were the chunk's own.
    """

    def _check_and_resolve_delays(
        self, real_delay: int, action_index_before_inference: int | None = None
    ) -> int:
        if action_index_before_inference is None:
            return max(0, real_delay)
        return max(0, self.last_index - action_index_before_inference)


def merge_after_executed_actions(engine) -> None:
    """Make the queue of a just-started real-time engine an :class:`ExecutedActionQueue` (other engines: no-op)."""
    queue = getattr(engine, "action_queue", None)
    if type(queue) is ActionQueue:
        queue.__class__ = ExecutedActionQueue


# ---------------------------------------------------------------------------------------------- 5. the others
def prepare_global_conditioning(diffusion_model, batch: dict):
    """The (B, G) global conditioning a LeRobot ``DiffusionModel`` computes from an observation batch."""
    return diffusion_model._prepare_global_conditioning(batch)


def save_config(config, directory) -> None:
    """Write a LeRobot policy config's ``config.json`` into ``directory`` (what ``save_pretrained`` writes)."""
    config._save_pretrained(directory)


def key_callbacks(teleop) -> tuple[Callable, Callable]:
    """The ``(on_press, on_release)`` callbacks a LeRobot keyboard teleoperator gives its pynput listener."""
    return teleop._on_press, teleop._on_release
