"""Run a trained LeRobot policy on suture envs (one, or several in one batch), as ``lerobot-eval`` does.

The policy is loaded through LeRobot's own factory, which discovers the policy plugin, with its
saved pre- and post-processors; observations go through the same steps as in ``lerobot-eval``
(``preprocess_observation``, task string, preprocessor, ``select_action`` under inference mode,
postprocessor).
"""

from __future__ import annotations

import dataclasses
import json
import logging
import shutil
from collections.abc import Sequence
from enum import Enum
from pathlib import Path

import numpy as np
import torch

from lerobot_suture.datasets.features import PRIVILEGED_FEATURES
from lerobot_suture.safety.ood.calibration_file import CALIBRATION_FILENAME, calibration_report_file
from lerobot_suture.sim.state_layout import state_parts
from lerobot_suture.sim.task import TASK

logger = logging.getLogger(__name__)
ACTION = "action"  # LeRobot's key of the action (and of a policy's action queue)


def load_policy(policy_path: str | Path, device: str = "cpu", overrides: dict | None = None):
    """A trained policy and its processors from a pretrained directory (offline).

    Args:
        overrides: config fields to change before the policy is built, as ``lerobot-eval``'s
            ``--policy.FIELD=VALUE`` does, e.g. ``{"num_inference_steps": 5}``: the inference-time
            approximations (fewer denoising steps, fewer samples per member). Validated by the config.

    Returns:
        (policy, preprocessor, postprocessor)

    Raises:
        FileNotFoundError: the directory or its ``config.json`` is missing.
        ValueError: an override names no field of the policy's config, a value its config refuses, or one
            the gate's calibration was not fitted with (the policy's message says how to calibrate for it).
    """
    from lerobot.configs.policies import PreTrainedConfig
    from lerobot.policies.factory import get_policy_class, make_pre_post_processors
    from lerobot.utils.import_utils import register_third_party_plugins

    path = Path(policy_path)
    if not (path / "config.json").is_file():
        raise FileNotFoundError(
            f"No trained policy at {path} (no config.json). Pass the `pretrained_model` directory of a "
            "lerobot-train checkpoint, e.g. outputs/train/NAME/checkpoints/last/pretrained_model."
        )
    register_third_party_plugins()
    config = override_config(PreTrainedConfig.from_pretrained(path), overrides)
    config.device = device
    policy = get_policy_class(config.type).from_pretrained(path, config=config)
    policy.eval()
    preprocessor, postprocessor = make_pre_post_processors(
        policy_cfg=config,
        pretrained_path=str(path),
        preprocessor_overrides={"device_processor": {"device": device}},
    )
    return policy, preprocessor, postprocessor


def parse_overrides(items: Sequence[str]) -> dict:
    """A command line's ``FIELD=VALUE`` config overrides as a dict, each value read as JSON (``[32,64]``,
    ``8``, ``true``) or, if it is none, kept as the string (``DDIM``).

    Raises:
        ValueError: an item has no ``=`` or no field name.
    """
    overrides = {}
    for item in items:
        field, sep, value = item.partition("=")
        if not sep or not field:
            raise ValueError(f"Config overrides are FIELD=VALUE pairs, e.g. n_action_steps=8. Got {item!r}.")
        try:
            overrides[field] = json.loads(value)
        except json.JSONDecodeError:
            overrides[field] = value
    return overrides


def override_config(config, overrides: dict | None):
    """``config`` with the fields of ``overrides`` changed, validated by the config's own checks.

    Raises:
        ValueError: an override names no field of the config, or a value the config refuses.
    """
    if not overrides:
        return config
    unknown = sorted(set(overrides) - {f.name for f in dataclasses.fields(config)})
    if unknown:
        raise ValueError(f"{unknown} name no field of the {config.type!r} policy's config; drop them.")
    return dataclasses.replace(config, **overrides)  # runs the config's own validation


def calibration_file(policy_dir: str | Path) -> Path:
    """Where the policy in ``policy_dir`` keeps its gate's calibration (its ``ood.calibration_file``)."""
    config = json.loads((Path(policy_dir) / "config.json").read_text())
    return Path(policy_dir) / config.get("ood", {}).get("calibration_file", CALIBRATION_FILENAME)


