"""Noise models (envs.noise): analytic moments from the spec, Monte Carlo agreement, densities.

Monte Carlo tolerances are Z standard errors of the estimator, the standard error itself
estimated from the samples, so a correct implementation fails with probability ~1e-6 per check.
"""

from __future__ import annotations

import math

import pytest
import torch
from daof.envs.noise import GaussianMixtureNoise, GaussianNoise, LaplaceNoise, OutlierLaplaceNoise
from torch import distributions as D

N_SAMPLES = 200_000
Z = 5.0  # standard errors allowed for a Monte Carlo estimate

SIGMA_XI = torch.tensor([0.002, 0.005])  # spec: process-noise scale per axis
B_ZETA = torch.tensor([1.5, 0.1])  # spec: Laplace scale per measurement channel
W, M, S = (0.7, 0.3), (-9.0 / 7.0, 3.0), (1.0, 2.0)  # spec: mixture weight, mean, std (× σ_ξ)


def spec_mixture() -> GaussianMixtureNoise:
    return GaussianMixtureNoise(W, M, S, SIGMA_XI)


def draw(noise, n=N_SAMPLES, seed=0) -> torch.Tensor:
    return noise.sample((n,), torch.Generator().manual_seed(seed)).double()


def assert_mean_within_se(x: torch.Tensor, mean: torch.Tensor) -> None:
    se = x.std(0) / math.sqrt(x.shape[0])
    assert ((x.mean(0) - mean.double()).abs() <= Z * se).all(), (x.mean(0), mean, se)


def assert_var_within_se(x: torch.Tensor, var: torch.Tensor) -> None:
    sq = (x - x.mean(0)) ** 2
    se = sq.std(0) / math.sqrt(x.shape[0])
    assert ((sq.mean(0) - var.double()).abs() <= Z * se).all(), (sq.mean(0), var, se)


# ----------------------------------------------------------------------------- Gaussian mixture
def test_mixture_analytic_mean_is_zero_and_covariance_is_spec_formula():
    noise = spec_mixture()
    factor = 0.7 * (1 + (9 / 7) ** 2) + 0.3 * (4 + 9)  # spec: ≈ 5.757
    assert factor == pytest.approx(5.757142857, rel=1e-9)
    torch.testing.assert_close(noise.mean, torch.zeros(2), atol=1e-9, rtol=0)
    torch.testing.assert_close(noise.covariance, torch.diag(SIGMA_XI**2 * factor), rtol=1e-6, atol=0)


def test_mixture_samples_match_moments_and_are_skewed():
    noise = spec_mixture()
    x = draw(noise)
    assert x.shape == (N_SAMPLES, 2) and x.dtype == torch.float64
    assert_mean_within_se(x, torch.zeros(2))
    assert_var_within_se(x, noise.covariance.diagonal())
    # Axes are independent: the empirical correlation is within Z/sqrt(n) of zero.
    corr = torch.corrcoef(x.T)[0, 1]
    assert abs(corr) < Z / math.sqrt(N_SAMPLES)
    # The mixture is asymmetric: E[z³] = Σ w_k (m_k³ + 3 m_k s_k²) ≈ 14.71 in units of σ_ξ³.
    third = sum(w * (m**3 + 3 * m * s**2) for w, m, s in zip(W, M, S))
    assert third == pytest.approx(14.7122, abs=1e-3)
    z3 = (x / SIGMA_XI.double()) ** 3
    se = z3.std(0) / math.sqrt(N_SAMPLES)
    assert ((z3.mean(0) - third).abs() <= Z * se).all(), (z3.mean(0), third, se)
    # Component 1 (weight 0.7, mean −9/7 σ) puts the median below zero: P(z < 0) ≈ 0.6558.
    p_neg = 0.7 * 0.5 * (1 + math.erf((9 / 7) / math.sqrt(2))) + 0.3 * 0.5 * (1 + math.erf(-1.5 / math.sqrt(2)))
    frac = (x < 0).double().mean(0)
    se = math.sqrt(p_neg * (1 - p_neg) / N_SAMPLES)
    assert ((frac - p_neg).abs() <= Z * se).all(), (frac, p_neg)


def test_mixture_log_prob_is_the_spec_density():
    noise = spec_mixture()
    x = torch.tensor([[0.0, 0.0], [-0.003, 0.01], [0.006, -0.02]])

    def axis_density(v, sigma):
        return sum(
            w / (s * sigma * math.sqrt(2 * math.pi)) * math.exp(-0.5 * ((v - m * sigma) / (s * sigma)) ** 2)
            for w, m, s in zip(W, M, S)
        )

    expected = [math.log(axis_density(float(r[0]), 0.002)) + math.log(axis_density(float(r[1]), 0.005)) for r in x]
    torch.testing.assert_close(noise.log_prob(x), torch.tensor(expected), rtol=1e-5, atol=1e-4)


