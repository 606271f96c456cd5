"""A system's scales from its own simulated data: output range, typical error and the UKF's excess error per state.

Nothing here presumes the answer. Every learned filter, env and study reads the first two of a system,
DAOF-v1's bound the third:

* the **output range** [low, high] per state (the env's action spec, the range learned estimates
  are squashed or clamped onto, the base of the divergence limits): the range of the simulated true
  states widened by ``RANGE_MARGIN`` of its width on each side. An estimate that reaches it is
  counted (``saturated`` in the study), never clamped silently;
* the **error scale** per state, the typical error of a decent filter (the env's reward weights
  W = 1/(n·s²), DSAC-T's exploration, the validation score): where the system has a model, the
  RMSE of a UKF on the simulated data; without one (or where the UKF fails), the RMSE of the best
  linear estimator of x_t from the last ``REGRESSION_WINDOW`` measurements and controls, fitted
  on half of the runs and measured on the other half;
* the UKF's **excess error** per state, √max(RMSE² − mean diag P⁺, 0): the part of its error that
  its own covariance does not account for. A consistent UKF has none; one far from optimal and
  sure of itself (a multimodal posterior) has much. DAOF-v1 widens its residual's bound to it
  (``daof.filters.learned.daof_v1``). Zero where the error scale is not a UKF's.

``data_scales(system)`` computes them once per system (``SCALES_RUNS`` × ``SCALES_STEPS`` steps of
seed ``SCALES_SEED``) and caches them by a fingerprint of the system's simulated data, so that
every object of the same system shares one computation. A system (or a user) may set any of
them instead: ``system.state_low = ...`` overrides the data's value.
"""

from __future__ import annotations

import hashlib
import warnings
from dataclasses import dataclass, replace

import torch

__all__ = ["SystemScales", "data_scales", "RANGE_MARGIN", "SCALES_SEED"]

#: the output range is the simulated states' range widened by this fraction of its width on each side
RANGE_MARGIN = 1.0
#: the simulated data the scales come from (a seed of its own, apart from training, validation and evaluation)
SCALES_SEED = 7_000_003
SCALES_RUNS = 32
SCALES_STEPS = 500
#: measurements (and controls) the linear estimator of a model-free system reads
REGRESSION_WINDOW = 10

_CACHE: dict[str, SystemScales] = {}


@dataclass(frozen=True)
class SystemScales:
    """Per state [n]: the output range ``low``/``high``, the ``error`` scale and the UKF's ``excess`` error;
    ``source`` names the error's origin."""

    low: torch.Tensor
    high: torch.Tensor
    error: torch.Tensor
    source: str
    excess: torch.Tensor

    def to(self, device) -> SystemScales:
        moved = {key: getattr(self, key).to(device) for key in ("low", "high", "error", "excess")}
        return replace(self, **moved)


def data_scales(system) -> SystemScales:
    """The scales of ``system`` from its simulated data (cached per system: module docstring)."""
    key = _fingerprint(system)
    if key not in _CACHE:
        data = system.simulate(SCALES_RUNS, SCALES_STEPS, SCALES_SEED, device=_device(system))
        low, high = output_range(data["state"])
        error, source, excess = error_scale(system, data)
        _CACHE[key] = SystemScales(low.cpu(), high.cpu(), error.cpu(), source, excess.cpu())
    return _CACHE[key]


def output_range(states: torch.Tensor) -> tuple[torch.Tensor, torch.Tensor]:
    """(low, high) per state: the range of ``states [..., n]`` widened by ``RANGE_MARGIN`` of its width per side."""
    flat = states.flatten(0, -2).double()
    low, high = flat.min(0).values, flat.max(0).values
    width = (high - low).clamp_min(1e-6 * high.abs().clamp_min(1.0))  # a constant state still gets a range
    return (low - RANGE_MARGIN * width).float(), (high + RANGE_MARGIN * width).float()


def error_scale(system, data) -> tuple[torch.Tensor, str, torch.Tensor]:
    """(RMSE per state, its source, excess): a UKF's RMSE and excess error where the system has a model and
    the UKF runs, else a linear estimator's RMSE and no excess."""
    if system.has_model:
        from daof.filters.kalman import UKF  # the filters import the systems

        try:
            with warnings.catch_warnings():
                warnings.simplefilter("ignore")
                ukf = UKF(system)  # its _run: ``run`` would also judge divergence, against these scales
                estimates, variances = ukf._run(*ukf.validate(data), variances=True)
            mse = (estimates.double() - data["state"].double()).pow(2).flatten(0, 1).mean(0)
            claimed = variances.double().flatten(0, 1).mean(0)
            if torch.isfinite(mse).all() and (mse > 0).all():
                return mse.sqrt().float(), "UKF", (mse - claimed).clamp_min(0).sqrt().float()
        except (RuntimeError, ValueError, torch.linalg.LinAlgError):
            pass
    return linear_estimator_rmse(data).float(), "linear estimator", torch.zeros(system.state_dim)


def linear_estimator_rmse(data, window: int = REGRESSION_WINDOW) -> torch.Tensor:
    """Held-out RMSE per state of the least-squares linear map from the last ``window`` [y, u] frames to x_t."""
    frames = torch.cat([data["measurement"], data["control"]], -1).double()  # [runs, steps, m + c]
    states = data["state"].double()
    runs, steps = states.shape[:2]
    window = min(window, steps)
    stacked = frames.unfold(1, window, 1).flatten(-2)  # [runs, steps − window + 1, (m + c)·window]
    features = torch.cat([stacked, torch.ones_like(stacked[..., :1])], -1)
    targets = states[:, window - 1 :]
    half = max(runs // 2, 1)
    fit_x, fit_y = features[:half].flatten(0, 1), targets[:half].flatten(0, 1)
    test_x, test_y = (features[half:], targets[half:]) if runs > 1 else (features, targets)
    gram = fit_x.T @ fit_x
    ridge = 1e-8 * gram.diagonal().mean() * torch.eye(len(gram), dtype=gram.dtype, device=gram.device)
    weights = torch.linalg.solve(gram + ridge, fit_x.T @ fit_y)
    error = test_x.flatten(0, 1) @ weights - test_y.flatten(0, 1)
    return error.pow(2).mean(0).sqrt().clamp_min(1e-12)


def _device(system) -> torch.device:
    """Where the system simulates: where its noises live (``StochasticSystem.to``)."""
    return system.prior.mean.device


def _fingerprint(system) -> str:
    """Who the system is: its class, scenario and a short simulation (two systems with equal data share scales)."""
    probe = system.simulate(4, 16, SCALES_SEED, device=_device(system))
    digest = hashlib.sha256()
    for key in ("state", "measurement", "control"):
        digest.update(probe[key].detach().double().cpu().numpy().tobytes())
    kind = type(system)
    return f"{kind.__module__}.{kind.__qualname__}/{system.scenario}/{digest.hexdigest()}"
