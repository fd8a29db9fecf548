"""A needle in tissue may only turn about its own centre: the arc guard.

A curved needle slides through the holes it made only while it turns about its own axis through its centre; any
other motion of a needle in tissue (its centre moving, or a turn about another axis) cuts and stretches the tissue,
which the env measures as strain (``sim.tissue.off_arc_motion``). The extraction's bound is 2 mm of it. A learned
insert that drives the needle on after its throw is over, as the expert does, but off the arc, strains the tissue
4.5-41 mm before it lets go (``docs/results.md``), where the expert's stays within the bound.

:class:`NeedleArcGuard` keeps every action to that motion while the needle is held in tissue: each control step's
target is replaced by the pose on the needle's arc nearest to it (``sim.tissue.arc_target``: the jaw turned about
the needle's centre, so that the tip comes closest to where the target would put it, by at most
``sim.actuation.MAX_TURN_RATE_IN_TISSUE``), before the CBF filters the tip's velocity, so the CBF's guarantee stands
as it is. Out of tissue, or with the needle let go, actions pass unchanged. What it reads, the needle's centre and
axis in the jaw, is the grasp that the tip position the CBF filters already rests on.

Measured on the expert's insertions with every jaw target jittered, 15 steps from 5 steps into the tissue
(``benchmarks/arc_guard.py``, seeds 3-5): 0.5 mm to 5 cm of jitter strain the tissue 14 to 65 mm without the guard
(2 cm tore the needle out once), 0.35 to 1.34 mm with it. It is not zero: the arm realizes each step's command with
small errors, and the guard also drops the corrections by which the expert holds its planned arc (its own drive
strains 0.01-0.02 mm, 0.27-0.47 mm behind the guard). A needle pulled back out of its hole is no longer guarded, and
one stabbed in again strains as any entry does. It works in the world frame: a moving phantom's own motion is not
taken out. Opt-in (``gym.make(..., arc_guard=True)``, ``--env.arc_guard=true``): an env without it moves as it
always has.
"""

from __future__ import annotations

import gymnasium as gym


class NeedleArcGuard(gym.Wrapper):
    """Hold a needle in tissue to its arc (see the module docstring) for as long as the wrapper is open.

    Raises:
        TypeError: the env is not a suture env (no ``drive`` with the guard's switch).
    """

    def __init__(self, env: gym.Env):
        super().__init__(env)
        drive = getattr(env.unwrapped, "drive", None)
        if not hasattr(drive, "needle_on_arc"):
            raise TypeError(
                f"NeedleArcGuard needs a suture env (lerobot_suture's SutureEnv); got {type(env.unwrapped).__name__}."
            )
        drive.needle_on_arc = True

    def close(self) -> None:
        self.env.unwrapped.drive.needle_on_arc = False
        super().close()
