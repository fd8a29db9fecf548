"""``SutureChainPolicy``: the running suture's high level above one LeRobot policy per subtask.

Each control step the rules of ``lerobot_suture.sim.subtasks`` read every environment's measured pose
(``observation.state``) and the registered wound's marks (``observation.environment_state``, (6,) m, then the
planned regrasp (9,) where a subtask policy reads it; on the robot path, after the pose in ``observation.state``:
:func:`state_apart`) and say which subtask its arm is in and which throw; the policy serving that subtask gives
the action. A subtask policy sees the environment state it was trained on: any combination of the marks (6,),
the subtask and throw (5,) and the planned regrasp (9,) (``lerobot_suture.sim.state_layout``), or none.

A chain written with ``--subtask_from_env=true`` reads the subtask and throw from the observation instead
(``observation.environment_state`` then holds the marks and the same rules' reading, ``--env.subtask=true``): the
env runs the rules at every step, whoever acts, so a surgeon who takes a subtask over and hands back (which resets
the policy, as LeRobot's DAgger does) leaves the chain at the subtask and throw the arm is in, not at the first
throw's insert where its own rules would start again.

A chain written with ``--scripted_regrasp=true`` scripts the extract subtask's regrasp: from the step an
environment enters ``extract``, a :class:`~lerobot_suture.sim.regrasp_servo.RegraspServo` on its measured pose and
planned regrasp acts until the jaw holds the tip; the extract policy, reset then, pulls. A jaw that held the tip
and then reads empty (its encoder fully closed: the needle slipped out) gets a new servo, which regrasps. Written
with ``--scripted_pull=true`` too, the pull is scripted as well: a
:class:`~lerobot_suture.sim.pull_servo.PullServo` turns the held needle out about its centre, estimated from the
jaw's measured pose at the hold, and the extract policy never acts.

A chain written with ``--scripted_pick_up=true`` scripts the pick-up: from the step an environment enters
``pick_up``, a :class:`~lerobot_suture.sim.pickup_servo.PickupServo` plans the grasp from where the jaw last held
the needle (its measured pose then, :class:`~lerobot_suture.sim.pickup_servo.NeedleRelease`) and the registered
surface (the marks' height), and acts until the jaw holds the needle; the next throw's insert acts then. A servo
whose every closing missed hands the arm to the pick-up policy, reset.

Subtask policies keep their own observation and action queues, one row per environment. A policy that an
environment enters is reset first, so its first action is predicted from the new subtask's observation and not
taken from a chunk queued before the switch; the other environments it serves then predict afresh too (a
replanning, no stale action). Every step each needed policy runs on the whole batch, and each environment takes
the row of its own subtask's policy.
"""

from __future__ import annotations

from pathlib import Path

import numpy as np
import torch
from lerobot.policies.pretrained import PreTrainedPolicy
from lerobot.utils.constants import OBS_ENV_STATE, OBS_STATE
from torch import Tensor, nn

from lerobot_suture.safety.ood.gate import silent_status
from lerobot_suture.sim.pickup_servo import NeedleRelease, PickupServo, PickupServoConfig, resting_needle
from lerobot_suture.sim.regrasp_servo import RegraspServoConfig
from lerobot_suture.sim.scripted_extract import ScriptedExtract
from lerobot_suture.sim.state_layout import LAYOUTS, registered_parts, state_parts
from lerobot_suture.sim.subtasks import SubtaskRules, subtask_reading, subtask_vector

from .configuration_suture_chain import POLICIES_DIR, SutureChainConfig, env_state_size

POSE_DIM = 10
"""Entries of the measured pose (``observation.state`` on the env path)."""


def state_apart(batch: dict[str, Tensor], env_state_size: int) -> dict[str, Tensor]:
    """``batch`` with the registered parts as ``observation.environment_state``: on the robot path LeRobot stacks
    every scalar the robot reports into ``observation.state``, so ``--robot.marks=true`` gives the pose and then
    the marks, (16,), and ``--robot.regrasp_target=true`` the planned regrasp after them, (25,); the env path gives
    them apart already."""
    state = batch[OBS_STATE]
    if OBS_ENV_STATE in batch or state.shape[-1] == POSE_DIM:
        return batch
    if "subtask" in (state_parts(env_state_size) or ()):
        raise ValueError(
            "This chain reads the subtask from the env (written with --subtask_from_env=true), and a robot reports "
            "none: write the chain again without it for the robot path."
        )
    if state.shape[-1] != POSE_DIM + env_state_size:
        flags = " ".join(f"--robot.{name}=true" for name in state_parts(env_state_size) or ())
        raise ValueError(
            f"The chain reads the pose ({POSE_DIM}) and then {env_state_size} registered entries from "
            f"observation.state on the robot path, and it holds {state.shape[-1]}: run the robot with {flags} and "
            "no other registered feature."
        )
    return {**batch, OBS_STATE: state[..., :POSE_DIM], OBS_ENV_STATE: state[..., POSE_DIM:]}


