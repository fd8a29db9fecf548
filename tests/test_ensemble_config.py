"""EnsembleDiffusionConfig: registration, reuse of DiffusionConfig, validation, presets."""

import json
from dataclasses import fields
from pathlib import Path

import draccus
import pytest
import torch
from lerobot.configs import PreTrainedConfig
from lerobot.optim import OptimizerConfig
from lerobot.policies.diffusion.configuration_diffusion import DiffusionConfig
from lerobot.policies.factory import get_policy_class, make_policy_config
from lerobot_policy_ensemble_diffusion import EnsembleDiffusionConfig, EnsembleOODConfig
from policy_builders import tiny_config

PRESETS = Path(__file__).resolve().parents[1] / "policies" / "presets"


def test_registered_and_discoverable():
    assert PreTrainedConfig.get_choice_class("ensemble_diffusion") is EnsembleDiffusionConfig
    config = make_policy_config("ensemble_diffusion", device="cpu")
    assert config.type == "ensemble_diffusion"
    assert get_policy_class("ensemble_diffusion").__name__ == "EnsembleDiffusionPolicy"


def test_defaults_are_the_paper_and_offline():
    config = EnsembleDiffusionConfig(device="cpu")
    assert config.n_members == 5
    assert (config.n_obs_steps, config.horizon, config.n_action_steps) == (4, 8, 4)
    assert config.noise_scheduler_type == "DDPM" and config.num_train_timesteps == 100
    assert config.optimizer_lr == 1e-4 and config.optimizer_weight_decay == 0.1
    assert config.scheduler_warmup_steps == 100
    assert config.pretrained_backbone_weights is None
    assert config.uncertainty_score == "max_abs_cov" and config.uncertainty_space == "normalized"
    assert config.ood.enforce is False
    optimizer = config.get_optimizer_preset()
    assert optimizer.type == "adamw_fused" and optimizer.weight_decay == 0.1


@pytest.mark.parametrize("name", ["adamw", "adam"])
def test_fused_optimizer_preset_matches_pytorch_default(name):
    """The preset's fused kernel takes the same steps as PyTorch's default Adam(W), and resumes by name."""
    config = EnsembleDiffusionConfig(device="cpu", optimizer_name=name, optimizer_lr=1e-2)
    preset = config.get_optimizer_preset()
    assert preset.type == f"{name}_fused"
    assert OptimizerConfig.get_choice_class(preset.type) is type(preset)  # what a resume looks up

    torch.manual_seed(0)
    start = [torch.randn(7, 5), torch.randn(3)]
    grads = [[torch.randn_like(p) for p in start] for _ in range(4)]
    default_cls = torch.optim.AdamW if name == "adamw" else torch.optim.Adam
    kwargs = {"lr": preset.lr, "betas": preset.betas, "eps": preset.eps, "weight_decay": preset.weight_decay}

    def run(build) -> tuple[list[torch.Tensor], torch.optim.Optimizer]:
        params = [p.clone().requires_grad_() for p in start]
        optimizer = build(params)
        for step_grads in grads:
            for p, g in zip(params, step_grads, strict=True):
                p.grad = g.clone()
            optimizer.step()
        return params, optimizer

    fused, fused_optimizer = run(preset.build)
    default, _ = run(lambda params: default_cls(params, foreach=False, **kwargs))
    assert fused_optimizer.defaults["fused"] is True
    for p_fused, p_default, p_start in zip(fused, default, start, strict=True):
        torch.testing.assert_close(p_fused, p_default, rtol=1e-5, atol=1e-6)
        assert not torch.allclose(p_fused, p_start)  # the steps did move the parameters


def test_every_diffusion_field_is_reused():
    diffusion = {f.name for f in fields(DiffusionConfig)}
    ensemble = {f.name for f in fields(EnsembleDiffusionConfig)}
    assert diffusion <= ensemble
    config = tiny_config(kernel_size=3, use_film_scale_modulation=False)
    member = config.member_config()
    assert type(member) is DiffusionConfig
    for name in diffusion:
        assert getattr(member, name) == getattr(config, name), name
    back = EnsembleDiffusionConfig.from_member_config(member, n_members=3)
    assert back.n_members == 3 and back.kernel_size == 3


