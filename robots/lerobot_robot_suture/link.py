"""The connected simulated arm of this process, for the teleoperators that drive it.

A surgeon's command moves a target pose that starts at the arm's measured pose when the surgeon takes
control (``lerobot_suture.surgeon.teleop_mapping``). LeRobot hands a teleoperator no observation, so
the teleoperators of ``lerobot_teleoperator_suture`` read the measured pose from the ``suture_sim`` robot connected in
the same process (LeRobot's commands run both in one process).
"""

from __future__ import annotations

_connected: list = []


def register(robot) -> None:
    if robot not in _connected:
        _connected.append(robot)


def unregister(robot) -> None:
    if robot in _connected:
        _connected.remove(robot)


def connected_robot():
    """The one connected ``SutureSim`` of this process.

    Raises:
        RuntimeError: none is connected, or several are.
    """
    if len(_connected) != 1:
        raise RuntimeError(
            f"The suture teleoperators drive the one `suture_sim` robot connected in their process; "
            f"{len(_connected)} are connected. Run them with `--robot.type=suture_sim`."
        )
    return _connected[0]
