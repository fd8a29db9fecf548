"""Ensemble statistics: mean, covariance, law-of-total-covariance split and scores (pure torch)."""

import numpy as np
import pytest
import torch
from lerobot_policy_ensemble_diffusion.ensemble_stats import (
    EnsembleActionStats,
    compute_ensemble_stats,
    ensemble_covariance,
    ensemble_mean,
    total_covariance_split,
)

from lerobot_suture.safety.ood.score import score_tensor


def _np_cov(samples: np.ndarray, ddof: int) -> np.ndarray:
    """Reference: np.cov per step. samples (N, T, A) -> (T, A, A)."""
    return np.stack([np.cov(samples[:, t, :], rowvar=False, ddof=ddof) for t in range(samples.shape[1])])


def test_covariance_matches_numpy_on_known_samples():
    # Three members, two steps, two action dims; hand-checkable first step.
    samples = torch.tensor(
        [
            [[1.0, 2.0], [0.0, 0.0]],
            [[3.0, 2.0], [1.0, -1.0]],
            [[2.0, 5.0], [2.0, 1.0]],
        ]
    )  # (N=3, T=2, A=2)
    cov = ensemble_covariance(samples)  # (T, A, A)
    # Step 0: x = [1, 3, 2] (var 1), y = [2, 2, 5] (var 3), cov(x, y) = 0.
    torch.testing.assert_close(cov[0], torch.tensor([[1.0, 0.0], [0.0, 3.0]]))
    for ddof in (0, 1):
        expected = _np_cov(samples.numpy().astype(np.float64), ddof)
        torch.testing.assert_close(
            ensemble_covariance(samples, correction=ddof).double(), torch.from_numpy(expected)
        )
    torch.testing.assert_close(ensemble_mean(samples), samples.mean(0))


def test_covariance_matches_numpy_on_random_batches():
    rng = np.random.default_rng(0)
    samples = rng.normal(size=(4, 5, 8, 10))  # (B, N, T, A)
    cov = ensemble_covariance(torch.from_numpy(samples))
    for b in range(4):
        torch.testing.assert_close(cov[b], torch.from_numpy(_np_cov(samples[b], 1)))


def test_covariance_symmetric_psd():
    g = torch.Generator().manual_seed(1)
    samples = torch.randn(16, 5, 8, 10, generator=g) * torch.linspace(0.01, 10, 10)  # (B, N, T, A)
    cov = ensemble_covariance(samples)  # (B, T, A, A)
    assert torch.equal(cov, cov.transpose(-1, -2))
    eigenvalues = torch.linalg.eigvalsh(cov.double())
    assert eigenvalues.min() >= -1e-6 * eigenvalues.abs().max()  # float32 rounding only


def test_covariance_zero_when_members_identical():
    member = torch.randn(1, 1, 8, 10)
    samples = member.expand(3, 5, 8, 10)  # (B, N, T, A): every member predicts the same chunk
    cov = ensemble_covariance(samples)
    assert torch.count_nonzero(cov) == 0
    stats = compute_ensemble_stats(member.expand(3, 5, 4, 8, 10))  # K = 4 identical samples too
    assert torch.count_nonzero(stats.covariance) == 0
    assert torch.count_nonzero(stats.aleatoric) == 0
    assert score_tensor(stats.covariance, "max_abs_cov").eq(0).all()


def test_covariance_needs_enough_samples():
    with pytest.raises(ValueError, match="at least 2 samples"):
        ensemble_covariance(torch.randn(1, 8, 10))


def test_total_covariance_split_is_law_of_total_covariance():
    g = torch.Generator().manual_seed(2)
    samples = torch.randn(3, 5, 7, 8, 10, generator=g, dtype=torch.float64)  # (B, N, K, T, A)
    aleatoric, epistemic, total = total_covariance_split(samples, correction=0)
    # Population covariance of the N*K samples pooled (numpy, bias=True).
    for b in range(3):
        pooled = samples[b].reshape(5 * 7, 8, 10).numpy()
        torch.testing.assert_close(total[b], torch.from_numpy(_np_cov(pooled, 0)))
    # Each part on its own matches numpy.
    member_means = samples.mean(dim=2)
    torch.testing.assert_close(epistemic[1], torch.from_numpy(_np_cov(member_means[1].numpy(), 0)))
    within = np.mean([_np_cov(samples[1, n].numpy(), 0) for n in range(5)], axis=0)
    torch.testing.assert_close(aleatoric[1], torch.from_numpy(within))
    # The unbiased split adds up by construction and each part is PSD.
    aleatoric1, epistemic1, total1 = total_covariance_split(samples, correction=1)
    torch.testing.assert_close(total1, aleatoric1 + epistemic1)
    for part in (aleatoric1, epistemic1):
        assert torch.linalg.eigvalsh(part).min() > -1e-12