def copy_policy(source: str | Path, out: str | Path, overrides: dict | None = None) -> None:
    """The policy's files copied to ``out`` without its calibrations (they hold only for the policy they were
    fitted to), ``overrides`` written into the copy's ``config.json``; ``out`` appears whole or not at all."""
    source, out = Path(source), Path(out)
    partial = out.with_name(out.name + ".partial")
    shutil.rmtree(partial, ignore_errors=True)
    own = calibration_file(source).name

    def calibrations(_, names) -> list[str]:  # the policy's own, and any other fitted for an engine
        return [
            n for n in names if n in (own, calibration_report_file(own)) or n.startswith("ood_calibration")
        ]

    shutil.copytree(source, partial, ignore=calibrations)
    if overrides:
        config = json.loads((partial / "config.json").read_text())
        (partial / "config.json").write_text(json.dumps({**config, **overrides}, indent=4))
    partial.rename(out)


def copy_with_overrides(source: str | Path, target: str | Path, overrides: dict) -> Path:
    """A copy of the policy directory ``source`` at ``target`` whose ``config.json`` holds ``overrides``
    (e.g. fewer DDIM steps), without the gate's calibration (:func:`copy_policy`); returns ``target``.

    Raises:
        FileExistsError: ``target`` exists and is not empty (nothing there is overwritten).
        ValueError: an override the policy's config refuses (checked before anything is copied).
    """
    from lerobot.configs.policies import PreTrainedConfig
    from lerobot.utils.import_utils import register_third_party_plugins

    target = Path(target)
    if target.exists() and any(target.iterdir()):
        raise FileExistsError(f"{target} exists and is not empty: pick another `copy_to`, or remove it.")
    register_third_party_plugins()
    override_config(PreTrainedConfig.from_pretrained(source), overrides)
    copy_policy(source, target, overrides)
    return target


WRIST_IMAGE = "observation.images.wrist"
"""The wrist camera's image feature (the env's ``pixels["wrist"]`` with ``wrist_camera=True``)."""


def env_kwargs_for_policy(config) -> dict:
    """The suture env's observation arguments that produce what a trained policy reads.

    Raises:
        ValueError: the policy reads features the suture env does not produce.
    """
    features = dict(config.input_features or {})
    privileged = sorted(set(features) & set(PRIVILEGED_FEATURES))
    if privileged:
        logger.warning(
            "The policy lists %s among its inputs: LeRobot makes every observation.* key of a dataset one, and "
            "these are privileged training targets that no env or real system gives. LeRobot's ACT and "
            "diffusion never read them; a policy whose model does fails at its first step. To keep them out "
            "of a policy's inputs, name its `input_features` in the training config (policies/presets/act.json).",
            privileged,
        )
        for key in privileged:
            features.pop(key)
    images = [k for k in features if k.startswith("observation.images.")]
    produced = {
        "observation.images.endoscope",
        WRIST_IMAGE,
        "observation.state",
        "observation.environment_state",
    }
    unknown = sorted(set(features) - produced)
    if unknown:
        raise ValueError(
            f"The policy reads {unknown}, which the suture env does not produce (it has {sorted(produced)}; "
            f"{WRIST_IMAGE} with wrist_camera=True)."
        )
    env_state = "observation.environment_state" in features
    size = int(np.prod(features["observation.environment_state"].shape)) if env_state else 0
    registered = state_parts(size) or ()  # None: the privileged state
    if images:
        sizes = {tuple(features[k].shape[-2:]) for k in images}
        height, width = sizes.pop()
        if height != width or sizes:
            raise ValueError(
                f"The suture env renders square images of one size; the policy reads {images} at "
                f"{sorted({tuple(features[k].shape[-2:]) for k in images})}."
            )
        kwargs = {
            "obs_type": "pixels_agent_pos_state" if env_state and not registered else "pixels_agent_pos",
            "image_size": int(height),
        }
        if WRIST_IMAGE in features:
            kwargs["wrist_camera"] = True
        for name in registered:
            kwargs[name] = True
        return kwargs
    if registered:
        raise ValueError(
            "The policy reads the wound's marks, the subtask or the planned regrasp without an image: the suture "
            "env gives them beside one."
        )
    return {"obs_type": "state"}


