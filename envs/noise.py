"""Noise models as torch distributions with generator-driven sampling.

Every noise here is a vector distribution over ``dim`` independent or jointly Gaussian axes and
offers what a simulator and a filter need: batched ``sample(shape, generator)`` that is
reproducible from a ``torch.Generator``, ``log_prob`` (exact density, for the particle filter),
``mean`` and ``covariance`` (what a Kalman-type filter uses as Q or R), and
``marginal_log_prob`` (the density of the present channels only, for a particle filter whose
measurement has missing channels, docs/missing_data.md).

Densities, means and variances come from ``torch.distributions``; sampling is written here
because ``torch.distributions`` cannot draw from an explicit ``torch.Generator``.
"""

from __future__ import annotations

import math

import torch
from torch import distributions as D

__all__ = [
    "Noise",
    "GaussianNoise",
    "GaussianMixtureNoise",
    "LaplaceNoise",
    "OutlierLaplaceNoise",
]


def _as_tensor(value, dtype=torch.float32) -> torch.Tensor:
    return torch.as_tensor(value, dtype=dtype).clone()


class Noise:
    """Common interface: a distribution over R^dim with generator-driven sampling."""

    dim: int

    def sample(self, shape=(), generator: torch.Generator | None = None) -> torch.Tensor:
        """Draw ``[*shape, dim]`` samples."""
        raise NotImplementedError

    def log_prob(self, value: torch.Tensor) -> torch.Tensor:
        """Log-density of ``[..., dim]`` values, summed over the ``dim`` axes -> ``[...]``."""
        raise NotImplementedError

    def channel_log_prob(self, value: torch.Tensor) -> torch.Tensor:
        """Log-density of each axis on its own -> ``[..., dim]``; ``log_prob`` is their sum.

        Only noises whose axes are independent have it.
        """
        raise NotImplementedError(f"{type(self).__name__} has no per-axis density (its axes are not independent)")

    def marginal_log_prob(self, value: torch.Tensor, present: torch.Tensor) -> torch.Tensor:
        """Log-density of the present axes only (the missing ones marginalised out) -> ``[...]``.

        ``present`` is a bool mask broadcastable to ``value``; missing entries of ``value`` may be
        NaN. For independent axes the marginal is the sum of ``channel_log_prob`` over the present
        axes; nothing present gives 0 (no information).
        """
        return torch.where(present, self.channel_log_prob(value), 0.0).sum(-1)

    @property
    def mean(self) -> torch.Tensor:
        raise NotImplementedError

    @property
    def covariance(self) -> torch.Tensor:
        raise NotImplementedError

    def to(self, device) -> Noise:
        """Move every tensor attribute to ``device`` (in place) and return self."""
        for name, value in vars(self).items():
            if isinstance(value, torch.Tensor):
                setattr(self, name, value.to(device))
        return self

    def _device(self) -> torch.device:
        return self.mean.device

    def _shape(self, shape) -> tuple[int, ...]:
        if isinstance(shape, int):
            shape = (shape,)
        return (*tuple(shape), self.dim)


class GaussianNoise(Noise):
    """Multivariate normal N(mean, cov); also used as a system's prior."""

    def __init__(self, mean, covariance):
        self.loc = _as_tensor(mean)
        self.cov = _as_tensor(covariance)
        self.dim = self.loc.shape[-1]
        if self.cov.shape != (self.dim, self.dim):
            raise ValueError(
                f"covariance must be [{self.dim}, {self.dim}] to match the mean, got {tuple(self.cov.shape)}"
            )
        self.scale_tril = torch.linalg.cholesky(self.cov)

    @classmethod
    def diagonal(cls, mean, std) -> GaussianNoise:
        std = _as_tensor(std)
        return cls(mean, torch.diag(std**2))

    def sample(self, shape=(), generator=None):
        eps = torch.randn(self._shape(shape), generator=generator, device=self._device())
        return self.loc + eps @ self.scale_tril.T

    def log_prob(self, value):
        return D.MultivariateNormal(self.loc, scale_tril=self.scale_tril).log_prob(value)

    def _is_diagonal(self) -> bool:
        return bool((self.cov == torch.diag(self.cov.diagonal())).all())

    def channel_log_prob(self, value):
        if not self._is_diagonal():
            return super().channel_log_prob(value)
        return D.Normal(self.loc, self.cov.diagonal().sqrt()).log_prob(value)

    def marginal_log_prob(self, value, present):
        if self._is_diagonal():
            return super().marginal_log_prob(value, present)
        # correlated axes: the marginal of the present axes is N(loc[S], cov[S, S]), one per pattern S
        present = torch.broadcast_to(present, value.shape)
        out = value.new_zeros(value.shape[:-1])
        for pattern in torch.unique(present.reshape(-1, self.dim), dim=0):
            rows = (present == pattern).all(-1)
            idx = pattern.nonzero().squeeze(-1)
            if idx.numel():
                marginal = D.MultivariateNormal(self.loc[idx], self.cov[idx][:, idx])
                out[rows] = marginal.log_prob(value[rows][:, idx])
        return out

    @property
    def mean(self):
        return self.loc

    @property
    def covariance(self):
        return self.cov


