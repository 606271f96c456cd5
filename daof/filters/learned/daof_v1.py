"""DAOF-v1: x̂_t = f(x̂_{t−1}, u_{t−1}) + K̄_t ν_t + b_t ⊙ π(h_t^N), a model predictor, a reference update and a
learned, bounded residual.

π ∈ [−1, 1]ⁿ; K̄_t is a UKF's mean Kalman gain at step t, ν_t the innovation of the prediction and
b_t = max(correction_sigmas · max(that UKF's √diag P⁺_t, its RMSE on the system's simulated data,
``error_scale``), EXCESS_COVER · its excess error) (``set_schedules``). Where its frame allows (it holds
u_t and u_{t−1}, or the system has no controls) the network also reads ν_t / √diag S_t. A missing
measurement reads as its prediction (``missing_fill``).

With ``reference_gain=False`` it is the paper's own form x̂_t = f(x̂_{t−1}, u_{t−1}) + b_t ⊙ π(h_t^N): no
reference update, the whole update learned, b_t = correction_sigmas · max(the UKF's √diag P⁻_t,
``error_scale``), wide enough for any update a Kalman-type filter would make.
"""

from __future__ import annotations

import torch

from daof.filters.learned.base import UpdateFilter, register
from daof.filters.learned.config import FilterConfig
from daof.filters.learned.network import SCHEDULE_STEPS, schedule_row

__all__ = ["DAOFv1", "EXCESS_COVER"]

#: the residual's bound covers this many RMS of the improvable part of the reference's error. By the
#: orthogonality of the MMSE estimate, E‖x − x̂_ref‖² = E‖x − x̂_opt‖² + E‖x̂_opt − x̂_ref‖²; with the
#: UKF's own P⁺ standing in for the optimum's error, the improvable part is its excess error
#: √max(RMSE² − P⁺, 0) (``daof.envs.scales``): none on a consistent UKF (the bound stays
#: correction_sigmas · √P⁺), large where the UKF is far from optimal and sure of itself.
EXCESS_COVER = 3.0


