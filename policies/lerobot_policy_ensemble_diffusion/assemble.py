#!/usr/bin/env python

# Licensed under the Apache License, Version 2.0 (the "License");
# you may not use this file except in compliance with the License.
# You may obtain a copy of the License at
#
#     http://www.apache.org/licenses/LICENSE-2.0
#
# Unless required by applicable law or agreed to in writing, software
# distributed under the License is distributed on an "AS IS" BASIS,
# WITHOUT WARRANTIES OR CONDITIONS OF ANY KIND, either express or implied.
# See the License for the specific language governing permissions and
# limitations under the License.
"""Assemble separately trained `diffusion` policies into one `ensemble_diffusion` policy, and back.

The scale-out route of the paper's ensemble: train each member as its own job,

    lerobot-train --policy.type=diffusion --seed=<k> ... --output_dir=outputs/member_<k>

then `assemble_members([...member pretrained_model dirs...], output_dir)` writes a pretrained directory in
exactly the format `lerobot-train --policy.type=ensemble_diffusion` saves: config.json (type
"ensemble_diffusion"), model.safetensors (key `members.<n>.<member key>` for every member, plus the action
unnormalization buffers) and the members' processor files. `export_member` goes the other way.
"""

from __future__ import annotations

import json
import shutil
from dataclasses import dataclass, field, fields
from pathlib import Path

import torch
from huggingface_hub.constants import CONFIG_NAME, SAFETENSORS_SINGLE_FILE
from lerobot.configs import PreTrainedConfig
from lerobot.policies.diffusion.configuration_diffusion import DiffusionConfig
from lerobot.utils.constants import POLICY_POSTPROCESSOR_DEFAULT_NAME, POLICY_PREPROCESSOR_DEFAULT_NAME
from safetensors.torch import load_file, save_file

from lerobot_suture.lerobot_shim import save_config

from .compatibility import MEMBERS_PREFIX
from .configuration_ensemble_diffusion import EnsembleDiffusionConfig
from .modeling_ensemble_diffusion import EnsembleDiffusionPolicy

# Member settings that may differ between separately trained members: they do not change the trained
# network or how it is run (training schedule, hub and device bookkeeping). Everything else must match.
_FREE_FIELDS = frozenset(
    {
        "device",
        "use_amp",
        "use_peft",
        "push_to_hub",
        "repo_id",
        "private",
        "tags",
        "license",
        "pretrained_path",
        "pretrained_revision",
        "pretrained_backbone_weights",
        "drop_n_last_frames",
        "crop_is_random",
        "gradient_checkpointing",
        "do_mask_loss_for_padding",
        "compile_model",
        "compile_mode",
        "optimizer_lr",
        "optimizer_betas",
        "optimizer_eps",
        "optimizer_weight_decay",
        "scheduler_name",
        "scheduler_warmup_steps",
    }
)


def _processor_files(policy_dir: Path) -> list[Path]:
    return sorted(
        p
        for p in policy_dir.iterdir()
        if p.name.startswith((POLICY_PREPROCESSOR_DEFAULT_NAME, POLICY_POSTPROCESSOR_DEFAULT_NAME))
    )


def _normalizer_stats(policy_dir: Path) -> dict[str, torch.Tensor]:
    """The flat normalization statistics ({"action.min": tensor, ...}) of a policy's preprocessor."""
    pipeline_file = policy_dir / f"{POLICY_PREPROCESSOR_DEFAULT_NAME}.json"
    if not pipeline_file.is_file():
        raise FileNotFoundError(
            f"{policy_dir} has no {pipeline_file.name}: not a LeRobot pretrained policy directory."
        )
    steps = json.loads(pipeline_file.read_text())["steps"]
    for step in steps:
        if step.get("registry_name") == "normalizer_processor" and step.get("state_file"):
            return load_file(str(policy_dir / step["state_file"]))
    return {}


def _unflatten_stats(flat: dict[str, torch.Tensor], key: str) -> dict[str, torch.Tensor]:
    return {name.removeprefix(f"{key}."): v for name, v in flat.items() if name.startswith(f"{key}.")}


