"""Bootstrap particle filter, batched in torch over runs × particles (docs/design.md, "The benchmark protocol").

Transitions are sampled from the system's true process noise around the nominal f, weights come
from the exact measurement log-density log p(y_t − g(x_t, u_t)), all in log space. The estimate is
the weighted mean before resampling; resampling is systematic. A NaN measurement channel is
missing: the weights then use the density of the present channels only, and a step with no
channel present leaves them unchanged (docs/missing_data.md). A run whose float32 weights no longer
sum to 1 after normalising (a wild measurement, 1e9) is normalised again in float64 (``_normalise``).
"""

from __future__ import annotations

import math

import torch

from daof.envs.checks import as_seed
from daof.envs.system import StochasticSystem
from daof.filters.base import Filter

__all__ = ["systematic_resample", "ParticleFilter", "JointParameterPF"]


def systematic_resample(weights: torch.Tensor, u: torch.Tensor) -> torch.Tensor:
    """Systematic resampling of normalised ``weights [..., N]`` with one uniform ``u [...]`` per row.

    Particle j is picked for positions (i + u) / N that fall in [c_{j-1}, c_j), c = cumsum(weights),
    which is ``filterpy.monte_carlo.systematic_resample`` vectorised over rows. Returns long
    indices ``[..., N]``.
    """
    n = weights.shape[-1]
    # float64 cumulative sum so that c_N = 1 holds to rounding even for 10^4+ particles
    cumsum = weights.double().cumsum(-1)
    cumsum[..., -1] = 1.0
    positions = (torch.arange(n, device=weights.device, dtype=torch.float64) + u.double()[..., None]) / n
    return torch.searchsorted(cumsum, positions, right=True).clamp_max_(n - 1)


