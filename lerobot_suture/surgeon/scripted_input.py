"""Scripted event sources that drive LeRobot's real teleoperators without a person or a device.

The teleoperator classes run unchanged; only the device at their seam is replaced:

- keyboard: ``KeyboardEndEffectorTeleop`` learns of keys through the callbacks it hands a pynput
  ``Listener`` (``_on_press`` / ``_on_release``). :class:`ScriptedKeyListener` is a pynput ``Listener``
  (so the teleoperator's ``is_connected`` holds) whose events come from a script instead of X11.
- gamepad: ``GamepadTeleop``'s ``GamepadController`` reads a pygame ``Joystick`` (axes, buttons) and
  pygame's event queue. :class:`ScriptedJoystick` stands in for the joystick and posts real pygame
  events, so the controller's own ``update`` / ``get_deltas`` / ``should_intervene`` run.

A script maps a control step to what is held during it; a key or button is pressed before the step's
poll and released after it (a tap shorter than a step would be lost by LeRobot's keyboard, which reads
key states, not presses).
"""

from __future__ import annotations

import threading
from collections.abc import Mapping, Sequence

from lerobot_suture.lerobot_shim import key_callbacks


def _key(name: str):
    """A pynput key from a name: a character (``"p"``) or a ``Key`` member (``"space"``, ``"up"``)."""
    from pynput import keyboard

    return name if len(name) == 1 else keyboard.Key[name]


def scripted_key_listener_class():
    """:class:`ScriptedKeyListener`, built on the pynput backend in use (imported lazily)."""
    from pynput import keyboard

    class ScriptedKeyListener(keyboard.Listener):
        """A pynput keyboard listener whose key events come from ``press`` / ``release`` calls."""

        def __init__(self, on_press, on_release):
            super().__init__(on_press=on_press, on_release=on_release)
            self._stopped = threading.Event()

        def _run(self):
            self._mark_ready()
            self._stopped.wait()

        def _stop_platform(self):
            self._stopped.set()

        def press(self, name: str) -> None:
            self.on_press(_key(name), False)

        def release(self, name: str) -> None:
            self.on_release(_key(name), False)

    return ScriptedKeyListener


class KeyScript:
    """Keys held during given control steps, played into a keyboard teleoperator.

    Args:
        teleop: a LeRobot ``KeyboardEndEffectorTeleop`` (not connected: the scripted listener connects it).
        script: control step -> key names held during it (``"space"``, ``"up"``, ``"p"``, ...).
    """

    def __init__(self, teleop, script: Mapping[int, Sequence[str]]):
        self.teleop = teleop
        self.script = {int(k): list(v) for k, v in script.items()}
        self.listener = scripted_key_listener_class()(*key_callbacks(teleop))
        self.listener.start()
        self.listener.wait()
        teleop.listener = self.listener  # what `connect` would set on a desktop
        self._held: list[str] = []

    def before_poll(self, step: int) -> None:
        self._held = self.script.get(step, [])
        for name in self._held:
            self.listener.press(name)

    def after_poll(self, step: int) -> None:
        for name in self._held:
            self.listener.release(name)
        self._held = []


class ScriptedJoystick:
    """A pygame ``Joystick`` stand-in: axes and buttons set per control step by a script.

    Args:
        script: control step -> {"axes": {index: value in [-1, 1]}, "buttons": [index, ...]} held then.
    """

    def __init__(self, script: Mapping[int, Mapping]):
        self.script = {int(k): dict(v) for k, v in script.items()}
        self._axes: dict[int, float] = {}
        self._buttons: set[int] = set()

    def init(self) -> None:
        pass

    def quit(self) -> None:
        pass

    def get_name(self) -> str:
        return "scripted joystick"

    def get_axis(self, index: int) -> float:
        return float(self._axes.get(index, 0.0))

    def get_button(self, index: int) -> int:
        return int(index in self._buttons)


class GamepadScript:
    """Plays a :class:`ScriptedJoystick` script into a connected LeRobot ``GamepadTeleop``."""

    def __init__(self, teleop, script: Mapping[int, Mapping]):
        import pygame

        self.pygame = pygame
        self.teleop = teleop
        self.joystick = ScriptedJoystick(script)
        teleop.gamepad.joystick = self.joystick  # what `GamepadController.start` finds on a desktop
        teleop.gamepad.running = True

    def before_poll(self, step: int) -> None:
        pygame = self.pygame
        entry = self.joystick.script.get(step, {})
        self.joystick._axes = {int(k): float(v) for k, v in entry.get("axes", {}).items()}
        pressed = {int(b) for b in entry.get("buttons", [])}
        for button in sorted(pressed - self.joystick._buttons):
            pygame.event.post(pygame.event.Event(pygame.JOYBUTTONDOWN, button=button, joy=0, instance_id=0))
        for button in sorted(self.joystick._buttons - pressed):
            pygame.event.post(pygame.event.Event(pygame.JOYBUTTONUP, button=button, joy=0, instance_id=0))
        self.joystick._buttons = pressed
        # The controller re-reads its intervention button only while handling an event, as with a real
        # stick, whose axes report motion every frame.
        pygame.event.post(pygame.event.Event(pygame.JOYAXISMOTION, axis=0, value=0.0, joy=0, instance_id=0))

    def after_poll(self, step: int) -> None:
        pass
