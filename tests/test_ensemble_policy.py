"""EnsembleDiffusionPolicy in Python: training loss, batched members, statistics, queues, save/load, errors."""

import copy

import numpy as np
import pytest
import torch
from lerobot.utils.constants import ACTION, OBS_IMAGES, OBS_STATE
from lerobot_policy_ensemble_diffusion import EnsembleDiffusionPolicy
from lerobot_policy_ensemble_diffusion.batched_members import FusedDiffusionEnsemble
from lerobot_policy_ensemble_diffusion.needle_keypoints import predict_needle_keypoints
from lerobot_policy_ensemble_diffusion.normalization import action_affine_from_stats
from policy_builders import (
    SUTURE_DATASET_FEATURES,
    fake_dataset_stats,
    random_observation,
    tiny_config,
)
from safetensors.torch import load_file, save_file


@pytest.fixture(autouse=True)
def _one_thread():
    threads = torch.get_num_threads()
    torch.set_num_threads(1)
    yield
    torch.set_num_threads(threads)


def _policy(**overrides) -> EnsembleDiffusionPolicy:
    torch.manual_seed(0)
    return EnsembleDiffusionPolicy(tiny_config(**overrides), dataset_stats=fake_dataset_stats())


@pytest.fixture(scope="module")
def shared_policy():
    torch.manual_seed(0)
    return EnsembleDiffusionPolicy(
        tiny_config(n_members=3, noise_scheduler_type="DDIM"), dataset_stats=fake_dataset_stats()
    ).eval()


@pytest.fixture
def policy(shared_policy):
    """The module's policy, built once, with empty queues: `select_action` fills the observation queues and
    `predict_action_distribution` reads them once filled, so a test must not see an earlier test's."""
    shared_policy.reset()
    shared_policy.config.batched_inference = True
    return shared_policy


def _train_batch(config, batch_size=4, seed=0):
    batch = random_observation(config, batch_size=batch_size, seed=seed)
    g = torch.Generator().manual_seed(seed + 1)
    batch[ACTION] = torch.randn(batch_size, config.horizon, config.action_feature.shape[0], generator=g)
    batch["action_is_pad"] = torch.zeros(batch_size, config.horizon, dtype=torch.bool)
    return batch


def _assert_fused_equals_loop(policy, obs, noise, samples_per_member):
    """The fused inference's samples equal the members' own loop's; returns the fused prediction."""
    policy.config.batched_inference = True
    fused = policy.predict_action_distribution(obs, samples_per_member=samples_per_member, noise=noise)
    policy.config.batched_inference = False
    loop = policy.predict_action_distribution(obs, samples_per_member=samples_per_member, noise=noise)
    policy.config.batched_inference = True
    torch.testing.assert_close(fused.normalized.samples, loop.normalized.samples, rtol=1e-4, atol=1e-4)
    return fused


def _clone(batch):
    return {k: v.clone() for k, v in batch.items()}


def _assert_batch_equal(a, b):
    assert a.keys() == b.keys()
    for k in a:
        torch.testing.assert_close(a[k], b[k], rtol=0, atol=0, equal_nan=True)


def test_members_are_lerobot_diffusion_policies_with_independent_weights(policy):
    from lerobot.policies.diffusion.modeling_diffusion import DiffusionPolicy

    assert len(policy.members) == 3
    assert all(type(m) is DiffusionPolicy for m in policy.members)
    w = [m.diffusion.unet.final_conv[1].weight for m in policy.members]
    assert not torch.equal(w[0], w[1]) and not torch.equal(w[1], w[2])


def test_member_seeds_make_initialisation_reproducible():
    a = EnsembleDiffusionPolicy(tiny_config(member_seeds=[11, 12]))
    torch.randn(10)  # the global RNG state must not matter
    b = EnsembleDiffusionPolicy(tiny_config(member_seeds=[11, 12]))
    c = EnsembleDiffusionPolicy(tiny_config(member_seeds=[12, 11]))
    _assert_batch_equal(a.state_dict(), b.state_dict())
    torch.testing.assert_close(a.members[0].state_dict(), c.members[1].state_dict(), rtol=0, atol=0)


