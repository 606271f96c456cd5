"""Learned filters as TensorDict modules: DAOF-v2, DAOF-v1 and the supervised SLF.

* DAOF-v2: x̂_t = π(h_t^N)                          (model-free; or, with ``v2_action="increment"``,
  x̂_t = x̂_{t−1} + b_t ⊙ π(h_t^N), the same function class with a bound b_t sized from data)
* DAOF-v1: x̂_t = f(x̂_{t−1}, u_{t−1}) + b_t ⊙ π(h_t^N)  (model predictor + learned update,
  π ∈ [−1, 1]ⁿ, the bound b_t sized from the noise: see ``FilterConfig.correction_bound``; with
  ``reference_gain`` the update is K̄_t ν_t + b_t ⊙ π(h_t^N), a learned residual on the update
  of a UKF's mean gain at step t)
* SLF:     x̂_t = φ(y_{t−N+1..t}, u_{t−N+1..t})     (open loop, trained by regression)

One ``LearnedFilter`` holds the network (window normaliser → MLP → (loc, log σ)) and gives
three views of it: ``stochastic_actor()`` (a TorchRL ``ProbabilisticActor`` with a TanhNormal,
loc not squashed, for DSAC-T), ``exploration_policy()`` (what a collector runs) and
``filter_module()`` (deterministic: the squashed loc, what a user runs). ``run(data)`` filters
simulated data closed loop exactly as the env does, and ``save``/``load`` keep everything in one
checkpoint file.
"""

from __future__ import annotations

from dataclasses import asdict, dataclass
from pathlib import Path

import torch
from tensordict.nn import TensorDictModule, TensorDictSequential
from torch import nn
from torchrl.data import Bounded
from torchrl.modules import MLP, ProbabilisticActor, TanhNormal

from daof.envs.filtering_env import FEEDBACK_KEY
from daof.envs.history import HISTORY_KEY, PADDINGS
from daof.envs.registry import make_system
from daof.envs.system import StochasticSystem
from daof.filters.base import Filter

__all__ = ["FilterConfig", "LearnedFilter", "hold_last_value", "load_filter"]

KINDS = {"DAOF-v1": "correction", "DAOF-v2": "action", "SLF": "action"}
CORRECTION_BOUNDS = ("kalman", "process", "posterior")
V2_ACTIONS = ("estimate", "increment")
#: what a learned filter reads for a missing measurement channel (``LearnedFilter.missing_fill``)
MISSING_FILLS = ("hold", "prediction")
#: what a DSAC-T collector feeds back into h_{t+1}: the sampled action or the deterministic estimate
FEEDBACKS = ("sample", "mean")
#: length of DAOF-v1's bound schedule b_t; later steps use its last entry (the settled value)
SCHEDULE_STEPS = 50
#: window key an SLF reads (measurements and controls only, no fed-back estimates)
OPEN_LOOP_KEY = "measurement_history"