def test_split_separates_disagreement_from_spread():
    g = torch.Generator().manual_seed(3)
    # Members agree on the mean but each is noisy: aleatoric only.
    spread = 0.5 * torch.randn(1, 5, 200, 8, 2, generator=g, dtype=torch.float64)
    # Members disagree, each one is certain: epistemic only.
    disagree = torch.randn(1, 5, 1, 8, 2, generator=g, dtype=torch.float64).expand(1, 5, 200, 8, 2)
    s_spread = compute_ensemble_stats(spread - spread.mean(dim=2, keepdim=True))  # member means all 0
    s_disagree = compute_ensemble_stats(disagree)
    assert (
        score_tensor(s_spread.epistemic, "max_abs_cov")
        < 1e-12
        < score_tensor(s_spread.aleatoric, "max_abs_cov")
    )
    assert (
        score_tensor(s_disagree.aleatoric, "max_abs_cov")
        == 0
        < score_tensor(s_disagree.epistemic, "max_abs_cov")
    )


def test_compute_ensemble_stats_shapes_and_k1():
    samples = torch.randn(2, 5, 1, 8, 10)  # (B, N, K=1, T, A)
    stats = compute_ensemble_stats(samples)
    assert stats.member_mean.shape == (2, 5, 8, 10)
    assert stats.mean.shape == (2, 8, 10)
    assert stats.covariance.shape == stats.epistemic.shape == (2, 8, 10, 10)
    assert stats.aleatoric is None
    torch.testing.assert_close(stats.covariance, ensemble_covariance(samples[:, :, 0]))
    stats_k = compute_ensemble_stats(torch.randn(2, 5, 3, 8, 10))
    assert stats_k.aleatoric.shape == (2, 8, 10, 10)
    torch.testing.assert_close(stats_k.covariance, stats_k.aleatoric + stats_k.epistemic)


def test_a_single_member_s_covariance_is_its_own_over_its_samples():
    samples = torch.randn(2, 1, 6, 8, 3, generator=torch.Generator().manual_seed(4), dtype=torch.float64)
    stats = compute_ensemble_stats(samples)
    torch.testing.assert_close(stats.covariance, ensemble_covariance(samples[:, 0]))
    torch.testing.assert_close(stats.aleatoric, stats.covariance)
    assert not stats.epistemic.any()
    with pytest.raises(ValueError, match="needs at least 2 samples"):
        compute_ensemble_stats(samples[:, :, :1])


def test_affine_matches_statistics_of_transformed_samples():
    samples = torch.randn(2, 5, 3, 8, 4, dtype=torch.float64)
    scale = torch.tensor([0.5, 2.0, 1.0, 3.0], dtype=torch.float64)
    offset = torch.tensor([1.0, -1.0, 0.0, 2.0], dtype=torch.float64)
    mapped = compute_ensemble_stats(samples).affine(scale, offset)
    direct = compute_ensemble_stats(samples * scale + offset)
    assert isinstance(mapped, EnsembleActionStats)
    for name in ("samples", "member_mean", "mean", "covariance", "epistemic", "aleatoric"):
        torch.testing.assert_close(getattr(mapped, name), getattr(direct, name))


def test_scores():
    cov = torch.zeros(2, 3, 2, 2)  # (B, T, A, A)
    cov[0, 1] = torch.tensor([[1.0, -4.0], [-4.0, 2.0]])
    cov[1, 2] = torch.tensor([[3.0, 0.5], [0.5, 3.0]])
    torch.testing.assert_close(score_tensor(cov, "max_abs_cov"), torch.tensor([4.0, 3.0]))
    torch.testing.assert_close(score_tensor(cov, "trace"), torch.tensor([3.0, 6.0]))
    logdet = score_tensor(cov, "logdet", logdet_eps=1e-3)
    assert torch.isfinite(logdet).all()
    torch.testing.assert_close(logdet[1], torch.logdet(cov[1, 2] + 1e-3 * torch.eye(2)))
    with pytest.raises(ValueError, match="Unknown OOD score name 'max'"):
        score_tensor(cov, "max")