def test_forward_loss_is_mean_of_member_losses_and_does_not_mutate_batch():
    policy = _policy().train()
    batch = _train_batch(policy.config)
    original = _clone(batch)
    torch.manual_seed(5)
    loss, output = policy.forward(batch)
    _assert_batch_equal(batch, original)
    assert set(output) == {"loss_member_0", "loss_member_1"}
    assert all(isinstance(v, float) for v in output.values())
    torch.testing.assert_close(loss.item(), sum(output.values()) / 2, rtol=1e-6, atol=0)
    # The same RNG draws reproduce each member's own LeRobot loss.
    torch.manual_seed(5)
    member_losses = [m.forward(batch)[0].item() for m in policy.members]
    assert member_losses == [output["loss_member_0"], output["loss_member_1"]]
    loss.backward()
    assert all(p.grad is not None for p in policy.get_optim_params())


def test_bootstrap_resamples_each_member_batch():
    policy = _policy(bootstrap=True).train()
    batch = _train_batch(policy.config, batch_size=8)
    seen = []
    for member in policy.members:
        original_forward = member.forward

        def spy(member_batch, _forward=original_forward):
            seen.append(member_batch[ACTION])
            return _forward(member_batch)

        member.forward = spy
    policy.forward(batch)
    assert len(seen) == 2 and not torch.equal(seen[0], seen[1])
    for actions in seen:  # every row is one of the batch's rows
        assert all(any(torch.equal(row, ref) for ref in batch[ACTION]) for row in actions)
    seen.clear()
    policy.eval()
    policy.forward(batch)  # no bootstrap outside training
    assert all(torch.equal(s, batch[ACTION]) for s in seen)


def test_batched_members_equal_member_loop(policy):
    obs = random_observation(policy.config, batch_size=2)
    noise = torch.randn(2, 3, 2, policy.config.horizon, 10)  # (B, N, K, T, A)
    _assert_fused_equals_loop(policy, obs, noise, samples_per_member=2)
    # Both conv modes of the fused U-Net agree with the members' own U-Nets.
    batch = dict(obs)
    batch[OBS_IMAGES] = torch.stack([obs[k] for k in policy.config.image_features], dim=-4)
    models = [m.diffusion for m in policy.members]
    x = torch.randn(2, 3, policy.config.horizon, 10)
    t = torch.full((2,), 3, dtype=torch.long)
    with torch.no_grad():
        cond = torch.stack([m._prepare_global_conditioning(batch) for m in models], dim=1)  # (B, N, G)
        expected = torch.stack(
            [m.unet(x[:, n], t, global_cond=cond[:, n]) for n, m in enumerate(models)], dim=1
        )
        for mode in ("gemm", "grouped"):
            fused_net = FusedDiffusionEnsemble(models, conv_mode=mode)
            torch.testing.assert_close(fused_net.encode(batch), cond, rtol=1e-4, atol=1e-5)
            torch.testing.assert_close(fused_net.unet(x, t, cond), expected, rtol=1e-4, atol=1e-5)


def test_inference_stays_full_precision_under_autocast(policy):
    """lerobot-eval autocasts when `use_amp` is set; the ensemble still samples and scores in fp32."""
    obs = random_observation(policy.config, batch_size=2)
    noise = torch.randn(2, 3, 1, policy.config.horizon, 10)
    plain = policy.predict_action_distribution(obs, noise=noise)
    with torch.autocast("cpu", dtype=torch.bfloat16):
        autocast = policy.predict_action_distribution(obs, noise=noise)
    assert autocast.normalized.samples.dtype == torch.float32
    torch.testing.assert_close(autocast.normalized.samples, plain.normalized.samples, rtol=0, atol=0)
    torch.testing.assert_close(autocast.score, plain.score, rtol=0, atol=0)


@pytest.mark.parametrize("mode", ["gemm", "grouped"])
@pytest.mark.parametrize(("kernel", "stride", "padding"), [(5, 1, 2), (3, 2, 1), (1, 1, 0)])
def test_fused_conv_equals_member_convs(mode, kernel, stride, padding):
    from lerobot_policy_ensemble_diffusion.fused_unet import FusedConv1d

    convs = [torch.nn.Conv1d(4, 6, kernel, stride, padding) for _ in range(3)]
    fused = FusedConv1d(convs, mode)
    for length in (1, 2, 3, 8):  # short inputs: the taps that only see padding are skipped
        x = torch.randn(2, 3 * 4, length)  # (B, N*C_in, T)
        with torch.no_grad():
            expected = torch.cat([c(x[:, 4 * n : 4 * (n + 1)]) for n, c in enumerate(convs)], dim=1)
            torch.testing.assert_close(fused(x), expected, rtol=1e-5, atol=1e-5)


