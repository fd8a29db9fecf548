"""``SutureKeyboard`` and ``SutureGamepad``: LeRobot's keyboard and gamepad teleoperators, driving
``suture_sim`` with target poses.

LeRobot's end-effector teleoperators emit a command (``delta_x/y/z`` in [-1, 1] and a gripper command);
``suture_sim`` takes, and LeRobot records as the action, a target pose. These teleoperator types are the
surgeons of ``lerobot-suture teleop`` (``lerobot_suture.surgeon.surgeons.KeyboardSurgeon`` and
``GamepadSurgeon``, around LeRobot's ``KeyboardEndEffectorTeleop`` and ``GamepadTeleop``): the same keys,
sticks and buttons, the same integration of the command into a target pose
(``lerobot_suture.surgeon.teleop_mapping``). The target starts at the arm's measured pose when the
teleoperator first acts, and again whenever the arm has started a new scene or executed commands of
someone else since the teleoperator's last one (a policy before a DAgger correction).

``get_action`` returns ``{"x.pos": ..., ..., "jaw.pos": ...}``; ``get_teleop_events`` returns LeRobot's
teleop events of the last ``get_action``.
"""

from __future__ import annotations

import json
from functools import cached_property
from pathlib import Path
from typing import Any

from lerobot.lerobot_types import RobotAction
from lerobot.teleoperators.teleoperator import Teleoperator
from lerobot_robot_suture import link
from lerobot_robot_suture.config_suture_sim import POSE_FEATURES

from .config_suture_teleop import SutureGamepadConfig, SutureKeyboardConfig, SutureScriptedConfig


def load_script(path: Path) -> dict:
    """A teleoperator script: a JSON object keyed by control step."""
    script = json.loads(Path(path).read_text())
    if not isinstance(script, dict):
        raise ValueError(f"A teleoperator script is a JSON object keyed by control step. Got {type(script)}.")
    return {int(step): held for step, held in script.items()}


class _ArmTeleop(Teleoperator):
    """A teleoperator of ``suture_sim`` target poses: the pose features, no calibration or feedback, and the rule
    for when it takes control of the arm connected in its process."""

    def __init__(self, config):
        super().__init__(config)
        self.config = config
        self._anchor: tuple | None = None
        self._commanded_at = 0

    @cached_property
    def action_features(self) -> dict:
        return dict.fromkeys(POSE_FEATURES, float)

    @cached_property
    def feedback_features(self) -> dict:
        return {}

    @property
    def is_calibrated(self) -> bool:
        return True

    def calibrate(self) -> None:
        pass

    def configure(self) -> None:
        pass

    def send_feedback(self, feedback: dict[str, Any]) -> None:
        pass

    def _takes_control(self, robot) -> bool:
        """Whether this command starts a new spell of control: the arm started a new scene, or executed more
        than one step since this teleoperator's last command (someone else drove it). Call once per command."""
        anchor = (id(robot), robot.scene_count)
        # The arm executes at most one step per command; more since the last one: someone else drove it.
        taking = anchor != self._anchor or robot.total_steps > self._commanded_at + 1
        self._anchor = anchor
        self._commanded_at = robot.total_steps
        return taking


class _SurgeonTeleop(_ArmTeleop):
    """A surgeon of ``lerobot_suture.surgeon.surgeons`` as a LeRobot teleoperator of target poses."""

    def __init__(self, config):
        super().__init__(config)
        self.surgeon = None
        self.script = None
        self.step = 0
        """``get_action`` calls so far: the control step a script is read at."""
        self.last_events: dict = {}

    @property
    def is_connected(self) -> bool:
        return self.surgeon is not None and self.surgeon.teleop.is_connected

    def get_action(self) -> RobotAction:
        if self.surgeon is None:
            raise RuntimeError(f"{self} is not connected.")
        robot = link.connected_robot()
        if self._takes_control(robot):  # from the measured pose
            self.surgeon.take_control(None, {"agent_pos": robot.measured_pose()})
        if self.script is not None:
            self.script.before_poll(self.step)
        try:
            command = self.surgeon.poll()
        finally:
            if self.script is not None:
                self.script.after_poll(self.step)
            self.step += 1
        self.last_events = dict(command.events)
        target = self.surgeon.act(None, command)
        return {name: float(value) for name, value in zip(POSE_FEATURES, target, strict=True)}

    def get_teleop_events(self) -> dict[str, Any]:
        return dict(self.last_events)

    def disconnect(self) -> None:
        if self.surgeon is not None:
            self.surgeon.close()
            self.surgeon = None
        self.script = None
        self._anchor = None