@register
class DAOFv1(UpdateFilter):
    """DAOF-v1 (module docstring): needs a system with a model (``has_model``)."""

    kind = "DAOF-v1"
    takes_reference_gain = True
    # reading the prediction beats holding the last value on every gap pattern measured
    # (diagnostics/missing_data.py, docs/missing_data.md); the others have no model to predict with
    missing_fills = ("prediction", "hold")

    @classmethod
    def check_config(cls, config: FilterConfig) -> None:
        super().check_config(config)
        if config.missing_mask:
            raise ValueError("missing_mask is for the model-free filters: DAOF-v1 reads a gap as its prediction")

    def _check_system(self) -> None:
        if not self.system.has_model:
            raise ValueError(f"DAOF-v1 needs a model predictor; {self.config.system} offers none (use DAOF-v2)")

    @property
    def innovation_input(self) -> bool:
        """Whether the network reads ν_t: it needs u_t and u_{t−1} in the frame when the system has controls."""
        return self.uses_controls or self.system.control_dim == 0

    def _innovation_feature(self):
        return self.innovation if self.innovation_input else None

    def _initial_bound(self) -> torch.Tensor:
        # a placeholder for a filter whose schedules are not set yet (``set_schedules`` replaces it): the process noise
        return self.config.correction_sigmas * self.system.process_noise.covariance.diagonal().sqrt()

    def _register_action_buffers(self) -> None:
        super()._register_action_buffers()
        s = self.system
        if self.config.reference_gain:
            self.register_buffer("reference_gain", torch.zeros(SCHEDULE_STEPS, s.state_dim, s.measurement_dim))

    # ----------------------------------------------------------------- model
    def predict(self, prev_estimate: torch.Tensor, prev_control: torch.Tensor) -> torch.Tensor:
        """The model predictor f(x̂_{t−1}, u_{t−1})."""
        return self.system.f(prev_estimate, prev_control)

    def innovation(self, window: torch.Tensor, prediction: torch.Tensor | None = None) -> torch.Tensor:
        """ν_t = y_t − g(x̂⁻_t, u_t), x̂⁻_t = f(x̂_{t−1}, u_{t−1}), from the newest frame of h_t^N.

        ``prediction`` is x̂⁻_t where the caller has it already.
        """
        s, at = self.system, self.layout.offset
        frame = self.layout.newest(window)
        if self.uses_controls:
            u, u_prev = frame[..., at("control")], frame[..., at("prev_control")]
        else:  # a system without controls: f and g take empty ones
            u = u_prev = frame[..., :0]
        if prediction is None:
            prediction = s.f(frame[..., at("prev_estimate")], u_prev)
        return frame[..., at("measurement")] - s.g(prediction, u)

    def _innovation_for(self, window: torch.Tensor, prediction: torch.Tensor) -> torch.Tensor | None:
        return self.innovation(window, prediction)

    def reference_update(self, window: torch.Tensor, prediction: torch.Tensor, step, nu=None) -> torch.Tensor | None:
        """K̄_t ν_t, the update of the reference gain ``reference_gain`` (K̄_t per step t); None in the paper's form."""
        if not self.config.reference_gain:
            return None
        if nu is None:
            nu = self.innovation(window, prediction)
        return (schedule_row(self.reference_gain, step) @ nu.unsqueeze(-1)).squeeze(-1)

    # ----------------------------------------------------------------- schedules
    @torch.no_grad()
    def set_schedules(self, schedule: dict[str, torch.Tensor]) -> None:
        """The per-step tables from a Kalman-type filter's ``covariance_schedule`` (rows t = 1..S).

        The update bound b_t (module docstring; schedule["estimate"]_t is √diag P⁺_t, schedule["prediction"]_t
        √diag P⁻_t), the gain K̄_t = schedule["gain"]_t and, with the innovation input, its scale
        √diag S_t = schedule["innovation"]_t. A shorter schedule is held at its last row. Stored in the
        checkpoint.
        """

        def rows(values: torch.Tensor) -> torch.Tensor:
            values = values.to(self.correction_scale)[:SCHEDULE_STEPS]
            return torch.cat([values, values[-1:].expand(SCHEDULE_STEPS - len(values), *values.shape[1:])])

        sigmas = self.config.correction_sigmas
        if not self.config.reference_gain:  # the paper's form: the bound covers the whole update
            prior = rows(schedule["prediction"]).clamp_min(1e-12)
            self.correction_scale.copy_(sigmas * torch.maximum(prior, self.error_scale.to(prior)))
        else:
            # never narrower than the reference's actual error on simulated data, and wide enough for what
            # an optimal filter would change of it where the UKF is overconfident (EXCESS_COVER)
            claimed = rows(schedule["estimate"]).clamp_min(1e-12)
            bound = sigmas * torch.maximum(claimed, self.error_scale.to(claimed))
            excess = EXCESS_COVER * self.system.scales().excess.to(claimed)
            self.correction_scale.copy_(torch.maximum(bound, excess))
            self.reference_gain.copy_(rows(schedule["gain"]))
        if self.innovation_input:
            self.policy.innovation_scale.copy_(rows(schedule["innovation"]).clamp_min(1e-12))

    # ----------------------------------------------------------------- missing measurements
    def _gap_fill(self, y: torch.Tensor, u_prev: torch.Tensor, u: torch.Tensor):
        """With ``missing_fill="prediction"``: a missing channel reads as its predicted measurement (ν_t = 0 there)."""
        if self.missing_fill != "prediction":
            return None
        gaps = torch.isnan(y)
        gappy = gaps.any(-1).any(0).tolist()
        y_part = self.layout.without("prev_estimate").offset("measurement")  # y_t leads the frame's measured part
        m = y_part.stop

        def fill(t: int, prev: torch.Tensor, present: torch.Tensor) -> torch.Tensor:
            if not gappy[t]:
                return present
            predicted = self.system.g(self.predict(prev, u_prev[:, t]), u[:, t])
            return torch.cat([torch.where(gaps[:, t], predicted, present[:, :m]), present[:, m:]], -1)

        return fill