@pytest.mark.parametrize("mode", ["gemm", "grouped"])
def test_fused_transposed_conv_equals_member_convs(mode):
    """The U-Net's upsampling (kernel 4, stride 2); on short inputs "gemm" mode runs its dense matrix."""
    from lerobot_policy_ensemble_diffusion.fused_unet import FusedConv1d

    convs = [torch.nn.ConvTranspose1d(4, 6, 4, 2, 1) for _ in range(3)]
    fused = FusedConv1d(convs, mode)
    for length in (1, 2, 3, 8):
        x = torch.randn(2, 3 * 4, length)
        with torch.no_grad():
            expected = torch.cat([c(x[:, 4 * n : 4 * (n + 1)]) for n, c in enumerate(convs)], dim=1)
            torch.testing.assert_close(fused(x), expected, rtol=1e-5, atol=1e-5)


@pytest.mark.parametrize(("size", "stride"), [(4, 2), (3, 1), (5, 2), (6, 2), (4, 1)])  # 2x2, 3x3 x3, 4x4
def test_small_map_gemm_equals_conv2d(size, stride):
    """ResNet's last stage at 64/72 px: 2x2/3x3 maps run as im2col + GEMM, larger maps as the conv."""
    from lerobot_policy_ensemble_diffusion.batched_members import SharedPreprocessEncoders, SmallMapConv2d

    torch.manual_seed(0)
    conv = torch.nn.Conv2d(8, 16, 3, stride, 1, bias=False)
    gemm = SmallMapConv2d(conv, SharedPreprocessEncoders.SMALL_MAP_POSITIONS)
    x = torch.randn(2, 8, size, size)
    with torch.no_grad():
        torch.testing.assert_close(gemm(x), conv(x), rtol=1e-5, atol=1e-5)


def test_prediction_shapes_and_statistics(policy):
    obs = random_observation(policy.config, batch_size=2)
    pred = policy.predict_action_distribution(obs, samples_per_member=3)
    n, t, a = 3, policy.config.horizon, 10
    stats = pred.normalized
    assert stats.samples.shape == (2, n, 3, t, a)
    assert stats.member_mean.shape == (2, n, t, a)
    assert stats.mean.shape == (2, t, a)
    assert stats.covariance.shape == stats.epistemic.shape == stats.aleatoric.shape == (2, t, a, a)
    torch.testing.assert_close(stats.covariance, stats.aleatoric + stats.epistemic)
    assert pred.score.shape == (2,)
    torch.testing.assert_close(pred.score, stats.covariance.abs().amax(dim=(-3, -2, -1)))
    assert policy.last_prediction is pred and torch.equal(policy.uncertainty, pred.score)
    assert pred.action_steps == slice(1, 5)
    # Unnormalized statistics: x = x_norm * scale + offset, the inverse of the MIN_MAX normalization.
    scale, offset = action_affine_from_stats(fake_dataset_stats(), policy._action_norm_mode())
    torch.testing.assert_close(pred.unnormalized.mean, stats.mean * scale + offset)
    torch.testing.assert_close(
        pred.unnormalized.covariance, stats.covariance * scale[:, None] * scale[None, :]
    )
    k1 = policy.predict_action_distribution(obs)
    assert k1.normalized.aleatoric is None and k1.normalized.samples.shape[2] == 1


def test_one_member_trains_and_reads_its_own_spread():
    """The ensemble's member recipe as a single policy: one member, K samples, the same loss and target."""
    policy = _policy(n_members=1, uncertainty_samples_per_member=4)
    loss, _ = policy.forward(_train_batch(policy.config))
    loss.backward()
    assert torch.isfinite(loss)
    pred = policy.eval().predict_action_distribution(random_observation(policy.config, batch_size=2))
    stats = pred.normalized
    assert stats.samples.shape[1:3] == (1, 4)
    assert not stats.epistemic.any() and (pred.score > 0).all()
    torch.testing.assert_close(stats.covariance, stats.aleatoric)


