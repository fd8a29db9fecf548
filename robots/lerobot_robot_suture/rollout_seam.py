"""This plugin's rollout strategies in ``lerobot-rollout``: ``--strategy.type=gated_dagger``.

The config registers itself with LeRobot's strategy registry; the class is routed to through the shim
(:func:`lerobot_suture.lerobot_shim.route_strategies`), since LeRobot's factory knows only its own types.
Importing this module routes them; importing it twice is harmless.
"""

from __future__ import annotations

from lerobot_suture.lerobot_shim import route_strategies

from .gated_dagger import GatedDAggerStrategy

PLUGIN_STRATEGIES = {"gated_dagger": GatedDAggerStrategy}

route_strategies(PLUGIN_STRATEGIES)