# ----------------------------------------------------------------------------- Laplace
def test_laplace_variance_is_two_b_squared_and_samples_agree():
    noise = LaplaceNoise(B_ZETA)
    torch.testing.assert_close(noise.covariance, torch.diag(2 * B_ZETA**2))
    torch.testing.assert_close(noise.mean, torch.zeros(2))
    x = draw(noise)
    assert_mean_within_se(x, torch.zeros(2))
    assert_var_within_se(x, 2 * B_ZETA**2)
    # E|x| = b for a Laplace: pins the shape, not only the variance.
    a = x.abs()
    se = a.std(0) / math.sqrt(N_SAMPLES)
    assert ((a.mean(0) - B_ZETA.double()).abs() <= Z * se).all()


def test_laplace_log_prob_matches_torch_distributions():
    noise = LaplaceNoise(B_ZETA)
    x = torch.tensor([[0.0, 0.0], [1.0, -0.3], [-4.0, 0.05]])
    expected = D.Laplace(torch.zeros(2), B_ZETA).log_prob(x).sum(-1)
    torch.testing.assert_close(noise.log_prob(x), expected)
    # Hand value at x = [1, -0.3]: Σ −log(2b) − |x|/b.
    hand = sum(-math.log(2 * b) - abs(v) / b for v, b in zip((1.0, -0.3), (1.5, 0.1)))
    assert float(noise.log_prob(x[1])) == pytest.approx(hand, rel=1e-6)


def test_laplace_sample_is_finite_when_the_uniform_draw_is_zero(monkeypatch):
    """torch.rand returns exactly 0 once in 2^24 draws; the inverse CDF must not give -inf there.

    (A 1.6M-frame training run hit it: an infinite measurement, then a NaN estimate.)
    """
    monkeypatch.setattr(torch, "rand", lambda shape, **kw: torch.zeros(shape))
    assert torch.isfinite(OutlierLaplaceNoise(B_ZETA).sample(4)).all()
    x = LaplaceNoise(B_ZETA).sample(4)
    # the smallest non-zero float32 draw, 2^-24, takes its place: x = -b·log(2^23)
    torch.testing.assert_close(x, (-23 * math.log(2) * B_ZETA).expand(4, -1))


# ----------------------------------------------------------------------------- Laplace + outliers
def test_outlier_covariance_and_samples():
    p, k = 0.05, 10.0
    noise = OutlierLaplaceNoise(B_ZETA, prob=p, magnitude=k)
    var = 2 * B_ZETA**2 + p * (k * B_ZETA) ** 2  # spec: 2b² + p·(10b)²
    torch.testing.assert_close(noise.covariance, torch.diag(var))
    x = draw(noise)
    assert_mean_within_se(x, torch.zeros(2))
    assert_var_within_se(x, var)
    # Gross errors sit at ±10b: P(|x| > 5b) = p(1 − (e⁻⁵ − e⁻¹⁵)/2) + (1 − p)e⁻⁵ ≈ 0.0562.
    rate = p * (1 - 0.5 * (math.exp(-5) - math.exp(-15))) + (1 - p) * math.exp(-5)
    frac = (x.abs() > 5 * B_ZETA.double()).double().mean(0)
    se = math.sqrt(rate * (1 - rate) / N_SAMPLES)
    assert ((frac - rate).abs() <= Z * se).all(), (frac, rate)
    # Both signs occur equally often among the gross errors.
    pos = (x > 5 * B_ZETA.double()).double().mean(0)
    neg = (x < -5 * B_ZETA.double()).double().mean(0)
    assert ((pos - neg).abs() <= Z * math.sqrt(2 * rate / N_SAMPLES)).all()


def test_outlier_log_prob_is_the_three_component_mixture():
    p, k = 0.05, 10.0
    noise = OutlierLaplaceNoise(B_ZETA, prob=p, magnitude=k)
    x = torch.tensor([[0.0, 0.0], [15.0, -1.0], [-14.0, 0.9]])
    expected = torch.zeros(3)
    for i, b in enumerate(B_ZETA):
        lap = D.Laplace(torch.tensor(0.0), b)
        v = x[:, i]
        dens = (1 - p) * lap.log_prob(v).exp() + p / 2 * (lap.log_prob(v - k * b).exp() + lap.log_prob(v + k * b).exp())
        expected += dens.log()
    torch.testing.assert_close(noise.log_prob(x), expected, rtol=1e-5, atol=1e-5)
    # With p = 0 the density is the plain Laplace.
    plain = OutlierLaplaceNoise(B_ZETA, prob=0.0)
    torch.testing.assert_close(plain.log_prob(x), LaplaceNoise(B_ZETA).log_prob(x))