class GateMode(Enum):
    """What the O.O.D. gate of an ensemble does with its decision.

    ``REPORT``: the policy keeps control; scores and decisions are only logged (the paper's experiments,
    calibration, studies). ``ENFORCE``: the first O.O.D. decision releases control to the surgeon and
    the policy holds the pose (needs a calibration).
    """

    REPORT = "report"
    ENFORCE = "enforce"

    @classmethod
    def of(cls, enforce: bool) -> GateMode:
        return cls.ENFORCE if enforce else cls.REPORT


class PolicyRunner:
    """``act(observation) -> (10,) float32`` for one env, ``act_batch`` for several, with LeRobot's processing.

    The runner owns the gate's mode: it is applied to the policy before every call, so two runners
    sharing one policy (:meth:`with_gate`) each act in their own mode. A policy without a gate (any
    other LeRobot policy) ignores it.

    Episode noise: after ``reset(seeds=...)`` the diffusion noise of batch row i comes from its own
    generator, seeded with ``seeds[i]``, drawn when the policy's action queue is empty (it predicts a
    chunk at that call) and handed to ``select_action(batch, noise)``. An episode's noise then depends on
    its seed alone, not on which other episodes share its batch: the same seed gives the same episode at
    any ``batch_envs``, and the same draws as one env with torch's global RNG seeded with that seed (the
    robot path). Policies with a deterministic scheduler's noise only (DDIM) are covered; ACT samples
    nothing at inference.
    """

    def __init__(self, policy, preprocessor, postprocessor, gate: GateMode):
        if not isinstance(gate, GateMode):
            raise TypeError(f"`gate` must be a GateMode (REPORT or ENFORCE). Got {gate!r}.")
        self.policy = policy
        self.preprocessor = preprocessor
        self.postprocessor = postprocessor
        self.gate = gate
        self.source: tuple[str, str, dict] | None = None  # (directory, device, overrides) if loaded
        self._generators: list[torch.Generator] | None = None
        self._noise_shape: tuple[int, ...] | None = None
        self._apply_gate()

    @classmethod
    def from_pretrained(
        cls, policy_path: str | Path, gate: GateMode, device: str = "cpu", overrides: dict | None = None
    ) -> PolicyRunner:
        """Load a policy (:func:`load_policy`, with its config ``overrides``) to run with its gate in mode
        ``gate``.

        Raises:
            FileNotFoundError: ``gate`` is ENFORCE and the ensemble has no calibration (the message says how
                to make one).
        """
        runner = cls(*load_policy(policy_path, device, overrides), gate=gate)
        runner.source = (str(policy_path), device, dict(overrides or {}))
        if gate is GateMode.ENFORCE and getattr(runner.policy, "ood_calibration", False) is None:
            raise FileNotFoundError(
                f"The gate cannot be enforced: the policy at {policy_path} has no O.O.D. calibration. Run "
                f"`lerobot-suture calibrate --policy.path={policy_path}` first, or run the gate in report mode."
            )
        return runner

    def with_gate(self, gate: GateMode) -> PolicyRunner:
        """A runner of the same policy and processors (no copy) whose gate acts in mode ``gate``."""
        runner = PolicyRunner(self.policy, self.preprocessor, self.postprocessor, gate)
        runner.source = self.source
        return runner

    def _apply_gate(self) -> None:
        ood = getattr(self.policy.config, "ood", None)
        if ood is not None:
            ood.enforce = self.gate is GateMode.ENFORCE

    def reset(self, seeds: Sequence[int] | None = None) -> None:
        """Start new episodes; with ``seeds`` (one per batch row), each row's noise from its own seed."""
        self._apply_gate()
        self.policy.reset()
        for pipeline in (self.preprocessor, self.postprocessor):
            pipeline.reset()
        self._generators = None
        self._noise_shape = noise_shape(self.policy.config)  # read now: the config may change between runs
        if seeds is not None and self._noise_shape is not None:
            self._generators = [torch.Generator().manual_seed(int(seed)) for seed in seeds]

    def _episode_noise(self, batch_size: int) -> torch.Tensor | None:
        """(B, *noise_shape) noise, row i from episode i's generator; None without seeded episodes."""
        if self._generators is None or not _predicts_now(self.policy):
            return None
        if batch_size != len(self._generators):
            raise ValueError(
                f"The runner was reset with {len(self._generators)} episode seeds but got {batch_size} "
                "observations: call reset(seeds=...) with one seed per env of the batch."
            )
        noise = torch.stack([torch.randn(self._noise_shape, generator=g) for g in self._generators])
        return noise.to(next(self.policy.parameters()).device)

    def act(self, observation: dict, task: str = TASK) -> np.ndarray:
        """(10,) float32: the action for one env's observation (``task``: its instruction)."""
        return self.act_batch([observation], [task])[0]

    def preprocess(self, observations: list[dict], tasks: Sequence[str] | None = None) -> dict:
        """B envs' observations as the policy's normalized input batch (row i is env i).

        ``tasks``: each env's instruction (its ``task_description``, as ``lerobot-eval`` sends it); unset:
        the insertion task's.
        """
        from lerobot.envs.utils import preprocess_observation

        batch = preprocess_observation(_stack(observations))
        batch["task"] = [TASK] * len(observations) if tasks is None else list(tasks)
        return self.preprocessor(batch)

    def act_batch(self, observations: list[dict], tasks: Sequence[str] | None = None) -> np.ndarray:
        """(B, 10) float32: the actions for B envs' observations, in one policy call (row i is env i;
        ``tasks`` as in :meth:`preprocess`)."""
        batch = self.preprocess(observations, tasks)
        self._apply_gate()
        noise = self._episode_noise(len(observations))
        with torch.inference_mode():
            action = self.policy.select_action(batch, *(() if noise is None else (noise,)))
        action = self.postprocessor(action)
        return action.to("cpu").numpy().astype(np.float32)