def _require_policy_dir(path: Path) -> None:
    if not path.is_dir():
        raise FileNotFoundError(f"Policy directory {path} does not exist.")
    for name in (CONFIG_NAME, SAFETENSORS_SINGLE_FILE):
        if not (path / name).is_file():
            raise FileNotFoundError(f"{path} has no {name}: not a LeRobot pretrained policy directory.")


def _prepare_output_dir(output_dir: Path, overwrite: bool) -> None:
    if output_dir.exists() and any(output_dir.iterdir()):
        if not overwrite:
            raise FileExistsError(
                f"Output directory {output_dir} exists and is not empty (pass overwrite=True)."
            )
        shutil.rmtree(output_dir)
    output_dir.mkdir(parents=True, exist_ok=True)


def assemble_members(
    member_dirs: list[str | Path], output_dir: str | Path, overwrite: bool = False, **ensemble_kwargs
) -> Path:
    """Assemble separately trained LeRobot `diffusion` policies into one saved `ensemble_diffusion` policy.

    Args:
        member_dirs: the members' pretrained directories (each with config.json of type "diffusion",
            model.safetensors and the processor files), at least two, in member order.
        output_dir: where to write the ensemble's pretrained directory.
        overwrite: replace a non-empty `output_dir`.
        **ensemble_kwargs: `EnsembleDiffusionConfig` fields beyond the member settings (e.g.
            `uncertainty_score="trace"`).
    Returns:
        `output_dir`, loadable with `EnsembleDiffusionPolicy.from_pretrained` and `lerobot-eval --policy.path`.
    Raises:
        FileNotFoundError / ValueError naming the member and what differs: not a policy directory, not a
        `diffusion` policy, member settings or features that differ, different normalization statistics
        (trained on different data), missing or misshapen tensors.
    """
    dirs = [Path(d) for d in member_dirs]
    if len(dirs) < 2:
        raise ValueError(f"An ensemble needs at least 2 members. Got {len(dirs)}: {[str(d) for d in dirs]}.")
    for d in dirs:
        _require_policy_dir(d)
    output_dir = Path(output_dir)

    configs = []
    for d in dirs:
        config = PreTrainedConfig.from_pretrained(d)
        if type(config) is not DiffusionConfig:
            raise ValueError(
                f"{d} holds a '{config.type}' policy; assembling needs plain 'diffusion' members."
            )
        configs.append(config)

    # Every setting that shapes the network or its inference must be equal.
    differences = []
    for f in fields(DiffusionConfig):
        if not f.init or f.name in _FREE_FIELDS:
            continue
        values = [getattr(c, f.name) for c in configs]
        if any(v != values[0] for v in values[1:]):
            per_member = ", ".join(
                f"{d.name if d.name != 'pretrained_model' else d.parent.parent.name}={v!r}"
                for d, v in zip(dirs, values, strict=True)
            )
            differences.append(f"`{f.name}` differs ({per_member})")
    if differences:
        raise ValueError(
            "The members do not share one architecture/feature set: " + "; ".join(differences) + "."
        )

    # Members must share the normalization (one dataset): the ensemble has one pre/post-processor.
    stats = [_normalizer_stats(d) for d in dirs]
    feature_keys = [*configs[0].input_features, *configs[0].output_features]
    for d, s in zip(dirs[1:], stats[1:], strict=True):
        for key in feature_keys:
            a, b = _unflatten_stats(stats[0], key), _unflatten_stats(s, key)
            if a.keys() != b.keys() or any(not torch.equal(a[k], b[k]) for k in a):
                raise ValueError(
                    f"{d} normalizes '{key}' with different statistics than {dirs[0]}: members must be trained on "
                    "the same dataset (same normalization)."
                )

    ensemble_kwargs.setdefault("n_members", len(dirs))
    if ensemble_kwargs["n_members"] != len(dirs):
        raise ValueError(
            f"`n_members`={ensemble_kwargs['n_members']} but {len(dirs)} member directories were given."
        )
    # The backbone's initial weights never matter here (the trained weights are loaded) and must not download.
    ensemble_config = EnsembleDiffusionConfig.from_member_config(
        configs[0], pretrained_backbone_weights=None, pretrained_path=None, **ensemble_kwargs
    )
    action_stats = (
        {"action": _unflatten_stats(stats[0], "action")} if _unflatten_stats(stats[0], "action") else None
    )
    policy = EnsembleDiffusionPolicy(ensemble_config, dataset_stats=action_stats)

    state = {k: v for k, v in policy.state_dict().items() if not k.startswith(f"{MEMBERS_PREFIX}.")}
    for n, (d, member) in enumerate(zip(dirs, policy.members, strict=True)):
        member_state = load_file(str(d / SAFETENSORS_SINGLE_FILE))
        expected = member.state_dict()
        missing = sorted(set(expected) - set(member_state))
        unexpected = sorted(set(member_state) - set(expected))
        mismatched = [
            f"{k}: {tuple(member_state[k].shape)} vs {tuple(v.shape)}"
            for k, v in expected.items()
            if k in member_state and member_state[k].shape != v.shape
        ]
        if missing or unexpected or mismatched:
            raise ValueError(
                f"{d / SAFETENSORS_SINGLE_FILE} does not match its config.json: missing {missing[:5]}, "
                f"unexpected {unexpected[:5]}, mismatched shapes {mismatched[:5]}."
            )
        state.update({f"{MEMBERS_PREFIX}.{n}.{k}": v for k, v in member_state.items()})
    policy.load_state_dict(state, strict=True)

    _prepare_output_dir(output_dir, overwrite)
    policy.save_pretrained(output_dir)
    for p in _processor_files(dirs[0]):
        shutil.copy2(p, output_dir / p.name)
    return output_dir


