"""Kalman-type baselines on filterpy: ``KalmanFilter`` (linear), ``EKF`` and ``UKF`` (nonlinear).

Each filter gets the system's nominal f and g, Q = process-noise covariance, R = measurement-noise
covariance and starts from x̂_0 = prior mean, P_0 = prior covariance; for t = 1..T it predicts with
u_{t-1} and updates with y_t = g(x_t, u_t) (``daof.envs.system`` time convention). filterpy works in
float64; ``dtype`` only sets the dtype of the returned estimates.

A NaN measurement channel is missing (sensor dropout): that step updates with the present
channels only (the rows S of H or g, R[S, S]), or only predicts if none is present
(docs/missing_data.md). Steps with every channel present run the unchanged filterpy step.

Two numerical rules of the benchmark protocol (docs/design.md): a covariance that is no longer positive definite is
repaired (symmetrise, add jitter until Cholesky succeeds) and counted in ``stats["repairs"]``; a run
whose estimate becomes non-finite (or whose algebra fails) is kept, its remaining estimates are NaN,
and it is counted in ``stats["diverged"]`` — it never stops the study. So is a run whose estimate leaves the
system's ``divergence_limits`` (``Filter.run``).
"""

from __future__ import annotations

import copy

import numpy as np
import torch
from filterpy.kalman import ExtendedKalmanFilter, MerweScaledSigmaPoints, UnscentedKalmanFilter
from filterpy.kalman import KalmanFilter as _FilterpyKF

from daof.envs.system import StochasticSystem
from daof.filters.base import Filter

__all__ = ["CovarianceRepair", "NumpyModel", "TorchModel", "make_model", "KalmanFilter", "EKF", "UKF"]


# ----------------------------------------------------------------------------- models
class TorchModel:
    """f, g and their Jacobians F = ∂f/∂x, H = ∂g/∂x from the system's torch functions (float64).

    Works for every system; each call converts numpy -> torch -> numpy, and the Jacobians come from
    ``torch.func.jacrev``.
    """

    def __init__(self, system: StochasticSystem):
        # StochasticSystem.to hands its argument to Tensor.to, which also accepts a dtype
        self.system = copy.deepcopy(system).to("cpu").to(torch.float64)
        self._F = torch.func.jacrev(self.system.f, argnums=0)
        self._H = torch.func.jacrev(self.system.g, argnums=0)

    def _call(self, fn, x, u) -> np.ndarray:
        with torch.no_grad():
            return fn(torch.from_numpy(np.asarray(x, np.float64)), torch.from_numpy(u)).numpy()

    def f(self, x, u):
        return self._call(self.system.f, x, u)

    def g(self, x, u):
        return self._call(self.system.g, x, u)

    def F(self, x, u):
        return self._call(self._F, x, u)

    def H(self, x, u):
        return self._call(self._H, x, u)


class NumpyModel:
    """A system's own numpy f and g (``f_numpy``, ``g_numpy``), batched over leading dims.

    The functions are complex-analytic, so the Jacobians come from the complex step
    ∂f/∂x_j = Im f(x + i h e_j) / h, exact to rounding (no subtractive cancellation).
    ``tests/test_classical_filters.py`` pins f, g, F, H against the torch model.
    """

    step = 1e-30  # complex-step size; any tiny h works, the result does not depend on it

    def __init__(self, f, g, state_dim: int):
        self.f, self.g, self.n = f, g, state_dim
        self._probe = 1j * self.step * np.eye(state_dim)

    def _jacobian(self, fn, x, u) -> np.ndarray:
        # row j of the batch is x + i h e_j -> column j of the Jacobian
        return fn(x + self._probe, u).imag.T / self.step

    def F(self, x, u):
        return self._jacobian(self.f, x, u)

    def H(self, x, u):
        return self._jacobian(self.g, x, u)


def make_model(system: StochasticSystem, kind: str = "auto"):
    """``"numpy"`` (the system's own numpy model, where it has one: ``system.has_numpy_model``),
    ``"torch"`` (any system) or ``"auto"``.

    ``auto`` prefers numpy: on veh2dof a call of f is ~2× and of F ~20× cheaper in numpy than
    through torch on a tiny tensor (``benchmarks/bench_classical.py --models``,
    docs/benchmarks/classical.md). No system is picked by name: a subclass that changes ``f`` or
    ``g`` without its numpy twin gets the torch model.
    """
    if kind not in ("auto", "numpy", "torch"):
        raise ValueError(f"model must be 'auto', 'numpy' or 'torch', got {kind!r}")
    if kind != "torch" and system.has_numpy_model:
        return NumpyModel(system.f_numpy, system.g_numpy, system.state_dim)
    if kind == "numpy":
        raise ValueError(f"no numpy model for system {system.name!r}; use model='torch'")
    return TorchModel(system)