def test_unnormalized_matches_lerobot_postprocessor(policy):
    from lerobot.policies.factory import make_pre_post_processors

    _, postprocessor = make_pre_post_processors(policy.config, dataset_stats=fake_dataset_stats())
    obs = random_observation(policy.config, batch_size=1)
    pred = policy.predict_action_distribution(obs)
    chunk = pred.normalized.mean[:, pred.action_steps]  # (1, 4, A)
    expected = torch.stack([postprocessor(chunk[:, i]) for i in range(chunk.shape[1])], dim=1)
    torch.testing.assert_close(pred.unnormalized.mean[:, pred.action_steps], expected)


def test_score_options():
    policy = _policy(
        uncertainty_score="trace", uncertainty_space="unnormalized", uncertainty_steps="action"
    ).eval()
    pred = policy.predict_action_distribution(random_observation(policy.config))
    cov = pred.unnormalized.covariance[:, pred.action_steps]
    torch.testing.assert_close(pred.score, cov.diagonal(dim1=-2, dim2=-1).sum(-1).amax(-1))
    policy = _policy(uncertainty_source="aleatoric", uncertainty_samples_per_member=2).eval()
    pred = policy.predict_action_distribution(random_observation(policy.config))
    torch.testing.assert_close(pred.score, pred.normalized.aleatoric.abs().amax(dim=(-3, -2, -1)))


def test_rescore_equals_the_policy_configured_for_that_choice(policy):
    obs = random_observation(policy.config, batch_size=2)
    noise = torch.randn(2, 3, 2, policy.config.horizon, 10)  # (B, N, K, T, A)
    pred = policy.predict_action_distribution(obs, samples_per_member=2, noise=noise)
    torch.testing.assert_close(policy.rescore(pred), pred.score, rtol=0, atol=0)
    choices = [
        {"uncertainty_score": "trace", "uncertainty_steps": "action"},
        {"uncertainty_score": "logdet", "uncertainty_space": "unnormalized"},
        {"uncertainty_source": "aleatoric"},
        {"uncertainty_source": "epistemic", "uncertainty_steps": "action"},
    ]
    for choice in choices:
        configured = copy.deepcopy(policy)
        for name, value in choice.items():
            setattr(configured.config, name, value)
        expected = configured.predict_action_distribution(obs, samples_per_member=2, noise=noise).score
        torch.testing.assert_close(policy.rescore(pred, **choice), expected, rtol=1e-6, atol=0)
    with pytest.raises(ValueError, match="`uncertainty_steps` must be one of"):
        policy.rescore(pred, uncertainty_steps="executed")
    with pytest.raises(ValueError, match="Unknown score settings \\['uncertainty_scale'\\]"):
        policy.rescore(pred, uncertainty_scale="max")
    k1 = policy.predict_action_distribution(obs, samples_per_member=1)
    with pytest.raises(ValueError, match="aleatoric.*two samples"):
        policy.rescore(k1, uncertainty_source="aleatoric")


def test_select_action_queue_semantics_and_no_mutation(policy):
    policy.reset()
    chunks = []
    original_predict = policy.predict_action_chunk

    def spy(batch, noise=None):
        chunk = original_predict(batch, noise=noise)
        chunks.append(chunk)
        return chunk

    policy.predict_action_chunk = spy
    try:
        actions = []
        for step in range(9):
            obs = random_observation(policy.config, batch_size=2, n_steps=0, seed=step)
            original = _clone(obs)
            actions.append(policy.select_action(obs))
            _assert_batch_equal(obs, original)
    finally:
        del policy.predict_action_chunk
    assert len(chunks) == 3  # a new chunk every n_action_steps = 4 steps
    assert all(a.shape == (2, 10) for a in actions)
    torch.testing.assert_close(torch.stack(actions[:4], dim=1), chunks[0], rtol=0, atol=0)
    torch.testing.assert_close(torch.stack(actions[4:8], dim=1), chunks[1], rtol=0, atol=0)
    # The executed chunk is the ensemble mean of the last prediction's executed steps.
    last = policy.last_prediction
    torch.testing.assert_close(chunks[-1], last.normalized.mean[:, last.action_steps], rtol=0, atol=0)


def test_fused_copy_follows_weight_updates():
    policy = _policy(noise_scheduler_type="DDIM").eval()
    obs = random_observation(policy.config)
    noise = torch.randn(1, 2, 1, policy.config.horizon, 10)
    before = policy.predict_action_distribution(obs, noise=noise).normalized.samples
    with torch.no_grad():
        policy.members[1].diffusion.unet.final_conv[1].bias.add_(1.0)  # in place, as an optimizer step
    after = policy.predict_action_distribution(obs, noise=noise).normalized.samples
    policy.config.batched_inference = False
    reference = policy.predict_action_distribution(obs, noise=noise).normalized.samples
    assert not torch.allclose(before, after)
    torch.testing.assert_close(after, reference, rtol=1e-4, atol=1e-4)


