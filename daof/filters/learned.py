"""Learned filters as TensorDict modules: DAOF-v2, DAOF-v1 and the supervised SLF.

* DAOF-v2: x̂_t = π(h_t^N)                          (model-free)
* DAOF-v1: x̂_t = f(x̂_{t−1}, u_{t−1}) + π(h_t^N)     (model predictor + learned update)
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

from daof.filters.base import Filter
from envs.history import HISTORY_KEY
from envs.registry import make_system
from envs.system import StochasticSystem

__all__ = ["FilterConfig", "LearnedFilter", "hold_last_value", "load_filter"]

KINDS = {"DAOF-v1": "correction", "DAOF-v2": "action", "SLF": "action"}
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
    #: DAOF-v1: the update π(h) is bounded to ± correction_sigmas · sqrt(diag Q)
    correction_sigmas: float = 4.0

    def __post_init__(self):
        if self.kind not in KINDS:
            raise ValueError(f"unknown filter kind {self.kind!r}; valid: {sorted(KINDS)}")
        if not isinstance(self.window, int) or self.window < 1:
            raise ValueError(f"window must be an integer N >= 1, got {self.window!r}")


class PolicyNet(nn.Module):
    """Raw window -> per-channel normalisation -> MLP -> (loc, σ) of the pre-squash Gaussian.

    σ = exp(clamp(log σ, −20, 0.5)) as in DSAC-T. The normalisation is a pair of buffers fitted
    on training data, so it travels with the weights.
    """

    def __init__(self, in_features: int, out_dim: int, num_cells: int, depth: int):
        super().__init__()
        self.register_buffer("input_loc", torch.zeros(in_features))
        self.register_buffer("input_scale", torch.ones(in_features))
        self.mlp = MLP(
            in_features=in_features,
            out_features=2 * out_dim,
            depth=depth,
            num_cells=num_cells,
            activation_class=nn.GELU,
        )

    def normalize(self, window: torch.Tensor) -> torch.Tensor:
        return (window - self.input_loc) / self.input_scale

    def forward(self, window: torch.Tensor):
        loc, log_std = self.mlp(self.normalize(window)).chunk(2, -1)
        return loc, log_std.clamp(-20.0, 0.5).exp()


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
        self.policy = PolicyNet(config.window * self.frame_dim, n, config.num_cells, config.depth)
        if config.kind == "DAOF-v1":
            half = config.correction_sigmas * s.process_noise.covariance.diagonal().sqrt()
            low, high = -half, half
        else:
            low, high = s.state_low.clone(), s.state_high.clone()
        self.register_buffer("low", low.float())
        self.register_buffer("high", high.float())
        # every estimate stays in the system's plausible state range (the env's action spec)
        self.register_buffer("state_low", s.state_low.clone().float())
        self.register_buffer("state_high", s.state_high.clone().float())

    # ----------------------------------------------------------------- shapes
    @property
    def frame_dim(self) -> int:
        s = self.system
        dim = s.measurement_dim + (2 * s.control_dim if self.uses_controls else 0)
        return dim + (s.state_dim if self.closed_loop else 0)

    @property
    def input_key(self) -> str:
        return HISTORY_KEY if self.closed_loop else OPEN_LOOP_KEY

    @property
    def action_key(self) -> str:
        return KINDS[self.config.kind]

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
        self.policy.input_loc.copy_(loc.repeat(self.config.window))
        self.policy.input_scale.copy_(scale.repeat(self.config.window))

    # ----------------------------------------------------------------- networks
    def predict(self, prev_estimate: torch.Tensor, prev_control: torch.Tensor) -> torch.Tensor:
        """DAOF-v1's model predictor f(x̂_{t−1}, u_{t−1})."""
        return self.system.f(prev_estimate, prev_control)

    def estimate(self, window, prev_estimate=None, prev_control=None) -> torch.Tensor:
        """Deterministic estimate x̂_t (the squashed loc, plus the prediction for DAOF-v1)."""
        return self._fast_estimate(self._inference_layers(), window, prev_estimate, prev_control)

    forward = estimate

    def stochastic_actor(self) -> ProbabilisticActor:
        """TanhNormal actor over ``action_key`` (the estimate, or the v1 correction) for DSAC-T."""
        module = TensorDictModule(self.policy, in_keys=[self.input_key], out_keys=["loc", "scale"])
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

    def _add_prediction(self, correction, prev_estimate, prev_control):
        """x̂_t = f(x̂_{t−1}, u_{t−1}) + correction, kept in the plausible state range.

        Without the clamp an untrained update can push the predictor outside the region where
        the vehicle model is stable, and the estimate then runs away for the rest of the episode.
        """
        estimate = correction + self.predict(prev_estimate, prev_control)
        return torch.clamp(estimate, self.state_low, self.state_high)

    def exploration_policy(self) -> TensorDictSequential:
        """What a collector runs: sample from π and, for DAOF-v1, add the prediction."""
        actor = self.stochastic_actor()
        if self.config.kind != "DAOF-v1":
            return TensorDictSequential(actor)
        add = TensorDictModule(
            self._add_prediction,
            in_keys=["correction", "prev_estimate", "prev_control"],
            out_keys=["action"],
        )
        return TensorDictSequential(actor, add)

    def filter_module(self) -> TensorDictModule:
        """Deterministic filter: reads h_t (and x̂_{t−1}, u_{t−1} for v1), writes ``action``."""
        in_keys = [self.input_key]
        if self.config.kind == "DAOF-v1":
            in_keys += ["prev_estimate", "prev_control"]
        return TensorDictModule(self, in_keys=in_keys, out_keys=["action"])

    # ----------------------------------------------------------------- offline filtering
    def open_loop_frames(self, y, u, u_prev) -> torch.Tensor:
        """Per-step frames without the fed-back estimate: [y_t, (u_t, u_{t−1})].

        A missing measurement (NaN) holds the channel's last value; before the first value of a
        channel it is the channel's training mean (see ``hold_last_value``).
        """
        start = self.system.state_dim if self.closed_loop else 0  # where y sits in a frame
        y_mean = self.policy.input_loc[start : start + self.system.measurement_dim]
        y = hold_last_value(y, y_mean)
        return torch.cat([y, u, u_prev] if self.uses_controls else [y], -1)

    def _inference_layers(self) -> list[tuple[torch.Tensor, torch.Tensor]]:
        """The policy's (weight, bias) per layer, for the deterministic filter only.

        The input normalisation is folded into the first layer and only the loc rows of the last
        are kept, so one filter step costs four ``linear`` calls and three GELUs. Rebuilt on every
        ``run`` (cheap), so it always matches the current weights.
        """
        linears = [m for m in self.policy.mlp if isinstance(m, nn.Linear)]
        first, last, n = linears[0], linears[-1], self.system.state_dim
        w0 = first.weight / self.policy.input_scale
        layers = [(w0, first.bias - w0 @ self.policy.input_loc)]
        layers += [(m.weight, m.bias) for m in linears[1:-1]]
        return layers + [(last.weight[:n], last.bias[:n])]

    def _fast_estimate(self, layers, window, prev_estimate=None, prev_control=None) -> torch.Tensor:
        """``estimate`` on pre-folded layers (``_run`` folds them once per trajectory)."""
        h = window
        for weight, bias in layers[:-1]:
            h = nn.functional.gelu(nn.functional.linear(h, weight, bias))
        u = nn.functional.linear(h, *layers[-1])  # the pre-squash loc; a = (hi−lo)/2 · tanh(u) + (hi+lo)/2
        out = torch.addcmul((self.high + self.low) / 2, (self.high - self.low) / 2, torch.tanh(u))
        if self.config.kind == "DAOF-v1":
            out = self._add_prediction(out, prev_estimate, prev_control)
        return out

    @torch.inference_mode()
    def _run(self, y: torch.Tensor, u_prev: torch.Tensor, u: torch.Tensor) -> torch.Tensor:
        """Filter [runs, steps] data -> [runs, steps, n] (``Filter.run`` validates the input).

        Closed-loop filters build the window exactly as the env's CatTensors + CatFrames do (N
        copies of the first frame after the reset), so ``run`` and an env rollout give the same
        estimates; the open-loop SLF filters every step at once.
        """
        if not self.closed_loop:
            return self.estimate(sliding_windows(self.open_loop_frames(y, u, u_prev), self.config.window))
        return self._stream(y, u_prev, u)

    def _stream(self, y: torch.Tensor, u_prev: torch.Tensor, u: torch.Tensor) -> torch.Tensor:
        """Step-by-step filtering (closed loop; for the SLF the streaming form of its windows)."""
        s, N = self.system, self.config.window
        runs, steps = y.shape[:2]
        layers = self._inference_layers()
        measured = self.open_loop_frames(y, u, u_prev)  # [runs, steps, F − n]
        prev = s.prior.mean.to(y.device).expand(runs, -1).clone()
        width = self.frame_dim
        out = torch.empty(runs, steps, s.state_dim, device=y.device)
        window = None
        for t in range(steps):
            frame = torch.cat([prev, measured[:, t]], -1) if self.closed_loop else measured[:, t]
            # slide the window by one frame; right after the reset it is N copies of frame 1
            window = frame.repeat(1, N) if window is None else torch.cat([window[:, width:], frame], -1)
            prev = self._fast_estimate(layers, window, prev, u_prev[:, t])
            out[:, t] = prev
        return out

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
    config = FilterConfig(**blob["config"])
    for key, value in (expect or {}).items():
        if getattr(config, key) != value:
            raise ValueError(f"checkpoint {path} has {key}={getattr(config, key)!r}, expected {value!r}")
    module = LearnedFilter(config, system)
    module.load_state_dict(blob["state_dict"])
    module.extra = blob.get("extra", {})
    return module.eval()
