"""LeRobot's real-time chunking queue, merging a new chunk after the actions the arm actually executed.

While a chunk is predicted, the control loop keeps taking actions from the queue. When the chunk arrives,
LeRobot 0.6.1's ``ActionQueue.merge`` drops ``ceil(latency / period)`` of its actions as already executed;
but the loop took one action per tick, and a tick that falls after the chunk arrives has not happened yet.
Whenever the inference does not end exactly on a tick, one action more is dropped than was executed: an action
of the plan is skipped (LeRobot logs "Indexes diff is not equal to real delay"). When the engine predicts once
per ``n_action_steps`` (``--inference.queue_threshold``), every prediction starts just after a tick, and every
chunk skips one: the arm runs through the plan faster than the policy planned it.

:class:`ExecutedActionQueue` drops exactly the actions taken while the chunk was predicted, which the queue
counts; the new chunk then resumes at the first action not yet executed. Its first ``d`` steps are the committed
prefix (``rtc_inpainting``), so the actions executed meanwhile were the chunk's own.
"""

from __future__ import annotations

from lerobot.policies.rtc import ActionQueue


class ExecutedActionQueue(ActionQueue):
    """``ActionQueue`` whose merge drops the actions executed during the inference, not the latency's ceiling."""

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