@pytest.mark.parametrize(("stages", "side"), [(4, 1), (3, 2), (2, 4)])
def test_cut_backbone_gives_a_finer_map_and_runs_batched(tmp_path, stages, side):
    """Fewer ResNet stages: a finer spatial-softmax map (1/32, 1/16, 1/8 of the 32 px image); the fused
    inference still equals the members' own, and a checkpoint rebuilds the cut encoder."""
    policy = _policy(vision_backbone_stages=stages, noise_scheduler_type="DDIM").eval()
    encoder = policy.members[0].diffusion.rgb_encoder
    encoder = encoder[0] if isinstance(encoder, torch.nn.ModuleList) else encoder  # one per camera
    with torch.no_grad():
        feature_map = encoder.backbone(torch.zeros(1, 3, 32, 32))
    assert feature_map.shape[-2:] == (side, side)
    assert (encoder.pool._in_h, encoder.pool._in_w) == (side, side)
    obs = random_observation(policy.config, batch_size=2)
    noise = torch.randn(2, 2, 1, policy.config.horizon, 10)
    _assert_fused_equals_loop(policy, obs, noise, samples_per_member=1)
    policy.save_pretrained(tmp_path)
    loaded = EnsembleDiffusionPolicy.from_pretrained(tmp_path)
    assert loaded.config.vision_backbone_stages == stages
    _assert_batch_equal(policy.state_dict(), loaded.state_dict())


def test_save_load_round_trip_identical_outputs(tmp_path):
    policy = _policy().eval()
    policy.save_pretrained(tmp_path)
    state = load_file(str(tmp_path / "model.safetensors"))
    assert {k.split(".")[1] for k in state if k.startswith("members.")} == {"0", "1"}
    loaded = EnsembleDiffusionPolicy.from_pretrained(tmp_path)
    assert loaded.config == policy.config
    _assert_batch_equal(policy.state_dict(), loaded.state_dict())
    obs = random_observation(policy.config, batch_size=2)
    outputs = []
    for p in (policy, loaded):
        torch.manual_seed(42)
        pred = p.predict_action_distribution(obs, samples_per_member=2)
        p.reset()
        torch.manual_seed(43)
        action = p.select_action(random_observation(policy.config, batch_size=2, n_steps=0))
        outputs.append((pred, action))
    (a, action_a), (b, action_b) = outputs
    for name in ("samples", "mean", "covariance", "epistemic", "aleatoric"):
        torch.testing.assert_close(getattr(a.normalized, name), getattr(b.normalized, name), rtol=0, atol=0)
    torch.testing.assert_close(a.score, b.score, rtol=0, atol=0)
    torch.testing.assert_close(action_a, action_b, rtol=0, atol=0)


def test_loading_checks_the_checkpoint(tmp_path):
    policy = _policy()
    policy.save_pretrained(tmp_path)
    state = load_file(str(tmp_path / "model.safetensors"))

    three = copy.deepcopy(policy.config)
    three.n_members = 3
    with pytest.raises(
        ValueError, match=r"holds members \[0, 1\] but the config has n_members=3 \(missing member"
    ):
        EnsembleDiffusionPolicy.from_pretrained(tmp_path, config=three)

    save_file(
        {k: v for k, v in state.items() if not k.startswith("members.1.")},
        str(tmp_path / "model.safetensors"),
    )
    with pytest.raises(ValueError, match=r"missing member\(s\) \[1\]"):
        EnsembleDiffusionPolicy.from_pretrained(tmp_path)

    bigger = copy.deepcopy(policy.config)
    bigger.down_dims = (16, 64)
    save_file(state, str(tmp_path / "model.safetensors"))
    with pytest.raises(ValueError, match="mismatched shapes"):
        EnsembleDiffusionPolicy.from_pretrained(tmp_path, config=bigger)