@dataclass
class FilterConfig:
    """Everything needed to rebuild a learned filter (stored in its checkpoint)."""

    kind: str  # "DAOF-v1" | "DAOF-v2" | "SLF"
    system: str
    scenario: str = "nominal"
    window: int = 20
    include_controls: bool = True
    num_cells: int = 256
    depth: int = 3
    #: DAOF-v1: the update is bounded to ± b_t = correction_sigmas · σ_t per state, where σ_t is
    #: "process": sqrt(diag Q) at every step;
    #: "kalman": max(sqrt(diag Q), the std of a UKF's own update at step t), which is wide in the
    #: start-up, when the prior's error has to be pulled in, and settles at sqrt(diag Q) or above;
    #: "posterior": a UKF's estimate error std sqrt(diag P⁺_t), the size of what is left to correct
    #: after a Kalman update (meant for ``reference_gain``)
    correction_sigmas: float = 4.0
    correction_bound: str = "kalman"
    #: DAOF-v1: the update is K̄_t ν_t + b_t ⊙ π(h_t), with K̄_t a UKF's mean Kalman gain at step t
    #: (``set_schedules``) and ν_t the innovation of the prediction. π(h_t) is still a function of the
    #: window alone; what it learns is the residual of a gain-scheduled Kalman update, so in the
    #: start-up, where that update is 5× the error left after it (on ``linear``), the action no longer
    #: has to place the large update to within a few percent of its range (docs/linear_check.md)
    reference_gain: bool = False
    #: closed-loop filters also read the start-up feature ρ_t (see ``startup_feature``)
    startup_input: bool = True
    #: DAOF-v1 also reads its newest innovation ν_t = y_t − g(f(x̂_{t−1}, u_{t−1}), u_t), which it
    #: computes from h_t^N and the model it has anyway (``LearnedFilter.innovation``), divided by
    #: a UKF's innovation std √diag S_t at step t: then the optimal unit action ≈ ν_t/√S_t / k at
    #: every step, start-up included (a Kalman update is K_t ν_t and b_t ∝ std of K_t ν_t)
    innovation_input: bool = True
    #: the policy's GELU: "tanh" (its tanh approximation) or "none" (exact, erf). Same function to
    #: ~1e-3; the exact one costs ~5x more at batch 1 on CPU (3 of them per estimate), see
    #: docs/benchmarks/learned.md. Checkpoints saved before the field existed are exact.
    gelu_approximate: str = "tanh"
    #: closed-loop filters: what fills the window in front of the first frame after a reset,
    #: "same" (copies of it) or "zeros" (``daof.envs.history``)
    window_padding: str = "same"
    #: DAOF-v2's action: "estimate" (the paper's x̂_t = π(h_t), squashed onto the plausible state
    #: range) or "increment" (x̂_t = x̂_{t−1} + b_t ⊙ π(h_t), π ∈ [−1, 1]ⁿ; x̂_{t−1} is in h_t, so the
    #: filters are the same but the action is sized like the error, not like the state's range).
    #: b_t = correction_sigmas · max(σ_Δ, ρ_t · σ_0) from simulated training data: σ_Δ the std of
    #: the state's change per step, σ_0 the std of the prior mean's error at t = 1. No model used.
    v2_action: str = "estimate"
    #: SLF, DAOF-v2: each frame also carries one 0/1 flag per measurement channel, 1 where the
    #: channel is missing (its value then holds the last present one). Meant for filters trained
    #: through random gaps (``dropout`` in the recipes' configs, ``daof.envs.gaps``); docs/missing_data.md
    missing_mask: bool = False

    def __post_init__(self):
        if self.kind not in KINDS:
            raise ValueError(f"unknown filter kind {self.kind!r}; valid: {sorted(KINDS)}")
        if not isinstance(self.window, int) or self.window < 1:
            raise ValueError(f"window must be an integer N >= 1, got {self.window!r}")
        if self.window_padding not in PADDINGS:
            raise ValueError(f"window_padding must be one of {PADDINGS}, got {self.window_padding!r}")
        if self.gelu_approximate not in ("tanh", "none"):
            raise ValueError(f"gelu_approximate must be 'tanh' or 'none', got {self.gelu_approximate!r}")
        if self.v2_action not in V2_ACTIONS:
            raise ValueError(f"v2_action must be one of {V2_ACTIONS}, got {self.v2_action!r}")
        if self.correction_bound not in CORRECTION_BOUNDS:
            raise ValueError(f"correction_bound must be one of {CORRECTION_BOUNDS}, got {self.correction_bound!r}")
        if self.reference_gain and self.kind != "DAOF-v1":
            raise ValueError("reference_gain is DAOF-v1's: it needs the model's innovation")
        if self.missing_mask and self.kind == "DAOF-v1":
            raise ValueError("missing_mask is for the model-free filters: DAOF-v1 reads a gap as its prediction")


def schedule_row(table: torch.Tensor, step) -> torch.Tensor:
    """Row t of a per-step table [S, k] for t ≥ 1 (an int, a [..., 1] integer tensor, or None: settled).

    Steps after S use the last row.
    """
    if step is None:
        return table[-1]
    if isinstance(step, int):
        return table[min(max(step, 1), len(table)) - 1]
    return table[step.squeeze(-1).clamp(1, len(table)) - 1]


def startup_feature(step) -> torch.Tensor:
    """ρ_t = max(0, 1 − (t − 1)/SCHEDULE_STEPS) for t ≥ 1 ([..., 1] integer tensor -> float [..., 1]).

    1 at the first measurement, 0 once the filter has settled (an int t gives a float). After a
    reset the window is N copies of the first frame and, past t = N, says nothing of t; the
    start-up (where the prior's error is pulled in) needs other updates than the settled filter,
    so the networks read ρ_t.
    """
    if isinstance(step, int):  # the streaming filter's hot path
        return min(max(1.0 - (step - 1) / SCHEDULE_STEPS, 0.0), 1.0)
    # in float64 like the int path, then rounded: ``run`` and an env rollout agree to the bit
    return (1.0 - (step.double() - 1.0) / SCHEDULE_STEPS).clamp(0.0, 1.0).float()


