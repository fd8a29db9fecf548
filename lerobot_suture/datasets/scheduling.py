"""Dataset writes must not leave the process at real-time priority.

LeRobot encodes dataset videos with SVT-AV1 (``libsvtav1``). Run as root (a container, a CI runner),
SVT-AV1 raises the thread that starts it to ``SCHED_FIFO`` priority 99, and the thread stays there after the
encoding: every later computation of the process and every child it starts (dataloader workers, async env
workers, ``lerobot-train``) would run at real-time priority and starve the rest of the machine.
:func:`normal_scheduling` puts the calling thread back where it was; :func:`ordinary_scheduling` starts a
child process at ordinary priority whatever its parent was left at.
"""

from __future__ import annotations

import contextlib
import os
from collections.abc import Iterator


@contextlib.contextmanager
def normal_scheduling() -> Iterator[None]:
    """Restore the calling thread's scheduling policy and priority on exit if the body changed them."""
    if not hasattr(os, "sched_getscheduler"):  # not Linux
        yield
        return
    policy, param = os.sched_getscheduler(0), os.sched_getparam(0)
    try:
        yield
    finally:
        if os.sched_getscheduler(0) != policy or os.sched_getparam(0) != param:
            os.sched_setscheduler(0, policy, param)


def ordinary_scheduling() -> None:
    """Ordinary (``SCHED_OTHER``) scheduling for the calling process: a ``preexec_fn`` for a child (a
    training) that must not inherit a real-time priority its parent was left at."""
    if hasattr(os, "sched_setscheduler") and os.sched_getscheduler(0) != os.SCHED_OTHER:
        os.sched_setscheduler(0, os.SCHED_OTHER, os.sched_param(0))