class GaussianMixtureNoise(Noise):
    """Gaussian mixture per axis, scaled per axis; the component independent per axis or joint.

    Axis i is ``scale_i * z_i`` with ``z_i ~ sum_k w_k N(m_ik, s_ik^2)``. ``weights``, ``means`` and
    ``stds`` are ``[K]`` (shared by all axes) or ``[dim, K]``.

    ``joint=False`` (default): the component is drawn independently per axis, so the axes are
    independent (a K^dim-component mixture of the vector; diagonal covariance).
    ``joint=True``: one component k per sample, shared by every axis, and the axes independent
    given k — a K-component mixture of the vector, e.g. a disturbance that is either small on
    all axes or large on all axes. Its weights must then be the same for every axis.
    """

    def __init__(self, weights, means, stds, scale, joint: bool = False):
        self.scale = _as_tensor(scale)
        self.dim = self.scale.shape[-1]
        w, m, s = (_as_tensor(v).expand(self.dim, -1).clone() for v in (weights, means, stds))
        if not torch.allclose(w.sum(-1), torch.ones(())):
            raise ValueError(f"mixture weights must sum to 1, got {w.sum(-1).tolist()}")
        if (s <= 0).any() or (self.scale <= 0).any():
            raise ValueError("mixture stds and axis scales must be positive")
        if joint and not (w == w[:1]).all():
            raise ValueError("a joint mixture (one component for all axes) needs the same weights on every axis")
        self.weights, self.means, self.stds = w, m, s
        self.joint = bool(joint)

    def _components(self) -> D.Distribution:
        """Per axis and component: N(m_ik·scale_i, (s_ik·scale_i)²), batch ``[dim, K]``."""
        return D.Normal(self.means * self.scale[:, None], self.stds * self.scale[:, None])

    def _dist(self) -> D.Distribution:
        if self.joint:
            # components over the whole vector: batch [K] of Independent normals over the dim axes
            comp = D.Normal(self.means.T * self.scale, self.stds.T * self.scale)
            return D.MixtureSameFamily(D.Categorical(probs=self.weights[0]), D.Independent(comp, 1))
        return D.Independent(D.MixtureSameFamily(D.Categorical(probs=self.weights), self._components()), 1)

    def sample(self, shape=(), generator=None):
        full = self._shape(shape)
        device = self._device()
        # Component index by inverse CDF of the categorical weights: one per axis, or one per
        # sample shared by all axes (joint).
        u = torch.rand((*full[:-1], 1) if self.joint else full, generator=generator, device=device)
        cdf = self.weights.cumsum(-1)
        k = (u[..., None] > cdf).sum(-1).clamp_max(self.weights.shape[-1] - 1)
        eps = torch.randn(full, generator=generator, device=device)
        # z = m_k + s_k·ε, selected component by component: a few elementwise ops instead of
        # advanced indexing, which dominated the particle filter's step.
        z = self.means[:, 0] + self.stds[:, 0] * eps
        for j in range(1, self.weights.shape[-1]):
            z = torch.where(k == j, self.means[:, j] + self.stds[:, j] * eps, z)
        return z * self.scale

    def log_prob(self, value):
        return self._dist().log_prob(value)

    def channel_log_prob(self, value):
        if self.joint:
            return super().channel_log_prob(value)
        return self._dist().base_dist.log_prob(value)

    def marginal_log_prob(self, value, present):
        if not self.joint:
            return super().marginal_log_prob(value, present)
        # the present axes S of a joint mixture: log Σ_k w_k ∏_{i∈S} N_ik(x_i); none present gives 0
        per_axis = self._components().log_prob(value[..., :, None])  # [..., dim, K]
        per_axis = torch.where(present[..., :, None], per_axis, 0.0)
        return torch.logsumexp(self.weights[0].log() + per_axis.sum(-2), -1)

    @property
    def mean(self):
        return (self.weights * self.means).sum(-1) * self.scale

    @property
    def covariance(self):
        mean = (self.weights * self.means).sum(-1)
        if self.joint:
            # Σ_k w_k (diag(s_k²) + m_k m_kᵀ) − μ μᵀ, in units of scale_i scale_j
            w, m = self.weights[0], self.means
            second = torch.einsum("k,ik,jk->ij", w, m, m) + torch.diag((self.weights * self.stds**2).sum(-1))
            return (second - torch.outer(mean, mean)) * torch.outer(self.scale, self.scale)
        second = (self.weights * (self.stds**2 + self.means**2)).sum(-1)
        return torch.diag((second - mean**2) * self.scale**2)


