"""Where this plugin's rollout strategies meet ``lerobot-rollout``.

LeRobot 0.6.1's strategy configs are a draccus registry that a plugin extends (``gated_dagger`` registers
itself), but ``lerobot.rollout.strategies.factory.create_strategy`` maps a config to its strategy class with a
fixed list of LeRobot's own types. :func:`install` puts a ``create_strategy`` in front of it that builds this
plugin's strategies and hands every other type to LeRobot's, in the factory module and wherever it was already
imported by name (``lerobot.rollout`` and the ``lerobot-rollout`` script, which imports it before it imports
plugins). Importing this module installs it; installing twice is harmless.
"""

from __future__ import annotations

import sys

from .gated_dagger import GatedDAggerStrategy

PLUGIN_STRATEGIES = {"gated_dagger": GatedDAggerStrategy}
_MODULES = (
    "lerobot.rollout.strategies.factory",
    "lerobot.rollout.strategies",
    "lerobot.rollout",
    "lerobot.scripts.lerobot_rollout",
)


def install() -> None:
    """Route this plugin's strategy types to their classes in ``lerobot-rollout``'s factory."""
    from lerobot.rollout.strategies import factory

    lerobot_create = getattr(factory.create_strategy, "lerobot_create_strategy", factory.create_strategy)

    def create_strategy(config):
        strategy = PLUGIN_STRATEGIES.get(config.type)
        return strategy(config) if strategy is not None else lerobot_create(config)

    create_strategy.lerobot_create_strategy = lerobot_create
    for name in _MODULES:
        module = sys.modules.get(name)
        if module is not None and hasattr(module, "create_strategy"):
            module.create_strategy = create_strategy


install()
