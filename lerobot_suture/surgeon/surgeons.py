"""The surgeons who can take over a policy run: nobody, the scripted expert, a keyboard or a gamepad.

Each is polled once per control step for its events (take over, hand back) and, while in control,
asked for the step's (10,) env action. The keyboard and the gamepad are LeRobot's own teleoperators
(``KeyboardEndEffectorTeleop``, ``GamepadTeleop``), read with LeRobot's ``get_action`` and
``get_teleop_events``; the surgeon's command is integrated into a target pose by
:mod:`~lerobot_suture.surgeon.teleop_mapping`.

Keyboard (LeRobot's keys, plus rotation and handover keys it leaves free):

=============================== =========================================================
key                             effect
=============================== =========================================================
arrows                          jaw tip along world x (left/right) and y (up/down)
left / right shift              jaw tip down / up (world z)
right / left ctrl               close / open the jaw (opening releases the needle)
i / k, j / l, u / o             turn the jaw about its own x, y, z axis (+ / -)
t or space, or any key above     take over from the policy
p                               hand control back to the policy
s, r, q                         LeRobot's success / re-record / quit events
=============================== =========================================================

Gamepad (LeRobot's mapping, plus a rotation axis and a hand-back button):

=============================== =========================================================
input                           effect
=============================== =========================================================
left stick                      jaw tip along world x and y
right stick, vertical           jaw tip along world z
right stick, horizontal (axis 2) turn the jaw about its own z axis
RB (button 5) held              take over (LeRobot's intervention button)
LB (button 4)                   hand control back to the policy
LT / RT (buttons 7 / 6)         open / close the jaw
=============================== =========================================================
"""

from __future__ import annotations

import os
import sys

import numpy as np

from lerobot_suture.runtime.takeover import ExpertSurgeon, NoSurgeon, SurgeonInput
from lerobot_suture.surgeon.teleop_mapping import TeleopMappingConfig, env_action, initial_target, step_target

SURGEON_CHOICES = ("none", "expert", "keyboard", "gamepad")

TAKE_OVER_KEYS = ("t", "space")
HAND_BACK_KEY = "p"
ROTATION_KEYS = {"i": (0, 1.0), "k": (0, -1.0), "j": (1, 1.0), "l": (1, -1.0), "u": (2, 1.0), "o": (2, -1.0)}
"""Key -> (jaw axis, sign) of a rotation command."""
GAMEPAD_ROTATION_AXIS = 2
GAMEPAD_HAND_BACK_BUTTON = 4
GAMEPAD_DEADZONE = 0.1  # LeRobot's GamepadController default


class TeleopSurgeon(NoSurgeon):
    """A person at a LeRobot teleoperator: the command moves a target pose held from the takeover."""

    present = True

    def __init__(self, teleop, mapping: TeleopMappingConfig | None = None):
        self.teleop = teleop
        self.mapping = mapping or TeleopMappingConfig()
        self.target: np.ndarray | None = None

    def take_control(self, env, observation: dict) -> None:
        self.target = initial_target(observation["agent_pos"])  # the measured pose

    def act(self, env, command: SurgeonInput) -> np.ndarray:
        if self.target is None:
            raise RuntimeError("`take_control` must come before the surgeon's first action.")
        self.target = step_target(self.target, command.teleop_action, command.rotation, self.mapping)
        return env_action(self.target)

    def close(self) -> None:
        if self.teleop.is_connected:
            self.teleop.disconnect()


class KeyboardSurgeon(TeleopSurgeon):
    """LeRobot's ``KeyboardEndEffectorTeleop`` (connected), with rotation and handover keys."""

    name = "keyboard"

    def poll(self) -> SurgeonInput:
        from lerobot.teleoperators.utils import TeleopEvents

        action = self.teleop.get_action()
        rotation = np.zeros(3)
        take_over = hand_back = False
        keep = []
        # Keys LeRobot does not map go to its `misc_keys_queue` ("useful for ... interventions"); its
        # `get_teleop_events` reads s / r / q from there, so those go back in.
        queue = self.teleop.misc_keys_queue
        while not queue.empty():
            key = queue.get_nowait()
            name = key if isinstance(key, str) else getattr(key, "name", None)
            if name in ROTATION_KEYS:
                axis, sign = ROTATION_KEYS[name]
                rotation[axis] += sign
            elif name in TAKE_OVER_KEYS:
                take_over = True
            elif name == HAND_BACK_KEY:
                hand_back = True
            else:
                keep.append(key)
        for key in keep:
            queue.put(key)
        events = self.teleop.get_teleop_events()
        take_over = take_over or bool(events[TeleopEvents.IS_INTERVENTION]) or bool(rotation.any())
        return SurgeonInput(action, np.clip(rotation, -1, 1), take_over, hand_back, events)