class PolicyNet(nn.Module):
    """Raw window (+ ν_t, ρ_t) -> per-channel normalisation -> MLP -> (loc, σ) of the pre-squash Gaussian.

    σ = exp(clamp(log σ, −20, 0.5)) as in DSAC-T. The normalisation is buffers fitted on training
    data, so it travels with the weights. ``innovation`` (a function of the window, or None) adds
    the newest innovation ν_t divided by its std at step t (``innovation_scale``, one row per
    step); ``startup_input`` adds ρ_t (``startup_feature``). The MLP's input is [window, ν_t, ρ_t].
    """

    def __init__(
        self,
        in_features: int,
        out_dim: int,
        num_cells: int,
        depth: int,
        startup_input: bool = False,
        innovation=None,
        innovation_dim: int = 0,
        gelu_approximate: str = "none",
    ):
        super().__init__()
        self.register_buffer("input_loc", torch.zeros(in_features))
        self.register_buffer("input_scale", torch.ones(in_features))
        self.innovation = innovation
        self.innovation_dim = innovation_dim if innovation else 0
        self.register_buffer("innovation_scale", torch.ones(SCHEDULE_STEPS, self.innovation_dim))
        self.startup_input = startup_input
        #: width of ``features``: the MLP's input
        self.feature_dim = in_features + self.innovation_dim + int(startup_input)
        self.gelu_approximate = gelu_approximate
        self.mlp = MLP(
            in_features=self.feature_dim,
            out_features=2 * out_dim,
            depth=depth,
            num_cells=num_cells,
            activation_class=nn.GELU,
            activation_kwargs={"approximate": gelu_approximate},
        )

    def normalize(self, window: torch.Tensor) -> torch.Tensor:
        return (window - self.input_loc) / self.input_scale

    def features(self, window: torch.Tensor, step=None) -> torch.Tensor:
        """The MLP's input: the normalised window, then ν_t and ρ_t where used."""
        parts = [self.normalize(window)]
        if self.innovation is not None:
            parts.append(self.innovation(window) / schedule_row(self.innovation_scale, step))
        if self.startup_input:
            parts.append(startup_feature(step))
        return torch.cat(parts, -1) if len(parts) > 1 else parts[0]

    def forward(self, window: torch.Tensor, step=None):
        loc, log_std = self.mlp(self.features(window, step)).chunk(2, -1)
        return loc, log_std.clamp(-20.0, 0.5).exp()


def increment_scale(states: torch.Tensor, system: StochasticSystem) -> torch.Tensor:
    """σ_t = max(σ_Δ, ρ_t · σ_0) per step t = 1..SCHEDULE_STEPS, [S, n], from [runs, steps, n] true states.

    σ_Δ: std of x_t − x_{t−1} over every run and step; σ_0: std of x_1 − x̂_0 (the prior mean's error
    at the first estimate); ρ_t the start-up feature. Data only: no model of the dynamics.
    """
    step_change = (states[:, 1:] - states[:, :-1]).flatten(0, 1).std(0)
    first_error = (states[:, 0] - system.prior.mean.to(states)).pow(2).mean(0).sqrt()
    rho = startup_feature(torch.arange(1, SCHEDULE_STEPS + 1, device=states.device).unsqueeze(-1))
    return torch.maximum(step_change, rho * first_error).float()


def sliding_windows(frames: torch.Tensor, window: int) -> torch.Tensor:
    """[runs, steps, F] frames -> [runs, steps, N·F] windows, oldest first, padded like CatFrames.

    The first frame is repeated N−1 times in front (``padding="same"``).
    """
    pad = frames[:, :1].expand(-1, window - 1, -1)
    padded = torch.cat([pad, frames], 1)  # [runs, steps + N − 1, F]
    return padded.unfold(1, window, 1).transpose(-1, -2).flatten(-2)


def hold_last_value(y: torch.Tensor, fill: torch.Tensor) -> torch.Tensor:
    """[runs, steps, m] with NaN gaps -> each NaN replaced by its channel's last present value.

    Leading gaps (nothing seen yet) take ``fill`` [m]. Learned filters are trained on complete data;
    holding the last value is their treatment of sensor dropouts (docs/missing_data.md).
    """
    missing = torch.isnan(y)
    if not missing.any():
        return y
    steps = torch.arange(y.shape[1], device=y.device).view(1, -1, 1).expand_as(y)
    last = torch.where(missing, -1, steps).cummax(1).values  # index of the last present value, −1 if none
    held = torch.gather(y, 1, last.clamp_min(0))
    return torch.where(last < 0, fill.to(y), held)


