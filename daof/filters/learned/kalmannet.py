"""KalmanNet: the model's f and g predict, a recurrent network outputs the Kalman gain.

Revach, Shlezinger, Ni, Escoriza, van Sloun, Eldar, "KalmanNet: Neural Network Aided Kalman
Filtering for Partially Known Dynamics", IEEE Trans. Signal Processing 70, 2022; the authors'
code: github.com/KalmanNet/KalmanNet_TSP (``KNet/KalmanNet_nn.py``, ``Pipelines/Pipeline_EKF.py``).
This is the paper's second architecture, written anew on ``torch.nn.GRUCell``:

    x̂⁻_t = f(x̂_{t−1}, u_{t−1}),   ŷ_t = g(x̂⁻_t, u_t),   x̂_t = x̂⁻_t + K_t (y_t − ŷ_t)

K_t comes from three GRUs (tracking Q, Σ and S) fed by the paper's features, each divided by its
channels' data scale (fitted, stored) and then L2-normalised as in the authors' code:
F1 = y_t − y_{t−1} (observation difference), F2 = y_t − ŷ_t (innovation), F3 = x̂_{t−1} − x̂_{t−2}
(forward evolution difference), F4 = x̂_{t−1} − x̂⁻_{t−1} (forward update difference). The network's
gain is in those units: K_t = D_x K̃_t D_y⁻¹. The hidden states start at vec(I), 0 and vec(I) (the
authors' priors for Q, Σ and S); x̂_0 is the prior mean, and the differences at t = 1 are taken
against x̂_0 and y_0 := g(x̂_0, 0), as the authors start a sequence.

A missing (NaN) measurement channel adds nothing: its innovation and observation difference are 0
and y_{t−1} holds its last present value; a step without any channel only predicts (the
stationary Kalman filter's rule). Estimates are kept in the plausible state range like the other
learned filters'. Only systems with a model (f, g) apply.
"""

from __future__ import annotations

from typing import NamedTuple

import torch
from tensordict.nn import TensorDictModule
from torch import nn

from daof.filters.learned.base import LearnedFilter, register

__all__ = ["STATE_KEYS", "GainNet", "KalmanNet", "KalmanNetState"]


class KalmanNetState(NamedTuple):
    """The recurrent state carried from step t−1 to step t."""

    estimate: torch.Tensor  # x̂_{t−1}
    prev_estimate: torch.Tensor  # x̂_{t−2}
    prev_prior: torch.Tensor  # x̂⁻_{t−1}
    prev_measurement: torch.Tensor  # y_{t−1}, each channel's last present value
    h_q: torch.Tensor  # Q-GRU [n²]
    h_sigma: torch.Tensor  # Σ-GRU [n²]
    h_s: torch.Tensor  # S-GRU [m²]


#: the recurrent state's keys under ``"kalmannet"`` in ``filter_module``'s tensordicts
STATE_KEYS = KalmanNetState._fields


def _fc(d_in: int, d_out: int) -> nn.Sequential:
    return nn.Sequential(nn.Linear(d_in, d_out), nn.ReLU())


class GainNet(nn.Module):
    """The paper's gain network (architecture 2): features F1–F4 and the GRU states -> (K̃_t [n, m], new states)."""

    def __init__(self, n: int, m: int, in_mult: int = 5, out_mult: int = 40):
        super().__init__()
        self.n, self.m = n, m
        self.fc_update = _fc(n, n * in_mult)  # F4 (the authors' FC5)
        self.gru_q = nn.GRUCell(n * in_mult, n * n)
        self.fc_evolution = _fc(n, n * in_mult)  # F3 (FC6)
        self.gru_sigma = nn.GRUCell(n * n + n * in_mult, n * n)
        self.fc_sigma = _fc(n * n, m * m)  # FC1
        self.fc_observation = _fc(2 * m, 2 * m * in_mult)  # F1, F2 (FC7)
        self.gru_s = nn.GRUCell(m * m + 2 * m * in_mult, m * m)
        hidden = (n * n + m * m) * out_mult
        self.fc_gain = nn.Sequential(nn.Linear(n * n + m * m, hidden), nn.ReLU(), nn.Linear(hidden, n * m))  # FC2
        self.fc_back_s = _fc(m * m + n * m, n * n)  # FC3
        self.fc_back_sigma = _fc(2 * n * n, n * n)  # FC4: the Σ-GRU's next state

    def forward(self, f1, f2, f3, f4, h_q, h_sigma, h_s):
        h_q = self.gru_q(self.fc_update(f4), h_q)
        sigma = self.gru_sigma(torch.cat([h_q, self.fc_evolution(f3)], -1), h_sigma)
        h_s = self.gru_s(torch.cat([self.fc_sigma(sigma), self.fc_observation(torch.cat([f1, f2], -1))], -1), h_s)
        gain = self.fc_gain(torch.cat([sigma, h_s], -1))
        h_sigma = self.fc_back_sigma(torch.cat([sigma, self.fc_back_s(torch.cat([h_s, gain], -1))], -1))
        return gain.unflatten(-1, (self.n, self.m)), h_q, h_sigma, h_s