# ----------------------------------------------------------------------------- all noises
def test_gaussian_log_prob_and_moments():
    cov = torch.tensor([[0.04, 0.01], [0.01, 0.09]])
    noise = GaussianNoise([0.5, -1.0], cov)
    x = torch.tensor([[0.5, -1.0], [0.0, 0.0]])
    diff = x - torch.tensor([0.5, -1.0])
    maha = torch.einsum("bi,ij,bj->b", diff, torch.linalg.inv(cov), diff)
    expected = -0.5 * maha - 0.5 * torch.logdet(2 * math.pi * cov)
    torch.testing.assert_close(noise.log_prob(x), expected, rtol=1e-5, atol=1e-5)
    s = draw(noise)
    assert_mean_within_se(s, torch.tensor([0.5, -1.0]))
    assert_var_within_se(s, cov.diagonal())
    emp_cov = torch.cov(s.T)
    # Cross-covariance standard error for a Gaussian: sqrt((σ₁²σ₂² + σ₁₂²)/n).
    se = math.sqrt((0.04 * 0.09 + 0.01**2) / N_SAMPLES)
    assert abs(float(emp_cov[0, 1]) - 0.01) <= Z * se


def test_gaussian_from_stds_has_those_stds():
    """``GaussianNoise.diagonal(mean, std)`` (how the linear system states its noises) draws with std, not std²."""
    std = torch.tensor([0.2, 0.05])
    noise = GaussianNoise.diagonal([0.0, 1.0], std)
    torch.testing.assert_close(noise.covariance, torch.diag(std**2))
    s = draw(noise)
    assert_mean_within_se(s, torch.tensor([0.0, 1.0]))
    assert_var_within_se(s, std**2)


ONE_D = {
    "gaussian": (GaussianNoise([0.3], [[2.0]]), 30.0),
    "mixture": (GaussianMixtureNoise(W, M, S, [1.0]), 30.0),
    "laplace": (LaplaceNoise([1.0]), 40.0),
    "outliers": (OutlierLaplaceNoise([1.0], 0.05, 10.0), 60.0),
}


@pytest.mark.parametrize("name", sorted(ONE_D))
def test_density_integrates_to_one_in_1d(name):
    noise, half_width = ONE_D[name]
    grid = torch.linspace(-half_width, half_width, 400_001)
    density = noise.log_prob(grid[:, None]).double().exp()
    total = torch.trapezoid(density, grid.double())
    assert float(total) == pytest.approx(1.0, abs=1e-4)


@pytest.mark.parametrize("name", sorted(ONE_D))
def test_sampling_is_reproducible_from_the_generator(name):
    noise, _ = ONE_D[name]
    a = noise.sample((4, 5), torch.Generator().manual_seed(7))
    b = noise.sample((4, 5), torch.Generator().manual_seed(7))
    c = noise.sample((4, 5), torch.Generator().manual_seed(8))
    assert a.shape == (4, 5, 1) and a.dtype == torch.float32
    assert torch.equal(a, b)
    assert not torch.equal(a, c)


def test_invalid_parameters_raise():
    with pytest.raises(ValueError, match="sum to 1"):
        GaussianMixtureNoise((0.5, 0.4), M, S, SIGMA_XI)
    with pytest.raises(ValueError, match="positive"):
        LaplaceNoise([1.0, 0.0])
    with pytest.raises(ValueError, match=r"\[0, 1\)"):
        OutlierLaplaceNoise([1.0], prob=1.0)
    with pytest.raises(ValueError, match="covariance"):
        GaussianNoise([0.0, 0.0], [[1.0]])