class LearnedFilter(nn.Module, Filter):
    """A learned filter on one system with one window length (see module docstring)."""

    def __init__(self, config: FilterConfig, system: StochasticSystem | None = None):
        nn.Module.__init__(self)
        Filter.__init__(self, system or make_system(config.system, config.scenario))
        self.config = config
        self.name = config.kind
        if config.kind == "DAOF-v1" and not self.system.has_model:
            raise ValueError(f"DAOF-v1 needs a model predictor; {config.system} offers none (use DAOF-v2)")
        s = self.system
        self.uses_controls = config.include_controls and s.control_dim > 0
        self.closed_loop = config.kind != "SLF"
        n = s.state_dim
        self.startup_input = config.startup_input and self.closed_loop
        # ν_t needs u_t and u_{t−1} in the frame when the system has controls
        self.innovation_input = (
            config.innovation_input and config.kind == "DAOF-v1" and (self.uses_controls or s.control_dim == 0)
        )
        self.policy = PolicyNet(
            config.window * self.frame_dim,
            n,
            config.num_cells,
            config.depth,
            self.startup_input,
            self.innovation if self.innovation_input else None,
            s.measurement_dim,
            config.gelu_approximate,
        )
        if self.acts_by_update:
            # the actor's action is the update in units of its bound b_t; DAOF-v1's b_t starts as
            # the process-noise bound and ``set_schedules`` widens it for "kalman"; an incremental
            # DAOF-v2's is fitted on data with the normaliser
            low, high = -torch.ones(n), torch.ones(n)
            if config.kind == "DAOF-v1":
                floor = config.correction_sigmas * s.process_noise.covariance.diagonal().sqrt()
            else:
                floor = config.correction_sigmas * s.error_scale
            self.register_buffer("correction_scale", floor.float().expand(SCHEDULE_STEPS, n).clone())
        else:
            low, high = s.state_low.clone(), s.state_high.clone()
        if config.reference_gain:  # only then: checkpoints saved before the option existed load as they are
            self.register_buffer("reference_gain", torch.zeros(SCHEDULE_STEPS, n, s.measurement_dim))
        self.register_buffer("low", low.float())
        self.register_buffer("high", high.float())
        # every estimate stays in the system's plausible state range (the env's action spec)
        self.register_buffer("state_low", s.state_low.clone().float())
        self.register_buffer("state_high", s.state_high.clone().float())
        # reading the prediction beats holding the last value on every gap pattern measured
        # (benchmarks/missing_data.py, docs/missing_data.md); the others have no model to predict with
        self.missing_fill = "prediction" if config.kind == "DAOF-v1" else "hold"

    # ----------------------------------------------------------------- missing measurements
    @property
    def missing_fill(self) -> str:
        """What a missing (NaN) measurement channel reads as (docs/missing_data.md).

        "hold": its last present value (``hold_last_value``); "prediction" (DAOF-v1 only): the
        predicted measurement g(f(x̂_{t−1}, u_{t−1}), u_t), so the channel's innovation is 0, as a
        Kalman filter skips the update of a missing channel.
        """
        return self._missing_fill

    @missing_fill.setter
    def missing_fill(self, value: str) -> None:
        if value not in MISSING_FILLS:
            raise ValueError(f"missing_fill must be one of {MISSING_FILLS}, got {value!r}")
        if value == "prediction" and self.config.kind != "DAOF-v1":
            raise ValueError(f"missing_fill='prediction' needs a model predictor: DAOF-v1 only, not {self.config.kind}")
        self._missing_fill = value

    # ----------------------------------------------------------------- shapes
    @property
    def acts_by_update(self) -> bool:
        """Whether the action is a bounded update of a prediction (DAOF-v1, incremental DAOF-v2)."""
        return self.config.kind == "DAOF-v1" or (self.config.kind == "DAOF-v2" and self.config.v2_action == "increment")

    @property
    def frame_dim(self) -> int:
        s = self.system
        dim = s.measurement_dim * (2 if self.config.missing_mask else 1) + (
            2 * s.control_dim if self.uses_controls else 0
        )
        return dim + (s.state_dim if self.closed_loop else 0)

    @property
    def input_key(self) -> str:
        return HISTORY_KEY if self.closed_loop else OPEN_LOOP_KEY

    @property
    def policy_in_keys(self) -> list[str]:
        """What the policy network reads: the window, and t where it uses the start-up feature."""
        return [self.input_key, "step"] if self.startup_input else [self.input_key]

    @property
    def action_key(self) -> str:
        return "correction" if self.acts_by_update else KINDS[self.config.kind]

    @property
    def action_scale(self) -> torch.Tensor:
        """What one unit of the actor's action is in state units, once the filter has settled.

        DAOF-v1's (and an incremental DAOF-v2's) action is its update in units of the bound b_t
        (the settled b is the schedule's last entry); DAOF-v2 and SLF output the estimate itself.
        DSAC-T's entropy target uses it.
        """
        if self.acts_by_update:
            return self.correction_scale[-1]
        return torch.ones_like(self.low)

    def innovation(self, window: torch.Tensor, prediction: torch.Tensor | None = None) -> torch.Tensor:
        """ν_t = y_t − g(x̂⁻_t, u_t), x̂⁻_t = f(x̂_{t−1}, u_{t−1}), from the newest frame of h_t^N.

        ``prediction`` is x̂⁻_t where the caller has it already. Frames are [x̂_{t−1}, y_t, u_t, u_{t−1}].
        """
        s = self.system
        n, m, c = s.state_dim, s.measurement_dim, s.control_dim
        frame = window[..., -self.frame_dim :]
        u, u_prev = frame[..., n + m : n + m + c], frame[..., n + m + c : n + m + 2 * c]
        if prediction is None:
            prediction = s.f(frame[..., :n], u_prev)
        return frame[..., n : n + m] - s.g(prediction, u)

    # ----------------------------------------------------------------- normalisation
    @torch.no_grad()
    def fit_normalizer(self, runs: int = 64, steps: int = 500, seed: int = 7_000_001) -> None:
        """Per-channel input loc/scale from simulated training data (stored in the checkpoint)."""
        data = self.system.simulate(runs, steps, seed, device=self.low.device)
        parts = []
        if self.closed_loop:
            parts.append(data["state"])
        parts.append(data["measurement"])
        if self.uses_controls:
            parts += [data["control"], data["prev_control"]]
        flat = torch.cat(parts, -1).flatten(0, 1)
        loc, scale = flat.mean(0), flat.std(0).clamp_min(1e-6)
        if self.config.missing_mask:  # the 0/1 missing flags enter as they are
            m = self.system.measurement_dim
            loc, scale = torch.cat([loc, loc.new_zeros(m)]), torch.cat([scale, scale.new_ones(m)])
        self.policy.input_loc.copy_(loc.repeat(self.config.window))
        self.policy.input_scale.copy_(scale.repeat(self.config.window))
        if self.acts_by_update and self.config.kind == "DAOF-v2":
            self.correction_scale.copy_(self.config.correction_sigmas * increment_scale(data["state"], self.system))

    @torch.no_grad()
    def set_schedules(self, schedule: dict[str, torch.Tensor]) -> None:
        """DAOF-v1's per-step tables from a Kalman-type filter's ``covariance_schedule`` (rows t = 1..S).

        The update bound b_t = correction_sigmas · max(sqrt(diag Q), schedule["update"]_t) (for
        the "kalman" bound; schedule["estimate"]_t for "posterior"), the innovation scale √diag S_t
        = schedule["innovation"]_t (with the innovation input) and, with ``reference_gain``, the gain
        K̄_t = schedule["gain"]_t. A shorter schedule is held at its last row. No-op for the other
        kinds. Stored in the checkpoint.
        """
        if self.config.kind != "DAOF-v1":
            return

        def rows(values: torch.Tensor) -> torch.Tensor:
            values = values.to(self.correction_scale)[:SCHEDULE_STEPS]
            return torch.cat([values, values[-1:].expand(SCHEDULE_STEPS - len(values), *values.shape[1:])])

        sigmas = self.config.correction_sigmas
        if self.config.correction_bound == "kalman":
            floor = self.system.process_noise.covariance.diagonal().sqrt().to(self.correction_scale)
            self.correction_scale.copy_(sigmas * torch.maximum(rows(schedule["update"]), floor))
        elif self.config.correction_bound == "posterior":
            self.correction_scale.copy_(sigmas * rows(schedule["estimate"]).clamp_min(1e-12))
        if self.config.reference_gain:
            self.reference_gain.copy_(rows(schedule["gain"]))
        if self.innovation_input:
            self.policy.innovation_scale.copy_(rows(schedule["innovation"]).clamp_min(1e-12))

    def reference_update(self, window: torch.Tensor, prediction: torch.Tensor, step, nu=None) -> torch.Tensor | None:
        """K̄_t ν_t, the update of the reference gain (``reference_gain``), or None without it."""
        if not self.config.reference_gain:
            return None
        if nu is None:
            nu = self.innovation(window, prediction)
        return (schedule_row(self.reference_gain, step) @ nu.unsqueeze(-1)).squeeze(-1)

    def bound_at(self, step) -> torch.Tensor:
        """DAOF-v1's bound b_t for ``step`` t ≥ 1 (an int, a [..., 1] integer tensor, or None: settled)."""
        return schedule_row(self.correction_scale, step)

    # ----------------------------------------------------------------- networks
    def predict(self, prev_estimate: torch.Tensor, prev_control: torch.Tensor) -> torch.Tensor:
        """DAOF-v1's model predictor f(x̂_{t−1}, u_{t−1}); an incremental DAOF-v2 holds x̂_{t−1}."""
        if self.config.kind != "DAOF-v1":
            return prev_estimate
        return self.system.f(prev_estimate, prev_control)

    def estimate(self, window, prev_estimate=None, prev_control=None, step=None) -> torch.Tensor:
        """Deterministic estimate x̂_t (the squashed loc; DAOF-v1 scales it by b_t and adds f)."""
        return self._fast_estimate(self._inference_layers(), window, prev_estimate, prev_control, step)

    forward = estimate

    def stochastic_actor(self) -> ProbabilisticActor:
        """TanhNormal actor over ``action_key`` (the estimate, or the v1 correction) for DSAC-T."""
        module = TensorDictModule(self.policy, in_keys=self.policy_in_keys, out_keys=["loc", "scale"])
        spec = Bounded(self.low, self.high, shape=self.low.shape, device=self.low.device)
        return ProbabilisticActor(
            module,
            in_keys=["loc", "scale"],
            out_keys=[self.action_key],
            spec=spec,
            distribution_class=TanhNormal,
            distribution_kwargs={"low": self.low, "high": self.high, "tanh_loc": False},
            return_log_prob=False,
        )

    def _add_prediction(self, correction, prev_estimate, prev_control, step, window=None, prediction=None, nu=None):
        """x̂_t = f(x̂_{t−1}, u_{t−1}) (+ K̄_t ν_t) + b_t ⊙ correction, kept in the plausible state range.

        Without the clamp an untrained update can push the predictor outside the region where
        the vehicle model is stable, and the estimate then runs away for the rest of the episode.
        ``window`` (h_t) or ``nu`` (ν_t) is needed with ``reference_gain`` only.
        """
        if prediction is None:
            prediction = self.predict(prev_estimate, prev_control)
        estimate = torch.addcmul(prediction, self.bound_at(step), correction)
        reference = self.reference_update(window, prediction, step, nu)
        if reference is not None:
            estimate = estimate + reference
        return torch.clamp(estimate, self.state_low, self.state_high)

    def squash_affine(self) -> tuple[torch.Tensor, torch.Tensor]:
        """(mid, half) of the actor's bounds: a = mid + half · tanh(u)."""
        return (self.high + self.low) / 2, (self.high - self.low) / 2

    def squash(self, loc: torch.Tensor) -> torch.Tensor:
        """The deterministic action of a pre-squash loc: mid + half · tanh(loc) on the actor's bounds."""
        return torch.addcmul(*self.squash_affine(), torch.tanh(loc))

    def exploration_policy(self, feedback: str = "sample") -> TensorDictSequential:
        """What a collector runs: sample from π and, for a filter that acts by updates, add the prediction.

        ``feedback="mean"`` also writes ``FEEDBACK_KEY``: the deterministic estimate (the squashed loc,
        through the same prediction), which the env then feeds back instead of the sampled one.
        """
        if feedback not in FEEDBACKS:
            raise ValueError(f"feedback must be one of {FEEDBACKS}, got {feedback!r}")
        by_update = ["prev_estimate", "prev_control", "step", self.input_key]

        def plus_prediction(key: str, out_key: str) -> list[TensorDictModule]:
            if not self.acts_by_update:
                return []
            return [TensorDictModule(self._add_prediction, in_keys=[key, *by_update], out_keys=[out_key])]

        modules = [self.stochastic_actor(), *plus_prediction("correction", "action")]
        if feedback == "mean":
            modules.append(TensorDictModule(self.squash, in_keys=["loc"], out_keys=[FEEDBACK_KEY]))
            modules += plus_prediction(FEEDBACK_KEY, FEEDBACK_KEY)
        return TensorDictSequential(*modules)

    def filter_module(self) -> TensorDictModule:
        """Deterministic filter: reads h_t (+ x̂_{t−1}, u_{t−1} for an update, t where used), writes ``action``."""
        if self.acts_by_update:
            in_keys = [self.input_key, "prev_estimate", "prev_control", "step"]
            return TensorDictModule(self, in_keys=in_keys, out_keys=["action"])
        return TensorDictModule(self, in_keys=dict(zip(["window", "step"], self.policy_in_keys)), out_keys=["action"])

    # ----------------------------------------------------------------- offline filtering
    def open_loop_frames(self, y, u, u_prev) -> torch.Tensor:
        """Per-step frames without the fed-back estimate: [y_t, (u_t, u_{t−1})].

        A missing measurement (NaN) holds the channel's last value; before the first value of a
        channel it is the channel's training mean (see ``hold_last_value``). With ``missing_mask``
        the frame ends with the channels' missing flags: [y_t, (u_t, u_{t−1}), 1{y_t missing}].
        """
        start = self.system.state_dim if self.closed_loop else 0  # where y sits in a frame
        y_mean = self.policy.input_loc[start : start + self.system.measurement_dim]
        parts = [hold_last_value(y, y_mean), *([u, u_prev] if self.uses_controls else [])]
        if self.config.missing_mask:
            parts.append(torch.isnan(y).to(parts[0].dtype))
        return torch.cat(parts, -1)

    def _inference_layers(self) -> list[tuple[torch.Tensor, ...]]:
        """The policy's (weight, bias) per layer, for the deterministic filter only.

        The input normalisation is folded into the first layer and only the loc rows of the last
        are kept (with the squash onto the action bounds, None for DAOF-v1's ±1), so one filter
        step costs four ``linear`` calls and three GELUs. The first entry
        also holds the weight columns of ν_t and of ρ_t (each None where unused); they enter as a
        per-step bias. Rebuilt on every ``run`` (cheap), so it always
        matches the current weights.
        """
        policy = self.policy
        linears = [m for m in policy.mlp if isinstance(m, nn.Linear)]
        first, last, n = linears[0], linears[-1], self.system.state_dim
        width, m = policy.input_loc.numel(), policy.innovation_dim
        w0 = first.weight[:, :width] / policy.input_scale
        w_nu = first.weight[:, width : width + m] if m else None
        w_rho = first.weight[:, width + m] if self.startup_input else None
        layers = [(w0, first.bias - w0 @ policy.input_loc, w_nu, w_rho)]
        layers += [(m.weight, m.bias) for m in linears[1:-1]]
        # a = mid + half · tanh(u) maps onto the action's bounds; DAOF-v1's are ±1 (a = tanh(u))
        squash = None if self.acts_by_update else self.squash_affine()
        return layers + [(last.weight[:n], last.bias[:n], squash)]

    def _fast_estimate(self, layers, window, prev_estimate=None, prev_control=None, step=None) -> torch.Tensor:
        """``estimate`` on pre-folded layers (``_run`` folds them once per trajectory)."""
        (w0, b0, w_nu, w_rho), *hidden = layers[:-1]
        by_update = self.acts_by_update
        prediction = self.predict(prev_estimate, prev_control) if by_update else None
        # ν_t and ρ_t times their weight columns are a per-step bias of the first layer
        nu = self.innovation(window, prediction) if w_nu is not None or self.config.reference_gain else None
        if w_nu is not None:
            b0 = b0 + (nu / schedule_row(self.policy.innovation_scale, step)) @ w_nu.T
        rho = startup_feature(step) if w_rho is not None and step is not None else 0.0
        if not isinstance(rho, float) or rho > 0.0:  # a settled streaming step skips it (+0 is exact)
            b0 = b0 + rho * w_rho
        gelu = self.policy.gelu_approximate
        h = nn.functional.gelu(nn.functional.linear(window, w0, b0), approximate=gelu)
        for weight, bias in hidden:
            h = nn.functional.gelu(nn.functional.linear(h, weight, bias), approximate=gelu)
        weight, bias, squash = layers[-1]
        out = torch.tanh(nn.functional.linear(h, weight, bias))  # tanh of the pre-squash loc
        if squash is not None:
            out = torch.addcmul(squash[0], squash[1], out)
        if by_update:
            out = self._add_prediction(out, prev_estimate, prev_control, step, window, prediction, nu)
        return out

    @torch.inference_mode()
    def _run(self, y: torch.Tensor, u_prev: torch.Tensor, u: torch.Tensor) -> torch.Tensor:
        """Filter [runs, steps] data -> [runs, steps, n] (``Filter.run`` validates the input).

        Closed-loop filters build the window exactly as the env's CatTensors + CatFrames do (the
        first frame behind the configured padding after the reset), so ``run`` and an env rollout
        give the same estimates; the open-loop SLF filters every step at once.
        """
        if not self.closed_loop:
            return self.estimate(sliding_windows(self.open_loop_frames(y, u, u_prev), self.config.window))
        return self._stream(y, u_prev, u)

    def _stream(self, y: torch.Tensor, u_prev: torch.Tensor, u: torch.Tensor) -> torch.Tensor:
        """Step-by-step filtering (closed loop; for the SLF the streaming form of its windows)."""
        out = [estimate for _, _, estimate in self.stream_steps(y, u_prev, u)]
        return torch.stack(out, 1) if out else torch.empty(y.shape[0], 0, self.system.state_dim, device=y.device)

    def stream_steps(self, y: torch.Tensor, u_prev: torch.Tensor, u: torch.Tensor):
        """Yield (h_t, x̂_{t−1}, x̂_t) for t = 1..T of step-by-step filtering of validated [runs, steps] data."""
        layers = self._inference_layers()
        measured = self.open_loop_frames(y, u, u_prev)  # [runs, steps, F − n]: y_t first
        gaps = torch.isnan(y) if self.missing_fill == "prediction" else None
        gappy = gaps.any(-1).any(0).tolist() if gaps is not None else None
        prev = self.system.prior.mean.to(y.device).expand(y.shape[0], -1).clone()
        width = self.frame_dim
        window = None
        for t in range(y.shape[1]):
            present = measured[:, t]
            if gappy is not None and gappy[t]:  # a missing channel reads as its prediction: ν_t = 0 there
                m = self.system.measurement_dim
                predicted = self.system.g(self.predict(prev, u_prev[:, t]), u[:, t])
                present = torch.cat([torch.where(gaps[:, t], predicted, present[:, :m]), present[:, m:]], -1)
            frame = torch.cat([prev, present], -1) if self.closed_loop else present
            # slide the window by one frame; right after the reset it is frame 1 behind N − 1 pads
            window = self._first_window(frame) if window is None else torch.cat([window[:, width:], frame], -1)
            estimate = self._fast_estimate(layers, window, prev, u_prev[:, t], t + 1)
            yield window, prev, estimate
            prev = estimate

    def _first_window(self, frame: torch.Tensor) -> torch.Tensor:
        """h_1: the first frame behind N − 1 padding frames, as the env's ``CatFrames`` pads it."""
        N = self.config.window
        if self.config.window_padding == "zeros" and self.closed_loop:
            return torch.cat([frame.new_zeros(frame.shape[0], (N - 1) * frame.shape[-1]), frame], -1)
        return frame.repeat(1, N)

    def run_streaming(self, data) -> torch.Tensor:
        """``run`` one step at a time, as a deployed filter would (the SLF's cost is timed this way)."""
        y, u_prev, u = self.validate(data)
        with torch.inference_mode():
            return self._stream(y, u_prev, u)

    # ----------------------------------------------------------------- checkpoint
    def save(self, path: str | Path, extra: dict | None = None) -> None:
        """One file: config, weights and normalisation (plus ``extra`` metadata)."""
        path = Path(path)
        path.parent.mkdir(parents=True, exist_ok=True)
        torch.save({"config": asdict(self.config), "state_dict": self.state_dict(), "extra": extra or {}}, path)