def test_feature_mismatch_is_named():
    from types import SimpleNamespace

    features = dict(SUTURE_DATASET_FEATURES)
    features["observation.state"] = {"dtype": "float32", "shape": (7,), "names": None}
    meta = SimpleNamespace(features=features, repo_id="local/other")
    with pytest.raises(
        ValueError, match=r"dataset local/other.*'observation.state' has shape \(7,\) there but \(10,\)"
    ):
        EnsembleDiffusionPolicy(tiny_config(), dataset_meta=meta)
    del features["observation.images.endoscope"]
    with pytest.raises(ValueError, match="'observation.images.endoscope' .* is missing"):
        EnsembleDiffusionPolicy(tiny_config(), dataset_meta=meta)


def test_observation_mismatch_is_named(policy):
    policy.reset()  # offline use: empty queues
    obs = random_observation(policy.config, batch_size=1)
    obs[OBS_STATE] = obs[OBS_STATE][..., :7]
    with pytest.raises(
        ValueError, match="'observation.state' has 7 dimensions but the policy was trained with 10"
    ):
        policy.predict_action_distribution(obs)


def test_unnormalized_needs_stats():
    policy = EnsembleDiffusionPolicy(tiny_config(uncertainty_space="unnormalized")).eval()
    assert not policy.has_action_stats
    with pytest.raises(ValueError, match="needs the action statistics"):
        policy.predict_action_distribution(random_observation(policy.config))


# ---- the auxiliary needle target --------------------------------------------------------------------
NEEDLE_KEY = "observation.needle_keypoints"


def _needle_inputs():
    from lerobot.configs import FeatureType, PolicyFeature
    from policy_builders import SUTURE_INPUT_FEATURES

    return {**SUTURE_INPUT_FEATURES, NEEDLE_KEY: PolicyFeature(type=FeatureType.STATE, shape=(6,))}


def _needle_policy(weight: float) -> EnsembleDiffusionPolicy:
    torch.manual_seed(0)
    config = tiny_config(input_features=_needle_inputs(), needle_keypoints_weight=weight)
    return EnsembleDiffusionPolicy(config, dataset_stats=fake_dataset_stats())


def test_needle_keypoints_are_a_target_never_an_input():
    """lerobot-train lists every `observation.*` dataset feature as an input; the keypoints are taken out."""
    policy = _needle_policy(weight=0.0)
    assert NEEDLE_KEY not in policy.config.input_features
    assert policy.config.needle_keypoints_dim == 6 and policy.needle_heads is None
    with pytest.raises(ValueError, match="needs the dataset feature 'observation.needle_keypoints'"):
        EnsembleDiffusionPolicy(tiny_config(needle_keypoints_weight=1.0))


def test_needle_loss_adds_the_weighted_keypoint_error_and_trains_the_encoders():
    policy = _needle_policy(weight=2.0).train()
    batch = _train_batch(policy.config)
    batch[NEEDLE_KEY] = torch.rand(4, policy.config.n_obs_steps, 6) * 2 - 1
    torch.manual_seed(5)
    loss, output = policy.forward(batch)
    assert set(output) == {"loss_member_0", "loss_member_1", "loss_needle_keypoints"}
    members_mean = (output["loss_member_0"] + output["loss_member_1"]) / 2
    torch.testing.assert_close(
        loss.item(), members_mean + 2.0 * output["loss_needle_keypoints"], rtol=1e-5, atol=0
    )
    # The error is each member's head on that member's image features of the current frame.
    errors = []
    for n, member in enumerate(policy.members):
        images = batch["observation.images.endoscope"][:, -1]
        features = member.diffusion.rgb_encoder[0](images)
        predicted = policy.needle_heads[n](features)
        errors.append(torch.nn.functional.mse_loss(predicted, batch[NEEDLE_KEY][:, -1]))
    torch.testing.assert_close(
        output["loss_needle_keypoints"], torch.stack(errors).mean().item(), rtol=1e-5, atol=0
    )
    loss.backward()
    params = list(policy.get_optim_params())
    assert all(p.grad is not None for p in params)
    assert any(p is policy.needle_heads[0].weight for p in params)  # the optimizer trains the heads
    # No hooks are left behind: inference and a plain forward are unchanged.
    assert not policy.members[0].diffusion.rgb_encoder[0]._forward_hooks
    del batch[NEEDLE_KEY]
    with pytest.raises(ValueError, match="needs 'observation.needle_keypoints' in the batch"):
        policy.forward(batch)


