"""``SutureChainConfig``: the running suture as LeRobot policy type ``suture_chain``, a high level that picks the
subtask above a LeRobot policy for each subtask."""

from __future__ import annotations

import math
import re
from dataclasses import dataclass, field

from lerobot.configs.policies import PreTrainedConfig
from lerobot.optim.optimizers import AdamWConfig
from lerobot.utils.constants import OBS_ENV_STATE

from lerobot_suture.sim.state_layout import state_parts
from lerobot_suture.sim.subtasks import SUBTASKS, SubtaskRulesConfig

POLICIES_DIR = "policies"
"""The folder of a chain's directory that holds its subtask policies, one ``pretrained_model`` folder each."""
_NAME = re.compile(r"^[A-Za-z0-9_.-]+$")


def env_state_size(config: PreTrainedConfig) -> int:
    """Entries of the ``observation.environment_state`` a policy reads (0: none)."""
    feature = (config.input_features or {}).get(OBS_ENV_STATE)
    return math.prod(feature.shape) if feature is not None else 0


@PreTrainedConfig.register_subclass("suture_chain")
@dataclass
class SutureChainConfig(PreTrainedConfig):
    """The chain: the high level's rules (``lerobot_suture.sim.subtasks``) and which policy runs each subtask.

    The chain has no weights of its own and is not trained: each subtask policy is a LeRobot policy trained with
    ``lerobot-train``; ``lerobot-suture chain`` writes the chain's directory around them.

    Args:
        subtask_policies: for every subtask of ``SUBTASKS`` (``insert``, ``extract``, ``lay_down``,
            ``pick_up``), the name of its policy's folder under ``policies/`` in the chain's directory. One name
            for every subtask is one subtask-conditioned policy.
        closed_above: jaw closure above which the jaw counts as closed, in (0, 1) (``SubtaskRulesConfig``).
        pulled_out_travel: jaw travel (m) after closing on the tip beyond which the needle is out, > 0.
        release_radius: distance (m) from the entry mark within which a release ends an insert, > 0.
        holding_below: jaw closure below which a closed jaw holds the needle, above ``closed_above``.
        scripted_regrasp: the extract subtask's regrasp is scripted, not learned: a servo on the measured pose and
            the planned regrasp (``lerobot_suture.sim.regrasp_servo``) takes the tip, then the extract policy
            pulls. The chain then reads the planned regrasp from the env (``--env.regrasp_target=true``).
        scripted_pull: the extract subtask's pull is scripted too (needs ``scripted_regrasp``): from the step the
            jaw holds the tip, a turn about the needle's centre estimated from that measured pose
            (``lerobot_suture.sim.pull_servo``) pulls it out, and the extract policy never acts.
        scripted_pick_up: the pick-up is scripted, not learned: a servo plans the grasp from where the jaw last held
            the needle and the marks' height (``lerobot_suture.sim.pickup_servo``) and acts until the jaw holds it;
            the pick-up policy acts only where every closing missed.
    """

    subtask_policies: dict[str, str] = field(default_factory=dict)
    closed_above: float = 0.5
    pulled_out_travel: float = 0.019
    release_radius: float = 0.010
    holding_below: float = 0.95
    scripted_regrasp: bool = False
    scripted_pull: bool = False
    scripted_pick_up: bool = False
    n_obs_steps: int = 1

    def __post_init__(self):
        super().__post_init__()
        missing = [s for s in SUBTASKS if s not in self.subtask_policies]
        unknown = sorted(set(self.subtask_policies) - set(SUBTASKS))
        if missing or unknown:
            raise ValueError(
                f"`subtask_policies` must name a policy for each subtask of {SUBTASKS} and nothing else. "
                f"Missing {missing}, unknown {unknown}. `lerobot-suture chain --policy=DIR` maps them all to one "
                "subtask-conditioned policy."
            )
        for subtask, name in self.subtask_policies.items():
            if not isinstance(name, str) or not _NAME.match(name):
                raise ValueError(
                    f"`subtask_policies[{subtask!r}]` must be a folder name under {POLICIES_DIR}/ (letters, digits, "
                    f"'_', '.', '-'). Got {name!r}."
                )
        _ = self.rules  # SubtaskRulesConfig checks the thresholds
        if self.scripted_pull and not self.scripted_regrasp:
            raise ValueError(
                "`scripted_pull` pulls from the hold the scripted regrasp makes: pass `scripted_regrasp=true` too."
            )
        if self.n_obs_steps != 1:
            raise ValueError(
                f"`n_obs_steps` must be 1 (each subtask policy keeps its own). Got {self.n_obs_steps}."
            )

    @property
    def rules(self) -> SubtaskRulesConfig:
        """The high level's thresholds."""
        return SubtaskRulesConfig(
            self.closed_above, self.pulled_out_travel, self.release_radius, self.holding_below
        )

    @property
    def policy_names(self) -> list[str]:
        """The distinct subtask policies, in the order of ``SUBTASKS``."""
        return list(dict.fromkeys(self.subtask_policies[s] for s in SUBTASKS))

    @property
    def observation_delta_indices(self) -> None:
        return None

    @property
    def action_delta_indices(self) -> None:
        return None

    @property
    def reward_delta_indices(self) -> None:
        return None

    def get_optimizer_preset(self) -> AdamWConfig:
        raise NotImplementedError(self._not_trained())

    def get_scheduler_preset(self) -> None:
        return None

    def validate_features(self) -> None:
        if "observation.state" not in self.input_features:
            raise ValueError(
                "The chain's high level reads the measured pose: `observation.state` must be an input feature."
            )
        if self.scripted_regrasp and "regrasp_target" not in (state_parts(env_state_size(self)) or ()):
            raise ValueError(
                "A chain with `scripted_regrasp` servos on the planned regrasp: its environment state must hold "
                "`regrasp_target` (write it with `lerobot-suture chain --scripted_regrasp=true`)."
            )

    @staticmethod
    def _not_trained() -> str:
        return (
            "A `suture_chain` is not trained: train each subtask policy with lerobot-train, then write the chain "
            "around them with `lerobot-suture chain`."
        )