def load_filter(path: str | Path, system: StochasticSystem | None = None, expect: dict | None = None):
    """Load a ``LearnedFilter`` saved by ``save``; ``expect`` checks config fields (system, window…)."""
    path = Path(path)
    if not path.is_file():
        raise FileNotFoundError(f"no filter checkpoint at {path}")
    blob = torch.load(path, map_location="cpu", weights_only=False)
    if not isinstance(blob, dict) or "config" not in blob:
        raise ValueError(f"{path} is not a learned-filter checkpoint")
    config = FilterConfig(**{"gelu_approximate": "none", **blob["config"]})  # older checkpoints: exact GELU
    for key, value in (expect or {}).items():
        if getattr(config, key) != value:
            raise ValueError(f"checkpoint {path} has {key}={getattr(config, key)!r}, expected {value!r}")
    if system is not None and system.name != config.system:
        raise ValueError(f"checkpoint {path} is a filter for {config.system!r}, not for {system.name!r}")
    module = LearnedFilter(config, system)
    try:
        module.load_state_dict(blob["state_dict"])
    except RuntimeError as error:  # saved by another version of the filter (other inputs or sizes)
        first = str(error).strip().splitlines()[-1].strip()
        raise ValueError(f"checkpoint {path} does not fit this filter's layout ({first})") from None
    module.extra = blob.get("extra", {})
    module.path = path
    return module.eval()
