"""The common interface of every filter: ``run(data) -> estimates [runs, steps, state_dim]``.

A filter that knows how sure it is also offers ``run_with_std(data) -> (estimates, std)``: the same
estimates and, beside each, its error standard deviation per state (√P_ii of a Kalman-type filter,
the weighted particle spread of a PF, a learned filter's uncertainty head); ``std_source`` says
where it comes from, and is None for a filter that gives none (``run_with_std`` then returns None).

A filter sees only what a real filter would: y_t ("measurement"), u_{t-1} ("prev_control") and
u_t ("control") for t = 1..T, plus the model if it is model-based. It starts from the prior
x̂_0 = prior mean (``daof.envs.system`` time convention); the truth ("state") is never read.
"""

from __future__ import annotations

from collections.abc import Mapping

import torch
from tensordict import TensorDictBase

from daof.envs.system import StochasticSystem

__all__ = ["Filter"]


class Filter:
    """Base class. Subclasses implement ``_run`` on validated tensors and fill ``self.stats``.

    ``run`` sets ``stats["diverged"]``: the runs with a non-finite estimate or one outside the
    system's ``divergence_limits`` (its plausible state range widened by its width on each side).
    """

    name: str = "filter"
    #: where ``run_with_std`` reads the error std from ("covariance", "particle spread", ...); None: it gives none
    std_source: str | None = None
    #: called with the number of run-steps each filtering step finishes (a progress bar's ``update``)
    progress = None

    def __init__(self, system: StochasticSystem):
        self.system = system
        #: diagnostics of the last ``run`` (e.g. ``{"repairs": 0, "diverged": 0}``)
        self.stats: dict = {}

    def run(self, data: TensorDictBase) -> torch.Tensor:
        """Estimates x̂_t for t = 1..T of every run -> ``[runs, steps, state_dim]`` on data's device."""
        y, u_prev, u = self.validate(data)
        self.stats = {}
        estimates = self._run(y, u_prev, u)
        self._record(estimates)
        return estimates

    def run_with_std(self, data: TensorDictBase) -> tuple[torch.Tensor, torch.Tensor | None]:
        """``run``'s estimates and each one's error std per state ``[runs, steps, state_dim]`` (None: no std).

        The estimates are those ``run`` gives on the same data; ``run`` itself never pays for the std.
        """
        if self.std_source is None:
            return self.run(data), None
        y, u_prev, u = self.validate(data)
        self.stats = {}
        estimates, std = self._run_with_std(y, u_prev, u)
        self._record(estimates)
        return estimates, std

    def _record(self, estimates: torch.Tensor) -> None:
        """What every run notes in ``stats``: the runs with a non-finite estimate or one outside the
        system's divergence limits."""
        self.stats["diverged"] = int(self.system.diverged_runs(estimates).sum())

    def _run(self, y: torch.Tensor, u_prev: torch.Tensor, u: torch.Tensor) -> torch.Tensor:
        raise NotImplementedError

    def _run_with_std(self, y: torch.Tensor, u_prev: torch.Tensor, u: torch.Tensor):
        """(estimates, std), both [runs, steps, n], on validated tensors (filters with a ``std_source``)."""
        raise NotImplementedError

    def _steps(self, runs: int, steps: int):
        """``range(steps)``, reporting ``runs`` finished run-steps to ``progress`` after each step."""
        for t in range(steps):
            yield t
            if self.progress is not None:
                self.progress(runs)

    def run_streaming(self, data: TensorDictBase) -> torch.Tensor:
        """``run`` one estimate per step, as deployed; what the cost per estimate times.

        Same as ``run`` for recursive filters; filters that can vectorise over time override it.
        """
        return self.run(data)

    def validate(self, data: TensorDictBase) -> tuple[torch.Tensor, torch.Tensor, torch.Tensor]:
        """Check shapes, dtypes and finiteness of the inputs once; raise ValueError otherwise.

        A NaN measurement entry marks a missing channel (sensor dropout, docs/missing_data.md) and
        passes; an infinite measurement and any non-finite control are errors.
        """
        if not isinstance(data, (TensorDictBase, Mapping)):
            raise ValueError(f"{self.name}: data must be a TensorDict, got {type(data).__name__}")
        s = self.system
        dims = {"measurement": s.measurement_dim, "prev_control": s.control_dim, "control": s.control_dim}
        out = []
        for key, dim in dims.items():
            if key not in data.keys():
                raise ValueError(f"{self.name}: data has no {key!r} entry (keys: {list(data.keys())})")
            value = data.get(key)
            if not isinstance(value, torch.Tensor) or value.ndim != 3 or value.shape[-1] != dim:
                shape = tuple(value.shape) if isinstance(value, torch.Tensor) else type(value).__name__
                raise ValueError(f"{self.name}: {key!r} must be [runs, steps, {dim}], got {shape}")
            if not value.is_floating_point():
                raise ValueError(f"{self.name}: {key!r} must be a float tensor, got {value.dtype}")
            if out and value.shape[:2] != out[0].shape[:2]:
                raise ValueError(
                    f"{self.name}: {key!r} has [runs, steps] = {tuple(value.shape[:2])}, "
                    f"measurement has {tuple(out[0].shape[:2])}"
                )
            # one reduction per key in the common all-finite case; locate the culprit only on failure
            if not torch.isfinite(value).all():
                bad = torch.isinf(value) if key == "measurement" else ~torch.isfinite(value)
                if bad.any():
                    where = tuple(bad.nonzero()[0].tolist())
                    what = (
                        "NaN or inf" if key != "measurement" else "inf (NaN marks a missing channel, inf is an error)"
                    )
                    raise ValueError(
                        f"{self.name}: {key!r} contains {what}, first at [run, step, channel] = {list(where)} "
                        f"(value {value[where].item()})"
                    )
            out.append(value)
        if out[0].shape[0] < 1 or out[0].shape[1] < 1:
            raise ValueError(f"{self.name}: data needs at least one run and one step, got {tuple(out[0].shape)}")
        return out[0], out[1], out[2]

    def __repr__(self) -> str:
        return f"{type(self).__name__}(name={self.name!r}, system={self.system.name!r})"