@pytest.mark.parametrize(
    ("kwargs", "message"),
    [
        ({"n_members": 0}, "`n_members` must be >= 1. Got 0."),
        ({"n_members": 1}, r"A single member .* needs `uncertainty_samples_per_member` >= 2"),
        (
            {"n_members": 1, "uncertainty_samples_per_member": 4, "uncertainty_source": "epistemic"},
            "has no members to disagree",
        ),
        ({"member_seeds": [1, 2, 3]}, r"`member_seeds` must hold one seed per member \(2\). Got 3"),
        ({"member_seeds": [4, 4]}, "`member_seeds` must be distinct"),
        (
            {"uncertainty_score": "max"},
            r"`uncertainty_score` must be one of \['max_abs_cov', 'trace', 'logdet'\]",
        ),
        ({"uncertainty_space": "raw"}, "`uncertainty_space` must be one of"),
        ({"uncertainty_source": "both"}, "`uncertainty_source` must be one of"),
        ({"uncertainty_steps": "all"}, "`uncertainty_steps` must be one of"),
        ({"optimizer_name": "sgd"}, "`optimizer_name` must be one of"),
        ({"uncertainty_source": "aleatoric"}, "needs `uncertainty_samples_per_member` >= 2"),
        ({"uncertainty_samples_per_member": 0}, "`uncertainty_samples_per_member` must be >= 1. Got 0."),
        ({"covariance_correction": 2}, "`covariance_correction` must be 0 or 1"),
        ({"logdet_eps": 0.0}, "`logdet_eps` must be > 0"),
        ({"n_action_steps": 8}, r"`n_action_steps` must be <= `horizon - n_obs_steps \+ 1` \(7\). Got 8."),
        ({"num_inference_steps": 20}, r"`num_inference_steps` must be in \[1, 10\]"),
        ({"needle_keypoints_weight": -1.0}, "`needle_keypoints_weight` must be >= 0"),
        ({"vision_backbone_stages": 5}, "`vision_backbone_stages` must be 1, 2, 3 or 4. Got 5."),
        ({"prior_scale": -0.5}, r"`prior_scale` must be finite and >= 0 \(0: no prior\). Got -0.5."),
        ({"prior_scale": float("nan")}, "`prior_scale` must be finite and >= 0"),
        # DiffusionConfig's own check still runs.
        ({"down_dims": (8, 16, 32, 64)}, "horizon should be an integer multiple"),
    ],
)
def test_validation_names_the_field(kwargs, message):
    with pytest.raises(ValueError, match=message):
        tiny_config(**kwargs)


def test_ood_options():
    assert tiny_config(ood={"enforce": False, "calibration_file": "c.json"}).ood.calibration_file == "c.json"
    with pytest.raises(ValueError, match="`ood.calibration_file` must be a plain file name"):
        EnsembleOODConfig(calibration_file="../c.json")


def test_json_round_trip(tmp_path):
    config = tiny_config(member_seeds=[3, 7], bootstrap=True, uncertainty_score="trace")
    config._save_pretrained(tmp_path)
    assert json.loads((tmp_path / "config.json").read_text())["type"] == "ensemble_diffusion"
    loaded = PreTrainedConfig.from_pretrained(tmp_path)
    assert isinstance(loaded, EnsembleDiffusionConfig)
    assert loaded == config


@pytest.mark.parametrize("preset", ["paper", "cpu"])
def test_presets_parse_and_never_download(preset):
    data = json.loads((PRESETS / f"{preset}.json").read_text())
    assert data["policy"]["type"] == "ensemble_diffusion"
    assert data["policy"]["pretrained_backbone_weights"] is None
    policy = {k: v for k, v in data["policy"].items() if k != "type"}
    with draccus.config_type("json"):
        config = draccus.decode(EnsembleDiffusionConfig, policy)
    assert config.pretrained_backbone_weights is None
    assert config.horizon % 2 ** len(config.down_dims) == 0
    if preset == "paper":
        assert (config.n_obs_steps, config.horizon, config.n_action_steps) == (4, 8, 4)
        assert config.noise_scheduler_type == "DDPM"
        assert config.num_train_timesteps == config.num_inference_steps == 100
        assert config.optimizer_lr == 1e-4 and config.optimizer_weight_decay == 0.1
        assert config.scheduler_warmup_steps == 100
        assert data["batch_size"] == 8
    else:
        assert config.noise_scheduler_type == "DDIM" and config.num_inference_steps <= 20
        assert max(config.crop_shape or config.resize_shape) < 96
        assert max(config.down_dims) < max(DiffusionConfig().down_dims)