class LaplaceNoise(Noise):
    """Independent zero-mean Laplace noise per channel with scale ``b`` (variance 2b²)."""

    def __init__(self, scale, loc=0.0):
        self.b = _as_tensor(scale)
        self.dim = self.b.shape[-1]
        self.loc = torch.broadcast_to(_as_tensor(loc), self.b.shape).clone()
        if (self.b <= 0).any():
            raise ValueError("Laplace scales must be positive")

    def _laplace(self, value, shift=0.0):
        return D.Laplace(self.loc + shift, self.b).log_prob(value)

    def sample(self, shape=(), generator=None):
        # Inverse CDF: b * sign(v) * -log(1 - 2|v|), v ~ U(-1/2, 1/2).
        # torch.rand can return exactly 0 (p = 2^-24 per draw in float32), and v = -1/2 gives -inf:
        # the smallest non-zero draw takes its place, so every other sample is unchanged.
        u = torch.rand(self._shape(shape), generator=generator, device=self._device())
        v = u.clamp_min(torch.finfo(u.dtype).eps / 2) - 0.5
        return self.loc - self.b * v.sign() * torch.log1p(-2 * v.abs())

    def channel_log_prob(self, value):
        return self._laplace(value)

    def log_prob(self, value):
        return self.channel_log_prob(value).sum(-1)

    @property
    def mean(self):
        return self.loc

    @property
    def covariance(self):
        return torch.diag(2 * self.b**2)


class OutlierLaplaceNoise(LaplaceNoise):
    """Laplace noise plus, with probability ``p`` per channel and step, a gross error ±``k``·b.

    The sign of the gross error is random, so the noise stays zero-mean; its density is the
    three-component mixture (1−p)·Lap(0) + p/2·Lap(+kb) + p/2·Lap(−kb).
    """

    def __init__(self, scale, prob=0.05, magnitude=10.0):
        super().__init__(scale)
        if not 0.0 <= prob < 1.0:
            raise ValueError(f"outlier probability must be in [0, 1), got {prob}")
        self.prob = float(prob)
        self.magnitude = float(magnitude)

    def sample(self, shape=(), generator=None):
        base = super().sample(shape, generator)
        u = torch.rand(base.shape, generator=generator, device=base.device)
        sign = torch.where(torch.rand(base.shape, generator=generator, device=base.device) < 0.5, -1.0, 1.0)
        return base + (u < self.prob) * sign * self.magnitude * self.b

    def channel_log_prob(self, value):
        offset = self.magnitude * self.b
        p = self.prob
        terms = torch.stack(
            [
                math.log1p(-p) + self._laplace(value),
                math.log(p / 2) + self._laplace(value, offset) if p > 0 else self._laplace(value) - math.inf,
                math.log(p / 2) + self._laplace(value, -offset) if p > 0 else self._laplace(value) - math.inf,
            ]
        )
        return torch.logsumexp(terms, 0)

    @property
    def covariance(self):
        return torch.diag(2 * self.b**2 + self.prob * (self.magnitude * self.b) ** 2)