# ----------------------------------------------------------------------------- joint mixture
def test_joint_mixture_draws_one_component_for_all_axes():
    """joint=True: the component is shared by the axes; joint=False: drawn per axis.

    The components sit at means 0 and 100 (std 1, scales 1 and 2), so each axis's component is read
    off a sample exactly (|z| < 50 or not: a misread needs a 50σ draw). With joint=True every sample's
    axes agree; with joint=False they disagree at the rate 2w(1 − w) = 0.42. Both fractions in the
    second component match its weight 0.3 within Z standard errors (SE = √(w(1 − w)/n) ≈ 0.001: a
    weight off by 0.01 fails with probability > 0.999).
    """
    w = 0.3
    joint = GaussianMixtureNoise((1 - w, w), (0.0, 100.0), (1.0, 1.0), [1.0, 2.0], joint=True)
    indep = GaussianMixtureNoise((1 - w, w), (0.0, 100.0), (1.0, 1.0), [1.0, 2.0])
    se = math.sqrt(w * (1 - w) / N_SAMPLES)
    for noise, mismatch in ((joint, 0.0), (indep, 2 * w * (1 - w))):
        k = (draw(noise) / torch.tensor([1.0, 2.0], dtype=torch.float64)).abs() > 50.0  # component per axis
        frac = k.double().mean(0)
        assert ((frac - w).abs() <= Z * se).all(), (noise.joint, frac)
        disagree = (k[:, 0] != k[:, 1]).double().mean().item()
        assert abs(disagree - mismatch) <= Z * math.sqrt(mismatch * (1 - mismatch) / N_SAMPLES), (noise.joint, disagree)
    assert joint.joint and not indep.joint


def test_joint_mixture_moments_density_and_marginal():
    """Same per-axis marginals as the per-axis mixture; the joint density is Σ_k w_k ∏_i N_ik."""
    joint = GaussianMixtureNoise(W, M, S, SIGMA_XI, joint=True)
    indep = spec_mixture()
    torch.testing.assert_close(joint.mean, indep.mean)
    # with zero component means (veh14dof) the covariance is diagonal; here m_k ≠ 0, so the axes co-vary:
    # Cov = Σ_k w_k (diag(s_k²) + m_k m_kᵀ) − μμᵀ, in units of σ_i σ_j (μ = 0 for this mixture)
    second = sum(w * (m * m) for w, m in zip(W, M))
    cross = second * SIGMA_XI[0] * SIGMA_XI[1]
    expected = indep.covariance.clone()
    expected[0, 1] = expected[1, 0] = cross
    torch.testing.assert_close(joint.covariance, expected, rtol=1e-6, atol=0)
    x = draw(joint)
    assert_mean_within_se(x, torch.zeros(2))
    assert_var_within_se(x, joint.covariance.diagonal())
    prod = x[:, 0] * x[:, 1]
    se = prod.std() / math.sqrt(N_SAMPLES)
    assert abs(prod.mean() - cross.double()) <= Z * se
    # density by hand
    v = torch.tensor([[0.0, 0.0], [-0.003, 0.01], [0.006, -0.02]])

    def normal(z, m, s):
        return math.exp(-0.5 * ((z - m) / s) ** 2) / (s * math.sqrt(2 * math.pi))

    def dens(row):
        return sum(
            w * normal(float(row[0]), m * 0.002, s * 0.002) * normal(float(row[1]), m * 0.005, s * 0.005)
            for w, m, s in zip(W, M, S)
        )

    expected_lp = torch.tensor([math.log(dens(r)) for r in v])
    torch.testing.assert_close(joint.log_prob(v), expected_lp, rtol=1e-5, atol=1e-4)
    # marginal of axis 0 alone is the 1-D mixture; both present is log_prob; none present is 0
    only0 = torch.tensor([True, False])
    torch.testing.assert_close(joint.marginal_log_prob(v, only0), indep.channel_log_prob(v)[:, 0])
    torch.testing.assert_close(joint.marginal_log_prob(v, torch.tensor([True, True])), joint.log_prob(v))
    torch.testing.assert_close(joint.marginal_log_prob(v, torch.tensor([False, False])), torch.zeros(3))
    nan_row = torch.tensor([[0.001, float("nan")]])
    assert torch.isfinite(joint.marginal_log_prob(nan_row, torch.tensor([True, False]))).all()
    with pytest.raises(NotImplementedError, match="not independent"):
        joint.channel_log_prob(v)
    with pytest.raises(ValueError, match="same weights"):
        GaussianMixtureNoise([[0.5, 0.5], [0.9, 0.1]], M, S, SIGMA_XI, joint=True)


def test_joint_mixture_density_integrates_to_one_in_2d():
    joint = GaussianMixtureNoise(W, M, S, [1.0, 1.0], joint=True)
    g = torch.linspace(-20.0, 25.0, 901, dtype=torch.float64)
    X, Y = torch.meshgrid(g, g, indexing="ij")
    dens = joint.log_prob(torch.stack([X, Y], -1).float()).double().exp()
    total = torch.trapezoid(torch.trapezoid(dens, g), g)
    assert float(total) == pytest.approx(1.0, abs=1e-4)