class GamepadSurgeon(TeleopSurgeon):
    """LeRobot's ``GamepadTeleop`` (connected), with a rotation axis and a hand-back button."""

    name = "gamepad"

    def poll(self) -> SurgeonInput:
        from lerobot.teleoperators.utils import TeleopEvents

        action = self.teleop.get_action()
        events = self.teleop.get_teleop_events()
        joystick = self.teleop.gamepad.joystick
        turn = float(joystick.get_axis(GAMEPAD_ROTATION_AXIS)) if joystick is not None else 0.0
        turn = 0.0 if abs(turn) < GAMEPAD_DEADZONE else -turn
        hand_back = bool(joystick.get_button(GAMEPAD_HAND_BACK_BUTTON)) if joystick is not None else False
        take_over = bool(events[TeleopEvents.IS_INTERVENTION])
        return SurgeonInput(action, np.array([0.0, 0.0, turn]), take_over, hand_back, events)


def headless() -> bool:
    """No display to read a keyboard from (Linux without X11 or Wayland)."""
    return sys.platform.startswith("linux") and not (
        os.environ.get("DISPLAY") or os.environ.get("WAYLAND_DISPLAY")
    )


def keyboard_teleop():
    """LeRobot's ``KeyboardEndEffectorTeleop`` (not connected), importable without a display.

    pynput picks its X11 backend on Linux and fails to import without a display, and LeRobot's keyboard
    module then cannot name a key. Headless, pynput's ``dummy`` backend is selected before the import: the
    key names exist, no key is captured (LeRobot's ``connect`` warns so), and a scripted listener
    (:func:`~lerobot_suture.surgeon.scripted_input.attach_scripted_keyboard`) can feed the teleoperator's
    own key callbacks.
    """
    if headless():
        os.environ.setdefault("PYNPUT_BACKEND", "dummy")
    from lerobot.teleoperators.keyboard import KeyboardEndEffectorTeleop, KeyboardEndEffectorTeleopConfig

    return KeyboardEndEffectorTeleop(KeyboardEndEffectorTeleopConfig(use_gripper=True))


def gamepad_teleop():
    """LeRobot's ``GamepadTeleop`` (not connected); headless, SDL's dummy video driver serves its events."""
    if headless():
        os.environ.setdefault("SDL_VIDEODRIVER", "dummy")
        os.environ.setdefault("SDL_AUDIODRIVER", "dummy")  # pygame.init opens audio too
    from lerobot.teleoperators.gamepad import GamepadTeleop, GamepadTeleopConfig

    return GamepadTeleop(GamepadTeleopConfig(use_gripper=True))


def make_surgeon(name: str, mapping: TeleopMappingConfig | None = None, connect: bool = True):
    """The surgeon ``name`` (one of :data:`SURGEON_CHOICES`); a teleoperator is connected when ``connect``.

    Raises:
        ValueError: an unknown name, or a keyboard with no display to read it from.
    """
    if name not in SURGEON_CHOICES:
        raise ValueError(f"`surgeon` must be one of {SURGEON_CHOICES}. Got {name!r}.")
    if name == "none":
        return NoSurgeon()
    if name == "expert":
        return ExpertSurgeon()
    if name == "keyboard":
        if connect and headless():
            raise ValueError(
                "`--surgeon=keyboard` needs a display: pynput reads keys on X11 (not headless, not Wayland). "
                "Run it in a desktop session, or use `--surgeon=gamepad` or `--surgeon=expert`."
            )
        teleop = keyboard_teleop()
        surgeon = KeyboardSurgeon(teleop, mapping)
    else:
        teleop = gamepad_teleop()
        surgeon = GamepadSurgeon(teleop, mapping)
    if connect:
        teleop.connect()
        if name == "gamepad" and teleop.gamepad.joystick is None and not teleop.config.hidapi_fallback:
            teleop.disconnect()
            raise ValueError(
                "`--surgeon=gamepad` found no gamepad (pygame sees none). Connect one and rerun."
            )
    return surgeon