# ----------------------------------------------------------------------------- repair
class CovarianceRepair:
    """Makes a covariance positive definite again the way practitioners do, and counts it.

    Symmetrise, shift the spectrum to just above zero, then multiply the jitter by 10 until a
    Cholesky factorisation succeeds. ``jitter`` is relative to the largest diagonal entry.
    """

    def __init__(self, jitter: float = 1e-9):
        self.jitter = jitter
        self.count = 0

    def __call__(self, P: np.ndarray) -> np.ndarray:
        try:
            np.linalg.cholesky(P)
            return P
        except np.linalg.LinAlgError:
            pass
        if not np.isfinite(P).all():
            raise FloatingPointError("covariance is not finite")
        P = 0.5 * (P + P.T)
        eye = np.eye(P.shape[0])
        scale = max(float(np.abs(np.diag(P)).max()), np.finfo(np.float64).tiny)
        jitter = max(-float(np.linalg.eigvalsh(P).min()), 0.0) + self.jitter * scale
        while True:
            try:
                np.linalg.cholesky(P + jitter * eye)
                break
            except np.linalg.LinAlgError:
                jitter *= 10.0
        self.count += 1
        return P + jitter * eye

    def sqrt(self, P: np.ndarray) -> np.ndarray:
        """Upper-triangular U with Uᵀ U = P (filterpy's sigma-point convention), repairing P first."""
        try:
            return np.linalg.cholesky(P).T
        except np.linalg.LinAlgError:
            return np.linalg.cholesky(self(P)).T