def environment_state_for(size: int, parts: dict[str, Tensor | None]) -> Tensor | None:
    """What a subtask policy whose environment state has ``size`` entries reads (0: none), stacked from ``parts``
    (name of ``STATE_PARTS`` -> (B, n) tensor, or None where the observation lacks it) in the env's order.

    Raises:
        ValueError: a size that is no combination of the parts, or a part it needs is absent.
    """
    layout = state_parts(size)
    if layout is None:
        sizes = ", ".join(f"{'+'.join(names)} ({n})" for n, names in LAYOUTS.items())
        raise ValueError(
            f"A subtask policy reads an environment state of {size} entries; the chain gives {sizes}."
        )
    if not layout:
        return None
    missing = [name for name in layout if parts.get(name) is None]
    if missing:
        env_flags = " ".join(f"`--env.{name}=true`" for name in missing)
        robot_flags = " ".join(f"`--robot.{name}=true`" for name in missing)
        raise ValueError(
            f"A subtask policy reads {missing}, and the observation has none: run the env with {env_flags} (the "
            f"robot with {robot_flags})."
        )
    first = parts[layout[0]]
    return torch.cat([parts[name].to(first) for name in layout], dim=-1)


class SutureChainPolicy(PreTrainedPolicy):
    """The chain of ``SutureChainConfig``: load it with :meth:`from_pretrained` from a directory that
    ``lerobot-suture chain`` wrote (its subtask policies in ``policies/<name>/``)."""

    config_class = SutureChainConfig
    name = "suture_chain"

    def __init__(self, config: SutureChainConfig, subtask_policies: dict | None = None, **kwargs):
        """``subtask_policies``: name -> (policy, preprocessor, postprocessor), one per name of
        ``config.subtask_policies``."""
        super().__init__(config)
        subtask_policies = subtask_policies or {}
        missing = sorted(set(config.policy_names) - set(subtask_policies))
        if missing:
            raise ValueError(
                f"The chain needs its subtask policies {missing}: load it with SutureChainPolicy.from_pretrained "
                "from a directory that `lerobot-suture chain` wrote."
            )
        self.policies = nn.ModuleDict({name: subtask_policies[name][0] for name in config.policy_names})
        self._processors = {name: subtask_policies[name][1:] for name in config.policy_names}
        self._rules: list[SubtaskRules] = []
        self.readings: list[tuple[str, int]] = []
        """Each environment's (subtask, throw) at the last step."""
        self.extracts: list[ScriptedExtract | None] = []
        """Each environment's scripted extract while it serves the throw (``scripted_regrasp``), else None."""
        self.releases: list[NeedleRelease] = []
        """Where each environment's jaw last held the needle (``scripted_pick_up``)."""
        self.pickups: list[PickupServo | None] = []
        """Each environment's scripted pick-up while it acts (``scripted_pick_up``), else None."""
        self.serving: list[str | None] = []
        """The policy that gave each environment's action at the last step (None: a scripted part)."""

    @classmethod
    def from_pretrained(cls, pretrained_name_or_path, *, config: SutureChainConfig | None = None, **kwargs):
        from lerobot.configs.policies import PreTrainedConfig

        from lerobot_suture.runtime.policy import load_policy

        path = Path(pretrained_name_or_path)
        if not path.is_dir():
            from huggingface_hub import snapshot_download

            path = Path(snapshot_download(str(pretrained_name_or_path), revision=kwargs.get("revision")))
        config = config or PreTrainedConfig.from_pretrained(path)
        device = config.device or "cpu"
        loaded = {}
        for name in config.policy_names:
            sub_path = path / POLICIES_DIR / name
            if not (sub_path / "config.json").is_file():
                raise FileNotFoundError(
                    f"The chain at {path} names the subtask policy {name!r}, and {sub_path} holds none. Write the "
                    "chain again with `lerobot-suture chain`."
                )
            loaded[name] = load_policy(sub_path, device)
        return cls(config, loaded)

    def _save_pretrained(self, save_directory: Path, state_dict=None) -> None:
        self.config._save_pretrained(save_directory)
        for name, policy in self.policies.items():
            target = Path(save_directory) / POLICIES_DIR / name
            policy.save_pretrained(target)
            for processor in self._processors[name]:
                processor.save_pretrained(target)

    def get_optim_params(self) -> dict:
        raise NotImplementedError(self.config._not_trained())

    def forward(self, batch: dict[str, Tensor]):
        raise NotImplementedError(self.config._not_trained())

    def reset(self):
        self._rules, self.readings, self.extracts, self.releases, self.pickups = [], [], [], [], []
        self.serving = []
        for policy in self.policies.values():
            policy.reset()

    def predict_action_chunk(self, batch: dict[str, Tensor], **kwargs) -> Tensor:
        raise NotImplementedError(
            "A `suture_chain` acts one step at a time (its subtask can change at any step): run it with "
            "select_action, as lerobot-eval and lerobot-rollout's sync engine do."
        )

    def _registered(self, batch: dict[str, Tensor]) -> dict[str, Tensor]:
        """The registered parts the observation's environment state holds (the chain's input layout)."""
        parts = registered_parts(batch.get(OBS_ENV_STATE))
        if parts is None:
            raise ValueError(
                f"The chain reads the registered wound, and observation.environment_state holds "
                f"{batch[OBS_ENV_STATE].shape[-1]} entries, the privileged state: run the env with "
                "obs_type=pixels_agent_pos and `--env.marks=true`."
            )
        return parts

    def _read_subtasks(self, batch: dict[str, Tensor], parts: dict[str, Tensor]) -> set[str]:
        """Update each environment's subtask (the env's reading where the observation holds it, else the rules');
        the policies some environment entered."""
        before = self.readings
        if "subtask" in parts:
            self.readings = [subtask_reading(v) for v in parts["subtask"].detach().float().cpu().numpy()]
            if len(before) != len(self.readings):  # the episode's first step, or the first after a reset
                return set()
        else:
            poses = batch[OBS_STATE].detach().float().cpu().numpy().reshape(len(batch[OBS_STATE]), -1)
            marks = parts.get("marks")
            marks_np = marks.detach().float().cpu().numpy() if marks is not None else [None] * len(poses)
            if len(self._rules) != len(poses):  # the episode's first step (lerobot-eval resets before it)
                self._rules = [SubtaskRules(self.config.rules) for _ in poses]
                self.readings = [rules.reset(pose) for rules, pose in zip(self._rules, poses, strict=True)]
                return set()
            self.readings = [r.update(p, m) for r, p, m in zip(self._rules, poses, marks_np, strict=True)]
        entered = {
            self.config.subtask_policies[new[0]]
            for old, new in zip(before, self.readings, strict=True)
            if new != old
        }
        return entered

    def _scripted_actions(
        self, batch: dict[str, Tensor], parts: dict[str, Tensor], before: list
    ) -> dict[int, Tensor]:
        """The scripted actions of each environment they serve this step (``scripted_regrasp``,
        ``scripted_pick_up``). The policy the arm goes back to is reset as a scripted part ends, so its first action
        comes from the next step's observation."""
        if len(before) != len(self.readings):  # the episode's first step
            before = [None] * len(self.readings)
        poses = batch[OBS_STATE].detach().double().cpu().numpy()
        actions, handed_back = {}, set()
        if self.config.scripted_regrasp:
            self._extract_actions(poses, parts["regrasp_target"], before, actions, handed_back)
        if self.config.scripted_pick_up:
            self._pick_up_actions(poses, parts["marks"], before, actions, handed_back)
        for subtask in handed_back:
            self.policies[self.config.subtask_policies[subtask]].reset()
        return actions

    def _extract_actions(self, poses, regrasp_target: Tensor, before: list, actions: dict, handed_back: set):
        """A scripted extract starts where an environment enters ``extract`` (or starts in it) and acts until the
        jaw holds the tip, with ``scripted_pull`` until the needle is turned out, whatever the rules read meanwhile
        (they end the extract on the jaw's travel, short of the whole turn)."""
        if len(self.extracts) != len(self.readings):
            self.extracts = [None] * len(self.readings)
        targets = regrasp_target.detach().double().cpu().numpy()
        for i, (reading, old) in enumerate(zip(self.readings, before, strict=True)):
            extract = self.extracts[i]
            if reading[0] == "extract" and (old is None or old[0] != "extract"):
                extract = ScriptedExtract(
                    self.config.scripted_pull,
                    RegraspServoConfig(
                        closed_above=self.config.closed_above, holding_below=self.config.holding_below
                    ),
                )
            elif reading[0] != "extract" and not (extract is not None and extract.pulling):
                extract = None
            self.extracts[i] = extract
            action = None if extract is None else extract.act(poses[i], targets[i])
            if action is not None:
                actions[i] = torch.from_numpy(action)
                if extract.handed_back:
                    handed_back.add(reading[0])

    def _pick_up_actions(self, poses, marks: Tensor, before: list, actions: dict, handed_back: set):
        """A scripted pick-up starts where an environment enters ``pick_up`` after its jaw held the needle, planned
        from where it last held it and the marks' height, and acts until it is done; one whose every closing
        missed hands the arm back to the pick-up policy."""
        if len(self.pickups) != len(self.readings):
            self.pickups = [None] * len(self.readings)
            self.releases = [
                NeedleRelease(self.config.closed_above, self.config.holding_below) for _ in self.readings
            ]
        marks_np = marks.detach().double().cpu().numpy()
        for i, (reading, old) in enumerate(zip(self.readings, before, strict=True)):
            release, pickup = self.releases[i], self.pickups[i]
            if reading[0] != "pick_up":
                release.update(poses[i], reading[0])
                self.pickups[i] = None
                continue
            if (old is None or old[0] != "pick_up") and release.pose is not None:
                surface = float(marks_np[i, [2, 5]].mean())
                pickup = self.pickups[i] = PickupServo(
                    resting_needle(*release.pose, release.held_angle, surface),
                    marks_np[i],
                    PickupServoConfig(
                        closed_above=self.config.closed_above, holding_below=self.config.holding_below
                    ),
                )
            if pickup is None or pickup.done:
                continue
            actions[i] = torch.from_numpy(pickup.act(poses[i], marks_np[i]))
            if pickup.done and not pickup.held:
                handed_back.add("pick_up")

    @torch.no_grad()
    def select_action(self, batch: dict[str, Tensor], **kwargs) -> Tensor:
        batch = state_apart(batch, env_state_size(self.config))
        parts = self._registered(batch)
        before = list(self.readings)
        entered = self._read_subtasks(batch, parts)
        for name in entered:
            self.policies[name].reset()
        scripted = self._scripted_actions(batch, parts, before)
        parts["subtask"] = torch.from_numpy(np.stack([subtask_vector(*reading) for reading in self.readings]))
        serving = [
            None if i in scripted else self.config.subtask_policies[subtask]
            for i, (subtask, _) in enumerate(self.readings)
        ]
        self.serving, actions = serving, None
        for name in dict.fromkeys(s for s in serving if s is not None):
            policy = self.policies[name]
            preprocessor, postprocessor = self._processors[name]
            sub_batch = {k: v for k, v in batch.items() if k != OBS_ENV_STATE}
            env_state = environment_state_for(env_state_size(policy.config), parts)
            if env_state is not None:
                sub_batch[OBS_ENV_STATE] = env_state
            action = postprocessor(policy.select_action(preprocessor(sub_batch)))
            if actions is None:
                actions = torch.empty_like(action)
            rows = torch.tensor([s == name for s in serving])
            actions[rows] = action[rows.to(action.device)]
        if scripted:
            if actions is None:
                actions = torch.empty((len(serving), *next(iter(scripted.values())).shape))
            for i, action in scripted.items():
                actions[i] = action.to(actions)
        return actions

    def ood_status(self, index: int = 0) -> dict:
        """The gate status (the keys of ``silent_status``) of the policy that gave environment ``index``'s action at
        the last step: an ensemble's members' score, so that a gate per stage (``runtime.gates.StageGates``) tests
        each subtask's policy against that subtask's threshold. Silent where a scripted part acted or the policy
        holds no gate."""
        name = self.serving[index] if index < len(self.serving) else None
        status = None if name is None else getattr(self.policies[name], "ood_status", None)
        return status(index) if callable(status) else silent_status()
