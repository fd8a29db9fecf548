"""``lerobot-suture chain``: write a ``suture_chain`` policy directory around trained LeRobot policies.

    lerobot-suture chain --policy=DIR --output_dir=outputs/chain            # one subtask-conditioned policy
    lerobot-suture chain --policy=DIR --extract=DIR2 --output_dir=...       # DIR2 for the extraction alone

Each policy's ``pretrained_model`` directory is copied under ``policies/`` in the chain's directory, so the chain
is one self-contained directory (``lerobot-eval --policy.path``, a Hub repository).
"""

from __future__ import annotations

import shutil
from dataclasses import dataclass
from pathlib import Path

import draccus
from lerobot.configs.policies import PreTrainedConfig
from lerobot.configs.types import FeatureType, PolicyFeature
from lerobot.utils.constants import ACTION, OBS_ENV_STATE
from lerobot.utils.import_utils import register_third_party_plugins

from lerobot_suture.datasets.features import PRIVILEGED_FEATURES
from lerobot_suture.sim.state_layout import state_parts, state_size
from lerobot_suture.sim.subtasks import SUBTASKS, SubtaskRulesConfig

from .configuration_suture_chain import POLICIES_DIR, SutureChainConfig, env_state_size
from .processor_suture_chain import make_suture_chain_pre_post_processors


@dataclass
class ChainCommandConfig:
    """Args:
    output_dir: the chain's directory to write (new, or empty).
    policy: a trained policy's ``pretrained_model`` directory, for every subtask not given its own below.
    insert: the policy of the insert subtask alone (drive the needle from the entry to the exit mark).
    extract: the policy of the extract subtask alone (regrasp the tip, pull the needle out along its arc).
    lay_down: the policy of the lay-down subtask alone (carry the needle to the phantom, let go).
    pick_up: the policy of the pick-up subtask alone (grasp the needle for the next throw).
    closed_above: the high level's jaw threshold (``SubtaskRulesConfig``).
    pulled_out_travel: the high level's pull (m) that ends an extract.
    release_radius: the high level's radius (m) around the entry mark that ends an insert.
    holding_below: the high level's jaw closure below which a closed jaw holds the needle.
    device: the device the chain runs its policies on.
    subtask_from_env: read the subtask and throw from the env's observation (``--env.subtask=true``, the same
        rules run by the env at every step) instead of running the rules in the chain: a surgeon's takeover and
        hand-back then leave the chain where the arm is. The env path only (a robot reports no subtask), with
        the rules' default thresholds.
    scripted_regrasp: script the extract subtask's regrasp (a servo on the measured pose and the planned regrasp,
        ``lerobot_suture.sim.regrasp_servo``); the extract policy pulls once the jaw holds the tip.
    scripted_pull: script the extract's pull too (a turn about the needle's centre estimated from the jaw's pose at
        the hold, ``lerobot_suture.sim.pull_servo``); needs ``scripted_regrasp``.
    scripted_pick_up: script the pick-up (a servo planned from where the jaw last held the needle and the marks'
        height, ``lerobot_suture.sim.pickup_servo``); the pick-up policy acts only where every closing missed.
    """

    output_dir: Path | None = None
    policy: Path | None = None
    insert: Path | None = None
    extract: Path | None = None
    lay_down: Path | None = None
    pick_up: Path | None = None
    closed_above: float = 0.5
    pulled_out_travel: float = 0.019
    release_radius: float = 0.010
    holding_below: float = 0.95
    device: str = "cpu"
    subtask_from_env: bool = False
    scripted_regrasp: bool = False
    scripted_pull: bool = False
    scripted_pick_up: bool = False

    def __post_init__(self):
        if self.output_dir is None:
            raise ValueError("Pass --output_dir=DIR: where to write the chain.")
        if self.subtask_from_env and self.rules != SubtaskRulesConfig():
            raise ValueError(
                "With --subtask_from_env=true the env's rules name the subtask, at their default thresholds: drop "
                "--closed_above, --pulled_out_travel, --release_radius and --holding_below, or read the subtask in "
                "the chain."
            )
        if self.output_dir.exists() and any(self.output_dir.iterdir()):
            raise ValueError(f"{self.output_dir} is not empty: pass a new --output_dir, or remove it first.")
        missing = [s for s in SUBTASKS if self.policy_of(s) is None]
        if missing:
            raise ValueError(
                f"No policy for the subtasks {missing}: pass --policy=DIR for every subtask, or --{missing[0]}=DIR."
            )
        for subtask in SUBTASKS:
            if not (self.policy_of(subtask) / "config.json").is_file():
                raise FileNotFoundError(
                    f"No trained policy at {self.policy_of(subtask)} (no config.json), given for {subtask!r}: pass "
                    "the `pretrained_model` directory of a lerobot-train checkpoint."
                )

    @property
    def rules(self) -> SubtaskRulesConfig:
        """The high level's thresholds (``SubtaskRulesConfig`` checks them)."""
        return SubtaskRulesConfig(
            self.closed_above, self.pulled_out_travel, self.release_radius, self.holding_below
        )

    def policy_of(self, subtask: str) -> Path | None:
        return getattr(self, subtask) or self.policy