# ----------------------------------------------------------------------------- filters
class _KalmanBase(Filter):
    """Shared loop: per run, reset to the prior; per step, repair P, predict(u_{t-1}), update(y_t).

    ``run_with_std`` also returns √diag P⁺_t, the std the filter claims for each estimate.
    """

    std_source = "covariance"

    def __init__(self, system: StochasticSystem, dtype: torch.dtype = torch.float32, jitter: float = 1e-9):
        super().__init__(system)
        self.dtype = dtype
        self.repair = CovarianceRepair(jitter)
        self.Q = system.process_noise.covariance.double().cpu().numpy()
        self.R = system.measurement_noise.covariance.double().cpu().numpy()
        self.x0 = system.prior.mean.double().cpu().numpy()
        #: P_0; tests may overwrite it to force the repair path
        self.P0 = system.prior.covariance.double().cpu().numpy()

    def _make(self):
        """A fresh filterpy filter at the prior."""
        raise NotImplementedError

    def _step(self, kf, y, u_prev, u) -> None:
        """Predict with u_{t-1}, update with every channel of y_t."""
        raise NotImplementedError

    def _step_missing(self, kf, y, u_prev, u, present: np.ndarray) -> None:
        """Predict with u_{t-1}, update with the channels ``present`` of y_t only (none: no update)."""
        raise NotImplementedError

    def _R_present(self, present: np.ndarray) -> np.ndarray:
        """R[S, S] of the present channels S (the marginal covariance of their noise)."""
        return self.R[np.ix_(present, present)]

    def _run(self, y, u_prev, u, variances: bool = False):
        """Estimates [runs, steps, n] (NaN after a run's failure); with ``variances``, also diag P⁺ per step."""
        device = y.device
        y, u_prev, u = (v.detach().double().cpu().numpy() for v in (y, u_prev, u))
        runs, steps = y.shape[:2]
        # missing channels (NaN), found once: the per-step test is a list lookup
        present = ~np.isnan(y)
        gappy = (~present).any(-1).tolist()
        out = np.full((runs, steps, self.system.state_dim), np.nan)
        var = np.full_like(out, np.nan) if variances else None
        self.repair.count = 0
        diverged = 0
        for r in range(runs):
            kf = self._make()
            yr, upr, ur, gr = y[r], u_prev[r], u[r], gappy[r]
            try:
                for t in self._steps(1, steps):
                    kf.P = self.repair(kf.P)
                    if gr[t]:
                        self._step_missing(kf, yr[t], upr[t], ur[t], present[r, t])
                    else:
                        self._step(kf, yr[t], upr[t], ur[t])
                    x = kf.x.reshape(-1)
                    if not np.isfinite(x).all():
                        raise FloatingPointError("non-finite estimate")
                    out[r, t] = x
                    if var is not None:
                        var[r, t] = np.diag(kf.P)
            except (FloatingPointError, np.linalg.LinAlgError, ValueError):
                diverged += 1  # the rest of this run stays NaN
        self.stats = {"repairs": self.repair.count, "diverged": diverged}
        estimates = torch.from_numpy(out).to(device=device, dtype=self.dtype)
        return (estimates, torch.from_numpy(var).to(device=device, dtype=self.dtype)) if variances else estimates

    def _run_with_std(self, y, u_prev, u):
        """Estimates and √diag P⁺_t, the filter's own error std of each estimate."""
        estimates, variances = self._run(y, u_prev, u, variances=True)
        return estimates, variances.clamp_min(0.0).sqrt()

    def covariance_schedule(self, data) -> dict[str, torch.Tensor]:
        """Per step t = 1..T, averaged over runs, the √diag of this filter's covariances (float64).

        ``update``: P⁻_t − P⁺_t = K S Kᵀ, the covariance of the update x̂_t − x̂⁻_t; ``prediction``:
        P⁻_t; ``estimate``: P⁺_t (each [steps, n]); ``innovation``: S_t, that of y_t − ŷ_t
        ([steps, m]). All are wide in the start-up, when the prior is wide, and small once P has
        settled. DAOF training sizes its update bound, inputs and rewards from them
        (``daof.train.schedules``). ``gain``: the mean Kalman gain K_t itself ([steps, n, m], not a
        square root). Needs complete data.
        """
        y, u_prev, u = (v.detach().double().cpu().numpy() for v in self.validate(data))
        if np.isnan(y).any():
            raise ValueError(f"{self.name}.covariance_schedule needs data without missing measurements")
        sums = {key: 0.0 for key in ("update", "prediction", "estimate", "innovation", "gain")}
        for r in range(y.shape[0]):
            kf = self._make()
            rows = {key: [] for key in sums}
            for t in range(y.shape[1]):
                kf.P = self.repair(kf.P)
                self._step(kf, y[r, t], u_prev[r, t], u[r, t])
                rows["update"].append(np.diag(kf.P_prior - kf.P_post))
                rows["prediction"].append(np.diag(kf.P_prior))
                rows["estimate"].append(np.diag(kf.P_post))
                rows["innovation"].append(np.diag(kf.S))
                rows["gain"].append(np.array(kf.K, dtype=float))
            sums = {key: sums[key] + np.array(rows[key]) for key in sums}
        means = {key: v / y.shape[0] for key, v in sums.items()}
        schedule = {key: torch.from_numpy(np.sqrt(np.maximum(v, 0.0))) for key, v in means.items() if key != "gain"}
        return {**schedule, "gain": torch.from_numpy(means["gain"])}


class KalmanFilter(_KalmanBase):
    """The exact Kalman filter of a linear-Gaussian system x_{t+1} = A x_t + B u_t + w, y = C x + v."""

    name = "KF"

    def __init__(self, system, dtype=torch.float32, jitter=1e-9):
        if not all(hasattr(system, m) for m in ("A", "B", "C")):
            raise ValueError(f"KalmanFilter needs a linear system with A, B, C; {system.name!r} has none")
        super().__init__(system, dtype, jitter)
        self.A, self.B, self.C = (m.double().cpu().numpy() for m in (system.A, system.B, system.C))

    def _make(self):
        kf = _FilterpyKF(dim_x=self.A.shape[0], dim_z=self.C.shape[0], dim_u=self.B.shape[1])
        kf.F, kf.B, kf.H, kf.Q, kf.R = self.A, self.B, self.C, self.Q, self.R
        kf.x, kf.P = self.x0[:, None].copy(), self.P0.copy()
        return kf

    def _step(self, kf, y, u_prev, u):
        kf.predict(u=u_prev[:, None])  # column u: filterpy's x is a column, B u must be one too
        kf.update(y)

    def _step_missing(self, kf, y, u_prev, u, present):
        kf.predict(u=u_prev[:, None])
        if present.any():  # filterpy only reshapes z when H is not given: pass a column
            kf.update(y[present][:, None], R=self._R_present(present), H=self.C[present])
        else:
            kf.update(None)  # filterpy's "no measurement": the posterior is the prediction