def export_member(
    ensemble_dir: str | Path, index: int, output_dir: str | Path, overwrite: bool = False
) -> Path:
    """Write member `index` of a saved ensemble as a plain LeRobot `diffusion` policy directory.

    Args:
        ensemble_dir: a pretrained `ensemble_diffusion` directory.
        index: the member, in [0, n_members).
        output_dir: where to write the member (config.json of type "diffusion", model.safetensors,
            the ensemble's processor files).
        overwrite: replace a non-empty `output_dir`.
    Returns:
        `output_dir`.
    """
    ensemble_dir = Path(ensemble_dir)
    _require_policy_dir(ensemble_dir)
    config = PreTrainedConfig.from_pretrained(ensemble_dir)
    if not isinstance(config, EnsembleDiffusionConfig):
        raise ValueError(f"{ensemble_dir} holds a '{config.type}' policy, not 'ensemble_diffusion'.")
    if not 0 <= index < config.n_members:
        raise ValueError(f"`index` must be in [0, {config.n_members}). Got {index}.")
    prefix = f"{MEMBERS_PREFIX}.{index}."
    state = load_file(str(ensemble_dir / SAFETENSORS_SINGLE_FILE))
    member_state = {k.removeprefix(prefix): v.contiguous() for k, v in state.items() if k.startswith(prefix)}
    if not member_state:
        raise ValueError(f"{ensemble_dir / SAFETENSORS_SINGLE_FILE} holds no tensors of member {index}.")

    output_dir = Path(output_dir)
    _prepare_output_dir(output_dir, overwrite)
    save_config(config.member_config(), output_dir)
    save_file(member_state, str(output_dir / SAFETENSORS_SINGLE_FILE), metadata={"format": "pt"})
    for p in _processor_files(ensemble_dir):
        shutil.copy2(p, output_dir / p.name)
    return output_dir


@dataclass
class AssembleConfig:
    """``lerobot-suture assemble`` flags.

    Args:
        members: the members' pretrained directories, e.g. ``--members='[outputs/m0/.../pretrained_model,...]'``.
        output_dir: where the ensemble's pretrained directory is written.
        overwrite: replace a non-empty ``output_dir``.
    """

    members: list[str] = field(default_factory=list)
    output_dir: str | None = None
    overwrite: bool = False

    def __post_init__(self):
        if self.output_dir is None:
            raise ValueError("`--output_dir` is required: where the assembled ensemble is written.")


def main(argv: list[str] | None = None) -> None:
    import draccus

    cfg = draccus.parse(config_class=AssembleConfig, args=argv, exit_on_error=False)
    path = assemble_members(cfg.members, cfg.output_dir, overwrite=cfg.overwrite)
    print(f"Assembled {len(cfg.members)} members into {path}")