def _unit(x: torch.Tensor) -> torch.Tensor:
    return nn.functional.normalize(x, p=2.0, dim=-1, eps=1e-12)


@register
class KalmanNet(LearnedFilter):
    """KalmanNet (module docstring); ``daof.train.kalmannet`` trains it by MSE with BPTT over sequences."""

    kind = "KalmanNet"
    # a missing channel's innovation is 0: as if it read its predicted measurement
    missing_fills = ("prediction",)

    def __init__(self, config, system=None):
        self._bind(config, system)
        s = self.system
        n, m = s.state_dim, s.measurement_dim
        self.gain_net = GainNet(n, m, config.kalmannet_in_mult, config.kalmannet_out_mult)
        # the channels' scales the features are divided by and the gain is expressed in (``fit_normalizer``)
        self.register_buffer("state_scale", torch.ones(n))
        self.register_buffer("measurement_scale", torch.ones(m))
        self._register_state_range()
        self.register_buffer("prior_mean", s.prior.mean.detach().clone().float())
        self.missing_fill = self.missing_fills[0]

    def _check_system(self) -> None:
        if not self.system.has_model:
            raise ValueError(f"KalmanNet predicts with the model f, g; {self.system.name!r} has none")

    @property
    def architecture(self) -> str:
        """One line for the reports."""
        c = self.config
        return f"3 GRUs (gain network ×{c.kalmannet_in_mult} in, ×{c.kalmannet_out_mult} out), model f, g"

    @torch.no_grad()
    def fit_normalizer(self, runs: int = 64, steps: int = 500, seed: int = 7_000_001) -> None:
        """Per-channel std of the state and the measurement in simulated training data (stored in the checkpoint)."""
        data = self.system.simulate(runs, steps, seed, device=self.state_scale.device)
        self.state_scale.copy_(data["state"].flatten(0, 1).std(0).clamp_min(1e-6))
        self.measurement_scale.copy_(data["measurement"].flatten(0, 1).std(0).clamp_min(1e-6))

    # ----------------------------------------------------------------- the recursion
    def initial_state(self, runs: int, device=None, dtype=torch.float32) -> KalmanNetState:
        """The state before step 1: x̂_0 = prior mean, y_0 = g(x̂_0, 0), the authors' GRU priors."""
        s, n, m = self.system, self.system.state_dim, self.system.measurement_dim
        device = device or self.state_scale.device
        x0 = self.prior_mean.to(device, dtype).expand(runs, n)
        y0 = s.g(x0, torch.zeros(runs, s.control_dim, device=device, dtype=dtype))
        eye_n = torch.eye(n, device=device, dtype=dtype).flatten().expand(runs, n * n)
        eye_m = torch.eye(m, device=device, dtype=dtype).flatten().expand(runs, m * m)
        return KalmanNetState(x0, x0, x0, y0, eye_n, torch.zeros_like(eye_n), eye_m)

    def step(self, state: KalmanNetState, y, u_prev, u) -> tuple[torch.Tensor, KalmanNetState]:
        """(state at t−1, y_t, u_{t−1}, u_t) -> (x̂_t, state at t); NaN in y_t marks a missing channel."""
        s = self.system
        prior = s.f(state.estimate, u_prev)
        present = ~torch.isnan(y)
        y_held = torch.where(present, y, state.prev_measurement)
        innovation = torch.where(present, y - s.g(prior, u), 0.0)
        ys, xs = self.measurement_scale, self.state_scale
        f1 = _unit((y_held - state.prev_measurement) / ys)
        f2 = _unit(innovation / ys)
        f3 = _unit((state.estimate - state.prev_estimate) / xs)
        f4 = _unit((state.estimate - state.prev_prior) / xs)
        gain, h_q, h_sigma, h_s = self.gain_net(f1, f2, f3, f4, state.h_q, state.h_sigma, state.h_s)
        update = xs * (gain @ (innovation / ys).unsqueeze(-1)).squeeze(-1)
        estimate = torch.clamp(prior + update, self.state_low, self.state_high)
        return estimate, KalmanNetState(estimate, state.estimate, prior, y_held, h_q, h_sigma, h_s)

    def filter_sequence(self, y, u_prev, u, state: KalmanNetState | None = None):
        """Steps over [runs, steps] data from ``state`` (default: the initial one) -> (estimates, last state)."""
        if state is None:
            state = self.initial_state(y.shape[0], y.device, y.dtype)
        out = []
        for t in self._steps(*y.shape[:2]):
            estimate, state = self.step(state, y[:, t], u_prev[:, t], u[:, t])
            out.append(estimate)
        return torch.stack(out, 1), state

    @torch.inference_mode()
    def _run(self, y: torch.Tensor, u_prev: torch.Tensor, u: torch.Tensor) -> torch.Tensor:
        """Step by step (the recursion cannot be vectorised over time)."""
        return self.filter_sequence(y, u_prev, u)[0]

    def run_streaming(self, data) -> torch.Tensor:
        """The same as ``run``: it already filters one step at a time."""
        return self.run(data)

    # ----------------------------------------------------------------- uncertainty
    @property
    def feature_width(self) -> int:
        """y_t (held), ν_t, x̂_t, x̂_t − x̂⁻_t, the three GRU states and ρ_t."""
        n, m = self.system.state_dim, self.system.measurement_dim
        return 2 * m + 2 * n + 2 * n * n + m * m + 1

    def uncertainty_features(self, y, u_prev, u):
        """(estimates, features) [runs, steps, ·]: per step what the gain network read and made: the measurement
        (a missing channel held), the innovation ν_t (0 where missing), x̂_t, its update x̂_t − x̂⁻_t, the GRU
        states after the step (the tracked Q, Σ and S) and ρ_t. The estimates are ``run``'s."""
        state = self.initial_state(y.shape[0], y.device, y.dtype)
        estimates, features = [], []
        for t in self._steps(*y.shape[:2]):
            estimate, state = self.step(state, y[:, t], u_prev[:, t], u[:, t])
            estimates.append(estimate)
            features.append(self.step_features(y[:, t], u[:, t], estimate, state))
        estimates = torch.stack(estimates, 1)
        return estimates, torch.cat([torch.stack(features, 1), self._startup_column(y)], -1)

    def step_features(self, measurement, control, estimate, new: KalmanNetState) -> torch.Tensor:
        """The head's features of one step but ρ_t: y_t (a missing channel held), ν_t (0 where missing), x̂_t,
        x̂_t − x̂⁻_t and the three GRU states, from the step's output ``estimate`` and state ``new``."""
        prior = new.prev_prior
        innovation = torch.nan_to_num(measurement - self.system.g(prior, control), nan=0.0)
        parts = [new.prev_measurement, innovation, estimate, estimate - prior, new.h_q, new.h_sigma, new.h_s]
        return torch.cat(parts, -1)

    # ----------------------------------------------------------------- as a TensorDict module
    def forward(self, measurement, prev_control, control, *state):
        estimate, new = self.step(KalmanNetState(*state), measurement, prev_control, control)
        return (estimate, *new)

    def filter_module(self, env=None) -> TensorDictModule:
        """One step as a TensorDictModule.

        Reads ``measurement`` (y_t), ``prev_control`` (u_{t−1}), ``control`` (u_t) and the recurrent
        state ``("kalmannet", k)`` for k in ``STATE_KEYS``; writes ``action`` (x̂_t) and the next state
        ``("next", "kalmannet", k)`` (TorchRL's convention for recurrent modules). ``initial_state``
        gives the state before step 1.
        """
        if env is not None:
            raise ValueError("KalmanNet reads y_t and its own recurrent state, not an env's window")
        state_in = [("kalmannet", k) for k in STATE_KEYS]
        state_out = [("next", "kalmannet", k) for k in STATE_KEYS]
        return TensorDictModule(
            self, in_keys=["measurement", "prev_control", "control", *state_in], out_keys=["action", *state_out]
        )
