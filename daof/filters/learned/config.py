"""``FilterConfig``: everything needed to rebuild a learned filter (stored in its checkpoint)."""

from __future__ import annotations

from collections.abc import Mapping
from dataclasses import MISSING, dataclass, fields

from daof.envs.history import PADDINGS

__all__ = ["CORRECTION_BOUNDS", "MISSING_FILLS", "V2_ACTIONS", "FilterConfig"]

CORRECTION_BOUNDS = ("kalman", "process", "posterior")
V2_ACTIONS = ("estimate", "increment")
#: what a learned filter reads for a missing measurement channel (``LearnedFilter.missing_fill``)
MISSING_FILLS = ("hold", "prediction")
#: the versions of a training config without ``kind`` (recipes/*/config.yaml's ``version``)
_VERSIONS = {"v1": "DAOF-v1", "v2": "DAOF-v2"}


@dataclass
class FilterConfig:
    """Everything needed to rebuild a learned filter (stored in its checkpoint).

    ``kind`` (with ``v2_action`` for DAOF-v2) picks the class (``daof.filters.learned.filter_class``);
    each class refuses the options it cannot honour (``LearnedFilter.check_config``).
    """

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
    #: computes from h_t^N and the model it has anyway (``DAOFv1.innovation``), divided by
    #: a UKF's innovation std √diag S_t at step t: then the optimal unit action ≈ ν_t/√S_t / k at
    #: every step, start-up included (a Kalman update is K_t ν_t and b_t ∝ std of K_t ν_t)
    innovation_input: bool = True
    #: the policy's GELU: "tanh" (its tanh approximation) or "none" (exact, erf). Same function to
    #: ~1e-3; the exact one costs ~5x more at batch 1 on CPU (3 of them per estimate), see
    #: docs/benchmarks/learned.md. Checkpoints saved before the field existed are exact.
    gelu_approximate: str = "tanh"
    #: closed-loop filters: what fills the window in front of the first frame after a reset,
    #: "same" (copies of it) or "zeros" (``daof.envs.history``); the open-loop SLF's is always "same"
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
        from daof.filters.learned.base import filter_class  # the classes import this module

        cls = filter_class(self)  # refuses an unknown kind
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
        cls.check_config(self)

    @classmethod
    def from_training(cls, cfg: Mapping, state_dict: Mapping | None = None) -> FilterConfig:
        """The filter config of a training run's config (``checkpoint.pt``'s ``config``, a dict or DictConfig).

        The kind is the config's ``kind``, or from its ``version`` (v1/v2: DSAC-T) or, with neither,
        the SLF (the supervised recipe's config). Options a kind does not take are dropped, as
        ``daof.train.base.FilterTrainer`` drops them (a config shared by v1 and v2 runs may set them).
        Options that shape the network but are not in the config (``innovation_input``,
        ``reference_gain``) are read off the filter's ``state_dict`` where it is given.
        """
        from daof.filters.learned.base import filter_class

        kind = cfg.get("kind") or ("SLF" if cfg.get("version") is None else _VERSIONS.get(cfg.get("version")))
        if kind is None:
            raise ValueError(f"training config has version {cfg.get('version')!r}; known: {sorted(_VERSIONS)}")
        net = cfg.get("network") or {}
        default = {f.name: f.default for f in fields(cls) if f.default is not MISSING}
        options = (
            "num_cells",
            "depth",
            "correction_sigmas",
            "correction_bound",
            "startup_input",
            "innovation_input",
            "reference_gain",
            "window_padding",
            "v2_action",
            "missing_mask",
        )
        kinds = {f: type(default[f]) for f in options}
        values = {f: kinds[f](net.get(f, default[f])) for f in options}
        config = cls(
            kind=str(kind),
            system=str(cfg["system"]),
            scenario=str(cfg.get("scenario", default["scenario"])),
            window=int(cfg.get("window", default["window"])),
            include_controls=bool(cfg.get("include_controls", default["include_controls"])),
            **{**values, "reference_gain": False},
        )
        accepts = filter_class(config).accepts_reference_gain
        config.reference_gain = values["reference_gain"] and accepts
        if state_dict is not None and accepts:  # DAOF-v1: its buffers say which inputs it was built with
            if "reference_gain" not in net:
                config.reference_gain = "reference_gain" in state_dict
            if "innovation_input" not in net and "policy.innovation_scale" in state_dict:
                config.innovation_input = state_dict["policy.innovation_scale"].shape[-1] > 0
        return config