def chain_input_features(
    configs: list[PreTrainedConfig], subtask_from_env: bool = False, scripted_regrasp: bool = False
) -> dict[str, PolicyFeature]:
    """What the chain reads: every subtask policy's inputs but the privileged ones, and as the environment state
    the wound's marks (the high level reads them), then the env's subtask and throw with ``subtask_from_env``,
    then the planned regrasp where a subtask policy or the ``scripted_regrasp`` reads it; each policy gets its
    own environment state from them.

    Raises:
        ValueError: two policies read one key at different shapes, or their actions differ.
    """
    features: dict[str, PolicyFeature] = {}
    for config in configs:
        for key, feature in (config.input_features or {}).items():
            if key in PRIVILEGED_FEATURES or key == OBS_ENV_STATE:
                continue
            if key in features and tuple(features[key].shape) != tuple(feature.shape):
                raise ValueError(
                    f"The subtask policies read {key} at different shapes ({tuple(features[key].shape)} and "
                    f"{tuple(feature.shape)}): train them on observations of one size."
                )
            features[key] = feature
    read = {name for c in configs for name in state_parts(env_state_size(c)) or ()}
    # The high level reads the marks; the planned regrasp comes from the env where a subtask policy reads it,
    # the subtask from the chain itself, or from the env where it is asked to read it there.
    parts = (
        "marks",
        *(["subtask"] if subtask_from_env else []),
        *(["regrasp_target"] if "regrasp_target" in read or scripted_regrasp else []),
    )
    features[OBS_ENV_STATE] = PolicyFeature(type=FeatureType.ENV, shape=(state_size(parts),))
    actions = {tuple(c.output_features[ACTION].shape) for c in configs}
    if len(actions) != 1:
        raise ValueError(
            f"The subtask policies act in different spaces {sorted(actions)}: one action for all."
        )
    return features


def write_chain(cfg: ChainCommandConfig) -> Path:
    """The chain's directory, written from ``cfg``; its subtask policies copied under ``policies/``."""
    register_third_party_plugins()
    sources = {subtask: cfg.policy_of(subtask).resolve() for subtask in SUBTASKS}
    names: dict[Path, str] = {}
    for subtask, source in sources.items():  # a policy is named after the first subtask it serves
        names.setdefault(source, "all" if len(set(sources.values())) == 1 else subtask)
    configs = {source: PreTrainedConfig.from_pretrained(source) for source in names}
    for source, config in configs.items():
        if state_parts(env_state_size(config)) is None:
            raise ValueError(
                f"The policy at {source} reads a privileged environment state "
                f"({tuple(config.input_features[OBS_ENV_STATE].shape)}): a chain runs on what a robot measures. "
                "Train it with obs_type=pixels_agent_pos."
            )
    first = next(iter(configs.values()))
    config = SutureChainConfig(
        subtask_policies={subtask: names[source] for subtask, source in sources.items()},
        closed_above=cfg.closed_above,
        pulled_out_travel=cfg.pulled_out_travel,
        release_radius=cfg.release_radius,
        holding_below=cfg.holding_below,
        scripted_regrasp=cfg.scripted_regrasp,
        scripted_pull=cfg.scripted_pull,
        scripted_pick_up=cfg.scripted_pick_up,
        input_features=chain_input_features(
            list(configs.values()), cfg.subtask_from_env, cfg.scripted_regrasp
        ),
        output_features={ACTION: first.output_features[ACTION]},
        device=cfg.device,
    )
    config.validate_features()
    out = cfg.output_dir
    out.mkdir(parents=True, exist_ok=True)
    for source, name in names.items():
        shutil.copytree(source, out / POLICIES_DIR / name)
    config._save_pretrained(out)
    for processor in make_suture_chain_pre_post_processors(config):
        processor.save_pretrained(out)
    return out


def main(argv: list[str] | None = None) -> None:
    cfg = draccus.parse(config_class=ChainCommandConfig, args=argv, exit_on_error=False)
    out = write_chain(cfg)
    config = PreTrainedConfig.from_pretrained(out)
    served = ", ".join(f"{subtask}: {name}" for subtask, name in config.subtask_policies.items())
    if config.scripted_regrasp:
        served += "; the extract's regrasp" + (" and pull" if config.scripted_pull else "") + " scripted"
    if config.scripted_pick_up:
        served += "; the pick-up scripted"
    print(f"Chain written to {out} ({served}).")
    flags = " ".join(f"--env.{name}=true" for name in state_parts(env_state_size(config)))
    print(f"Run it: lerobot-eval --policy.path={out} --env.type=suture --env.task=running_suture {flags}")
    if "regrasp_target" in flags:
        print(
            "The regrasp is planned through the marks; --env.regrasp_from=release plans it from where the jaw let go."
        )