class SutureKeyboard(_SurgeonTeleop):
    """LeRobot's ``KeyboardEndEffectorTeleop`` through ``KeyboardSurgeon``: arrows and shifts move the jaw tip,
    right / left ctrl close / open the jaw, i/k, j/l, u/o turn it."""

    config_class = SutureKeyboardConfig
    name = "suture_keyboard"

    def connect(self, calibrate: bool = True) -> None:
        from lerobot.teleoperators.keyboard import teleop_keyboard

        from lerobot_suture.surgeon.surgeons import KeyboardSurgeon, headless, keyboard_teleop

        teleop = keyboard_teleop()
        if teleop_keyboard.keyboard is None:
            raise RuntimeError(
                "pynput could not load a keyboard backend, so LeRobot's keyboard teleoperator cannot name "
                "keys. On a machine without a display, start the command with PYNPUT_BACKEND=dummy in its "
                "environment and give --teleop.script."
            )
        if self.config.script is not None:
            from lerobot_suture.surgeon.scripted_input import KeyScript

            script = load_script(self.config.script)
            keys = teleop_keyboard.keyboard.Key
            special = sorted({name for held in script.values() for name in held if len(name) > 1})
            if special and keys.left is keys.esc:
                # pynput's dummy backend gives every special key one value: an arrow would read as
                # every other special key, its release as Esc (which disconnects LeRobot's teleoperator).
                raise ValueError(
                    f"The script holds special keys {special}, which pynput's dummy backend (no display) "
                    "cannot tell apart. Headless, script character keys (i/k/j/l/u/o turn the jaw) or use "
                    "--teleop.type=suture_gamepad."
                )
            self.script = KeyScript(teleop, script)
        elif headless():
            raise ValueError(
                "suture_keyboard needs a display: pynput reads keys on X11 (not headless, not Wayland). Run "
                "it in a desktop session, or use --teleop.type=suture_gamepad, or play --teleop.script."
            )
        else:
            teleop.connect()
        self.surgeon = KeyboardSurgeon(teleop, self.config.mapping)


class SutureGamepad(_SurgeonTeleop):
    """LeRobot's ``GamepadTeleop`` through ``GamepadSurgeon``: left stick x/y, right stick z and a turn of
    the jaw, LT / RT open / close the jaw."""

    config_class = SutureGamepadConfig
    name = "suture_gamepad"

    def connect(self, calibrate: bool = True) -> None:
        from lerobot_suture.surgeon.surgeons import GamepadSurgeon, gamepad_teleop

        teleop = gamepad_teleop()
        teleop.connect()
        if self.config.script is not None:
            from lerobot_suture.surgeon.scripted_input import GamepadScript

            self.script = GamepadScript(teleop, load_script(self.config.script))
        elif teleop.gamepad.joystick is None and not teleop.config.hidapi_fallback:
            teleop.disconnect()
            raise ValueError("suture_gamepad found no gamepad (pygame sees none). Connect one and rerun.")
        self.surgeon = GamepadSurgeon(teleop, self.config.mapping)


class SutureScripted(_ArmTeleop):
    """The scripted surgeon stand-in: ``ScriptedExpert`` re-planned from the connected arm's simulator state
    whenever it takes control (a new scene, or the arm driven by someone else since its last command)."""

    config_class = SutureScriptedConfig
    name = "suture_scripted"

    def __init__(self, config: SutureScriptedConfig):
        super().__init__(config)
        self.expert = None

    @property
    def is_connected(self) -> bool:
        return self.expert is not None

    def connect(self, calibrate: bool = True) -> None:
        from lerobot_suture.expert import ScriptedExpert

        self.expert = ScriptedExpert()

    def get_action(self) -> RobotAction:
        if self.expert is None:
            raise RuntimeError(f"{self} is not connected.")
        robot = link.connected_robot()
        if self._takes_control(robot):
            self.expert.reset(robot.env)
        target = self.expert.act(robot.env)
        return {name: float(value) for name, value in zip(POSE_FEATURES, target, strict=True)}

    def disconnect(self) -> None:
        self.expert = None
        self._anchor = None