class _FilterpyEKF(ExtendedKalmanFilter):
    """filterpy's EKF with the nonlinear prediction x̂⁻ = f(x̂, u) instead of F x̂ + B u."""

    def __init__(self, model, dim_x, dim_z):
        super().__init__(dim_x, dim_z)
        self.model = model

    def predict_x(self, u=0):
        self.x = self.model.f(self.x[:, 0], u)[:, None]


class EKF(_KalmanBase):
    """Extended Kalman filter: F = ∂f/∂x at x̂_{t-1}, H = ∂g/∂x at x̂⁻_t (``model``: see make_model)."""

    name = "EKF"

    def __init__(self, system, model: str = "auto", dtype=torch.float32, jitter=1e-9):
        super().__init__(system, dtype, jitter)
        self.model = make_model(system, model)
        m = self.model
        self._H = lambda x, u: m.H(x[:, 0], u)
        self._g = lambda x, u: m.g(x[:, 0], u)[:, None]

    def _make(self):
        kf = _FilterpyEKF(self.model, self.system.state_dim, self.system.measurement_dim)
        kf.Q, kf.R = self.Q, self.R
        kf.x, kf.P = self.x0[:, None].copy(), self.P0.copy()
        return kf

    def _step(self, kf, y, u_prev, u):
        kf.F = self.model.F(kf.x[:, 0], u_prev)
        kf.predict(u=u_prev)
        kf.update(y[:, None], self._H, self._g, args=(u,), hx_args=(u,))  # filterpy wants a column z

    def _step_missing(self, kf, y, u_prev, u, present):
        kf.F = self.model.F(kf.x[:, 0], u_prev)
        kf.predict(u=u_prev)
        if not present.any():
            kf.update(None, self._H, self._g)
            return
        m = self.model
        kf.update(
            y[present][:, None],
            lambda x, u: m.H(x[:, 0], u)[present],
            lambda x, u: m.g(x[:, 0], u)[present][:, None],
            R=self._R_present(present),
            args=(u,),
            hx_args=(u,),
        )


class _FilterpyUKF(UnscentedKalmanFilter):
    """filterpy's UKF, passing all sigma points through f in one batched call."""

    def compute_process_sigmas(self, dt, fx=None, **fx_args):
        sigmas = self.points_fn.sigma_points(self.x, self.P)
        self.sigmas_f = (fx or self.fx)(sigmas, dt, **fx_args)


class UKF(_KalmanBase):
    """Unscented Kalman filter with Merwe scaled sigma points (α, β, κ); the sigma-point square
    root goes through the same counted repair as P.

    Defaults α = 1, β = 2, κ = 3 − n: the classic choice, all weights non-negative. On veh2dof
    α = 0.1 and 1e-3 (large negative centre weight) gave the same RMSE within 0.1 %.
    """

    name = "UKF"

    def __init__(self, system, alpha=1.0, beta=2.0, kappa=None, model: str = "auto", dtype=torch.float32, jitter=1e-9):
        super().__init__(system, dtype, jitter)
        n = system.state_dim
        self.model = make_model(system, model)
        self.points = MerweScaledSigmaPoints(
            n, alpha=alpha, beta=beta, kappa=3.0 - n if kappa is None else kappa, sqrt_method=self.repair.sqrt
        )
        m = self.model
        self._f = lambda x, dt, u: m.f(x, u)
        self._g = lambda x, u: m.g(x, u)

    def _make(self):
        s = self.system
        kf = _FilterpyUKF(s.state_dim, s.measurement_dim, s.dt, self._g, self._f, self.points)
        kf.Q, kf.R = self.Q, self.R
        kf.x, kf.P = self.x0.copy(), self.P0.copy()
        return kf

    def _step(self, kf, y, u_prev, u):
        kf.predict(u=u_prev)
        kf.update(y, u=u)

    def _step_missing(self, kf, y, u_prev, u, present):
        kf.predict(u=u_prev)
        if not present.any():
            kf.update(None)
            return
        m = self.model
        kf.update(y[present], R=self._R_present(present), hx=lambda x, u: m.g(x, u)[..., present], u=u)