def _predicts_now(policy) -> bool:
    """Whether ``policy`` predicts a new chunk at its next ``select_action``: its action queue is empty
    (LeRobot's queue semantics; a policy without that queue is asked at every call)."""
    queues = getattr(policy, "_queues", None)
    return not isinstance(queues, dict) or len(queues.get(ACTION, ())) == 0


def noise_shape(config) -> tuple[int, ...] | None:
    """The per-row shape of the initial diffusion noise ``select_action(batch, noise)`` takes, or None for
    a policy that takes none (ACT, and schedulers that draw noise at every step: DDPM).

    ``ensemble_diffusion``: (members, samples per member, horizon, action dim); LeRobot's ``diffusion``:
    (horizon, action dim).
    """
    if getattr(config, "noise_scheduler_type", None) != "DDIM":
        return None
    action_dim = config.action_feature.shape[0]
    if config.type == "ensemble_diffusion":
        return (config.n_members, config.uncertainty_samples_per_member, config.horizon, action_dim)
    if config.type == "diffusion":
        return (config.horizon, action_dim)
    return None


def reporting_runner(
    policy_path: str | Path,
    device: str = "cpu",
    needs: str | None = None,
    needed_for: str = "",
    overrides: dict | None = None,
) -> PolicyRunner:
    """A runner whose O.O.D. gate reports and never stops a rollout: calibration, experiments and studies
    read the gate's scores over whole episodes.

    Args:
        needs: an attribute the policy must have (a capability of ``ensemble_diffusion``), or None.
        needed_for: the error's end when it lacks it: "the <command> needs an ensemble_diffusion policy, ...".
        overrides: config overrides at load (:func:`load_policy`).
    """
    runner = PolicyRunner.from_pretrained(policy_path, GateMode.REPORT, device, overrides)
    if needs is not None and not hasattr(runner.policy, needs):
        raise ValueError(
            f"The policy at {policy_path} is a {runner.policy.config.type!r} policy; {needed_for}"
        )
    return runner


def _stack(observations: list[dict]) -> dict:
    """Env observations (nested dicts of arrays) stacked along a new leading batch axis."""
    first = observations[0]
    return {
        key: _stack([o[key] for o in observations])
        if isinstance(value, dict)
        else np.stack([np.asarray(o[key]) for o in observations])
        for key, value in first.items()
    }
