"""Teleoperator types ``suture_keyboard`` and ``suture_gamepad``: LeRobot's keyboard and gamepad driving
``suture_sim`` through the surgeon's mapping of ``lerobot-suture teleop``; ``suture_scripted``: the scripted
surgeon stand-in."""

from __future__ import annotations

from dataclasses import dataclass, field
from pathlib import Path

from lerobot.teleoperators.config import TeleoperatorConfig

from lerobot_suture.surgeon.teleop_mapping import TeleopMappingConfig


@TeleoperatorConfig.register_subclass("suture_keyboard")
@dataclass
class SutureKeyboardConfig(TeleoperatorConfig):
    """LeRobot's ``KeyboardEndEffectorTeleop`` (keys in ``lerobot_suture.surgeon.surgeons``).

    Args:
        mapping: speeds of a full command (``--teleop.mapping.translation_speed`` m/s, ``rotation_speed``
            rad/s).
        script: a JSON file ``{"<control step>": ["<key>", ...]}`` of the keys held during each control step
            (the teleoperator's n-th ``get_action`` is step n), played into the teleoperator's own key
            callbacks in place of a keyboard (``lerobot_suture.surgeon.scripted_input``). None: the keyboard.
    """

    mapping: TeleopMappingConfig = field(default_factory=TeleopMappingConfig)
    script: Path | None = None


@TeleoperatorConfig.register_subclass("suture_gamepad")
@dataclass
class SutureGamepadConfig(TeleoperatorConfig):
    """LeRobot's ``GamepadTeleop`` (sticks and buttons in ``lerobot_suture.surgeon.surgeons``).

    Args:
        mapping: speeds of a full command (m/s, rad/s).
        script: a JSON file ``{"<control step>": {"axes": {"<index>": value}, "buttons": [index, ...]}}`` of
            the stick and buttons held during each control step, played through a scripted joystick and
            pygame's event queue in place of a gamepad. None: the gamepad.
    """

    mapping: TeleopMappingConfig = field(default_factory=TeleopMappingConfig)
    script: Path | None = None


@TeleoperatorConfig.register_subclass("suture_scripted")
@dataclass
class SutureScriptedConfig(TeleoperatorConfig):
    """The scripted surgeon stand-in (``lerobot_suture.expert.ScriptedExpert``) as a teleoperator: it plans from
    the connected ``suture_sim``'s simulator state and takes over wherever the arm is, so a DAgger correction
    or a gate's handover runs without a person (tests, CI, benchmarks)."""