class ParticleFilter(Filter):
    """Bootstrap PF with N particles; all runs at once, chunked over runs above ``max_elements``.

    ``resample="ess"`` (default) resamples a run when its effective sample size 1/Σw² drops below
    ``ess_fraction``·N; ``resample="always"`` resamples every step. Runs are processed in chunks
    of at most ``max_elements`` run-particles; one ``torch.Generator`` seeded by ``seed`` drives
    the chunks in order, so results depend on ``seed`` and the chunk size only. A run whose
    estimate goes non-finite keeps NaN estimates from then on and is counted in
    ``stats["diverged"]``. ``run_with_std`` also returns the particles' weighted spread per state
    (the std of the filter's posterior), from the same particles and random stream.
    """

    name = "PF"
    std_source = "particle spread"

    def __init__(
        self,
        system: StochasticSystem,
        num_particles: int = 1000,
        seed: int = 0,
        resample: str = "ess",
        ess_fraction: float = 0.5,
        max_elements: int = 2**21,
    ):
        super().__init__(system)
        if num_particles < 1:
            raise ValueError(f"num_particles must be >= 1, got {num_particles}")
        if resample not in ("ess", "always"):
            raise ValueError(f"resample must be 'ess' or 'always', got {resample!r}")
        self.num_particles = num_particles
        self.seed = as_seed(seed)
        self.resample = resample
        self.ess_fraction = ess_fraction
        self.max_elements = max_elements
        #: what the particles follow: prior, process noise, f, g, measurement noise, state_dim
        self.model = system

    def _run(self, y, u_prev, u):
        return self._chunks(y, u_prev, u, spread=False)[0]

    def _run_with_std(self, y, u_prev, u):
        """The estimates and the weighted particle spread √(Σ w^i (x^i − x̂_t)²) per state."""
        return self._chunks(y, u_prev, u, spread=True)

    @torch.no_grad()
    def _chunks(self, y, u_prev, u, spread: bool) -> tuple[torch.Tensor, torch.Tensor | None]:
        """(estimates, spread or None) of all runs, filtered in chunks of at most ``max_elements`` run-particles."""
        runs = y.shape[0]
        generator = torch.Generator(device=y.device).manual_seed(int(self.seed))
        chunk = max(1, self.max_elements // self.num_particles)
        self.stats = {"resamples": 0, "diverged": 0}
        out = [
            self._filter(y[i : i + chunk], u_prev[i : i + chunk], u[i : i + chunk], generator, spread)
            for i in range(0, runs, chunk)
        ]
        estimates = torch.cat([e for e, _ in out])
        return estimates, torch.cat([s for _, s in out]) if spread else None

    def _filter(self, y, u_prev, u, generator, spread: bool = False):
        """One chunk of runs -> (estimates, weighted particle std or None), [runs, steps, n] each."""
        s, n = self.model, self.num_particles
        runs, steps = y.shape[:2]
        y, u_prev, u = (v.to(torch.float32) for v in (y, u_prev, u))
        x = s.prior.sample((runs, n), generator)  # particles of x_0 ~ prior, [runs, N, state_dim]
        log_w = torch.full((runs, n), -math.log(n), device=y.device)
        out = torch.empty(runs, steps, s.state_dim, device=y.device)
        std = torch.empty_like(out) if spread else None
        # missing channels (NaN), found once: the per-step test is a list lookup, so a study with
        # nothing missing runs exactly the loop it ran before
        present = ~torch.isnan(y)
        gappy = (~present).any(-1).any(0).tolist()
        resamples = 0
        diverged = torch.zeros(runs, dtype=torch.bool, device=y.device)
        for t in self._steps(runs, steps):
            u_prev_t, u_t = (v[:, t, None, :].expand(runs, n, -1) for v in (u_prev, u))
            x, log_p = self._move(
                x, y[:, t, None, :], u_prev_t, u_t, present[:, t, None, :] if gappy[t] else None, generator, t
            )
            log_w, w = _normalise(log_w, log_p)
            estimate = (w[..., None] * x).sum(1)  # x̂_t = Σ w^i x^i
            # a run that went non-finite stays NaN (resampling could otherwise revive it)
            diverged |= ~torch.isfinite(estimate).all(-1)
            out[:, t] = estimate.masked_fill(diverged[:, None], math.nan)
            if spread:  # the weighted spread of the same particles, before resampling
                variance = (w[..., None] * (x - estimate[:, None]).square()).sum(1)
                std[:, t] = variance.sqrt().masked_fill(diverged[:, None], math.nan)
            uniforms = torch.rand(runs, generator=generator, device=y.device)
            if self.resample == "always":
                rows = torch.ones(runs, dtype=torch.bool, device=y.device)
            else:
                rows = 1.0 / (w * w).sum(-1) < self.ess_fraction * n
            if rows.any():
                idx = systematic_resample(w, uniforms)
                # keep the particles of runs that do not resample: gather with the identity there
                idx = torch.where(rows[:, None], idx, torch.arange(n, device=y.device))
                x = x.gather(1, idx[..., None].expand_as(x))
                log_w = torch.where(rows[:, None], torch.full_like(log_w, -math.log(n)), log_w)
                resamples += int(rows.sum())
        self.stats["resamples"] += resamples
        self.stats["diverged"] += int(diverged.sum())
        return out, std

    def _move(self, x, y, u_prev, u, present, generator, t: int) -> tuple[torch.Tensor, torch.Tensor]:
        """Particles x_t [runs, N, n] from x_{t-1} and each one's log-weight increment [runs, N] at step index t.

        ``y`` is [runs, 1, m]; ``present`` the mask of its present channels, None when all are.
        The bootstrap: x_t^i = f(x_{t-1}^i, u_{t-1}) + ξ^i with ξ^i ~ the true process noise, and the
        increment log p_ζ(y_t − g(x_t^i, u_t)).
        """
        s = self.model
        x = s.f(x, u_prev) + s.process_noise.sample(x.shape[:-1], generator)
        return x, self._log_likelihood(y - s.g(x, u), present)

    def _log_likelihood(self, innovation, present) -> torch.Tensor:
        """log p(y_t | x_t^i) from the innovations; only the present channels where some are missing:
        p(y_t[S] | x_t^i) = ∏_{j∈S} p_ζj(innovation_j)."""
        noise = self.model.measurement_noise
        return noise.log_prob(innovation) if present is None else noise.marginal_log_prob(innovation, present)


#: normalised weights of a run that sum further from 1 than this lost their normalisation in float32
WEIGHT_SUM_TOLERANCE = 1e-3


def _normalise(log_w: torch.Tensor, log_p: torch.Tensor) -> tuple[torch.Tensor, torch.Tensor]:
    """Normalised log-weights and weights [runs, N] of ``log_w + log_p`` (both float32).

    In float32; a run whose weights then do not sum to 1 (log-likelihoods of ~-1e10, as a 1e9
    measurement gives, keep no difference between particles after ``log_w − logsumexp``, so several
    weights become 1) is normalised again in float64 after subtracting its largest log-weight.
    Ordinary runs never take that path, so their numbers are those of the float32 filter.
    """
    normalised = log_w + log_p
    normalised = normalised - torch.logsumexp(normalised, -1, keepdim=True)
    w = normalised.exp()
    lost = (w.sum(-1) - 1.0).abs() > WEIGHT_SUM_TOLERANCE
    if lost.any():
        wide = log_w[lost].double() + log_p[lost].double()
        wide = wide - wide.amax(-1, keepdim=True)  # the largest is 0: exp never overflows
        wide = wide - torch.logsumexp(wide, -1, keepdim=True)
        normalised[lost], w[lost] = wide.float(), wide.exp().float()
    return normalised, w


class _Appended:
    """A noise of the base state with extra coordinates drawn by ``extra(shape, generator, device)``."""

    def __init__(self, base, extra):
        self.base, self.extra = base, extra

    def sample(self, shape=(), generator=None):
        x = self.base.sample(shape, generator)
        return torch.cat([x, self.extra(shape, generator, x.device)], -1)


class _JointParameterModel:
    """A system's state with its uncertain parameters θ appended: θ static, from its uniform prior."""

    def __init__(self, system: StochasticSystem):
        ranges = system.uncertain_parameters()
        self.system, self.names = system, list(ranges)
        self.low = torch.tensor([lo for lo, _ in ranges.values()])
        self.high = torch.tensor([hi for _, hi in ranges.values()])
        self.state_dim = system.state_dim + len(ranges)
        self.measurement_noise = system.measurement_noise
        self.prior = _Appended(system.prior, self._sample_parameters)
        self.process_noise = _Appended(
            system.process_noise, lambda shape, _, device: torch.zeros(*shape, len(ranges), device=device)
        )

    def _sample_parameters(self, shape, generator, device):
        low, high = self.low.to(device), self.high.to(device)
        return low + (high - low) * torch.rand(*shape, len(self.names), generator=generator, device=device)

    def _split(self, x):
        d = self.system.state_dim
        return x[..., :d], {name: x[..., d + i] for i, name in enumerate(self.names)}

    def f(self, x, u):
        base, params = self._split(x)
        return torch.cat([self.system.f_with(base, u, params), x[..., self.system.state_dim :]], -1)

    def g(self, x, u):
        base, params = self._split(x)
        return self.system.g_with(base, u, params)


class JointParameterPF(ParticleFilter):
    """Bootstrap PF that infers the scenario's uncertain model parameters along with the state.

    Each particle carries (x, θ), θ = ``system.uncertain_parameters()`` (e.g. μ and B of veh2dof
    ``mismatch``) drawn once from their uniform prior and then static. The filter is told nothing
    about the run, like a learned filter, but knows the scenario's prior: with enough particles it
    is the scenario's Bayes filter. ``run`` returns the state estimates; ``parameter_estimates``
    holds the posterior mean of θ at every step of the last run ``[runs, steps, len(θ)]``.
    """

    name = "PF-joint"

    def __init__(self, system: StochasticSystem, num_particles: int = 20000, seed: int = 0, **kwargs):
        if not system.uncertain_parameters():
            raise ValueError(
                f"{system.name} ({system.scenario}) has no uncertain model parameters to infer; use ParticleFilter"
            )
        super().__init__(system, num_particles, seed, **kwargs)
        self.model = _JointParameterModel(system)
        self.parameter_estimates: torch.Tensor | None = None

    def _run(self, y, u_prev, u):
        return self._joint(y, u_prev, u, spread=False)[0]

    def _run_with_std(self, y, u_prev, u):
        return self._joint(y, u_prev, u, spread=True)

    def _joint(self, y, u_prev, u, spread: bool):
        """The states' estimates (and spread); μ and B's estimates are kept in ``parameter_estimates``."""
        joint, std = self._chunks(y, u_prev, u, spread)
        d = self.system.state_dim
        self.parameter_estimates = joint[..., d:]
        return joint[..., :d], std[..., :d] if std is not None else None