def test_needle_heads_are_saved_and_loaded(tmp_path):
    policy = _needle_policy(weight=1.0).eval()
    obs = random_observation(policy.config, batch_size=3)
    estimates = predict_needle_keypoints(policy, obs)
    assert estimates.shape == (3, 2, 6)
    member = policy.members[1]
    features = member.diffusion.rgb_encoder[0](obs["observation.images.endoscope"][:, -1])
    torch.testing.assert_close(estimates[:, 1], policy.needle_heads[1](features))
    with pytest.raises(ValueError, match="trained without the auxiliary needle target"):
        predict_needle_keypoints(_needle_policy(weight=0.0), obs)
    policy.save_pretrained(tmp_path)
    loaded = EnsembleDiffusionPolicy.from_pretrained(tmp_path)
    assert loaded.config.needle_keypoints_dim == 6 and NEEDLE_KEY not in loaded.config.input_features
    _assert_batch_equal(policy.state_dict(), loaded.state_dict())


def _prior_output_std() -> float:
    """The std of a random prior's output before its scale, from its init law by Gauss-Hermite quadrature.

    Layer norm makes each first pre-activation exactly N(0, 1) (weights N(0, 1/fan_in)); after Mish each of
    the 256 hidden units has second moment m2 = E[mish(z)^2], so the next pre-activation is about
    N(0, m2), and the output's variance is E[mish(sqrt(m2) z)^2].
    """
    z, w = np.polynomial.hermite_e.hermegauss(80)
    z, w = torch.from_numpy(z), torch.from_numpy(w / w.sum())
    m2 = (w * torch.nn.functional.mish(z) ** 2).sum()
    return float((w * torch.nn.functional.mish(m2.sqrt() * z) ** 2).sum().sqrt())


def test_random_priors_are_frozen_distinct_and_added_to_the_unet_output():
    """`prior_scale` > 0: each member's U-Net output is its own U-Net's plus its own fixed random prior of the
    conditioning; the priors take no gradient, so training leaves them as drawn."""
    policy = _policy(prior_scale=0.5)
    unets = [m.diffusion.unet for m in policy.members]
    priors = [u.prior for u in unets]
    assert not torch.equal(priors[0].layers[0].weight, priors[1].layers[0].weight)
    cond_dim = priors[0].layers[0].in_features
    cond = torch.randn(3, cond_dim)
    x = torch.randn(3, policy.config.horizon, 10)
    t = torch.tensor([5, 50, 90])
    with torch.no_grad():
        torch.testing.assert_close(
            unets[0](x, t, global_cond=cond), unets[0].unet(x, t, cond) + priors[0](cond)
        )
        assert priors[0](cond).shape == (3, policy.config.horizon, 10)
        # The scale the init law gives (see _prior_output_std), times `prior_scale`: the scale is in the
        # output's normalized units. Over weight draws the ratio stays within 5% of 1.
        ratio = priors[0](torch.randn(256, cond_dim)).std().item() / (0.5 * _prior_output_std())
        assert 0.85 < ratio < 1.15
    before = [p.layers[0].weight.clone() for p in priors]
    # The training optimizer (fused AdamW with weight decay) must leave them as drawn too.
    optimizer = torch.optim.AdamW(policy.get_optim_params(), lr=1e-2, weight_decay=0.1, fused=True)
    loss, _ = policy.forward(_train_batch(policy.config))
    loss.backward()
    assert all(param.grad is None for p in priors for param in p.parameters())
    optimizer.step()
    assert all(torch.equal(b, p.layers[0].weight) for b, p in zip(before, priors, strict=True))


def test_random_priors_run_batched_and_are_saved(tmp_path):
    """The fused inference adds the same priors as the members' own U-Nets, and a checkpoint restores them."""
    policy = _policy(prior_scale=1.0, noise_scheduler_type="DDIM").eval()
    obs = random_observation(policy.config, batch_size=2)
    noise = torch.randn(2, 2, 2, policy.config.horizon, 10)
    fused = _assert_fused_equals_loop(policy, obs, noise, samples_per_member=2)
    without = _policy(noise_scheduler_type="DDIM").eval()
    plain = without.predict_action_distribution(obs, samples_per_member=2, noise=noise)
    assert not torch.allclose(fused.normalized.samples, plain.normalized.samples)
    policy.save_pretrained(tmp_path)
    loaded = EnsembleDiffusionPolicy.from_pretrained(tmp_path)
    assert loaded.config.prior_scale == 1.0
    _assert_batch_equal(policy.state_dict(), loaded.state_dict())
