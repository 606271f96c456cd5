"""``FilterConfig``: everything needed to rebuild a learned filter (stored in its checkpoint)."""

from __future__ import annotations

from collections.abc import Mapping
from dataclasses import MISSING, dataclass, fields

__all__ = ["MISSING_FILLS", "RETIRED_OPTIONS", "FilterConfig", "retire_options", "retired_refusal"]

#: what a learned filter reads for a missing measurement channel (``LearnedFilter.missing_fill``)
MISSING_FILLS = ("hold", "prediction")
#: the versions of a training config without ``kind`` (recipes/*/config.yaml's ``version``)
_VERSIONS = {"v1": "DAOF-v1", "v2": "DAOF-v2"}
#: options measured not to help and deleted (docs/log/2026-12-07-retired-options.md,
#: docs/log/2026-12-07-daof-v2-increment-form-removed.md): option -> (the kinds that read it, the
#: value that survives). Old checkpoints and configs may still hold them; ``retire_options`` reads those.
RETIRED_OPTIONS = {
    "correction_bound": (("DAOF-v1",), "posterior"),  # b_t = k · a UKF's √diag P⁺_t
    "innovation_input": (("DAOF-v1",), True),  # the network reads ν_t where its frame allows
    "window_padding": (("DAOF-v1", "DAOF-v2"), "same"),  # copies of the first frame (the SLF's always were)
    "v2_action": (("DAOF-v2",), "estimate"),  # x̂_t = π(h_t); the increment form x̂_{t−1} + b_t ⊙ π(h_t) is gone
}
_RETIRED_LOG = "docs/log/2026-12-07-retired-options.md"
#: the log entry of DAOF-v2's increment form, removed on 2026-12-07 (it was ``v2_action="increment"``)
INCREMENT_FORM_LOG = "docs/log/2026-12-07-daof-v2-increment-form-removed.md"


def retired_refusal(option: str, value, kind: str, name: str | None = None) -> str:
    """The one line that refuses a retired ``option`` holding ``value``, not its surviving value, for ``kind``.

    ``name``: what the option is called where it was given (a training key ``network.v2_action``).
    """
    name = name or option
    if option == "v2_action":
        return (
            f"{name}={value!r} was removed on 2026-12-07 with DAOF-v2's increment form ({INCREMENT_FORM_LOG}): "
            "a DAOF-v2 is always the estimate form x̂_t = π(h_t) now"
        )
    surviving = RETIRED_OPTIONS[option][1]
    return f"{name}={value!r} was retired ({_RETIRED_LOG}): a {kind} now always has {option}={surviving!r}"


def retire_options(kind: str, options: Mapping) -> dict:
    """``options`` without the retired ones (``RETIRED_OPTIONS``), which must hold their surviving value.

    A retired option that ``kind`` never read (a DAOF-v2's ``correction_bound``, the SLF's
    ``window_padding``) is dropped whatever its value; one that ``kind`` read with another value than
    the one that survives is refused with one ``ValueError`` line (``retired_refusal``): the filter it
    describes no longer exists (a DAOF-v2 with ``v2_action="increment"``).
    """
    for option, (kinds, surviving) in RETIRED_OPTIONS.items():
        if option in options and kind in kinds and options[option] != surviving:
            raise ValueError(retired_refusal(option, options[option], kind))
    return {key: value for key, value in options.items() if key not in RETIRED_OPTIONS}


@dataclass
class FilterConfig:
    """Everything needed to rebuild a learned filter (stored in its checkpoint).

    ``kind`` picks the class (``daof.filters.learned.filter_class``);
    each class refuses the options it cannot honour (``LearnedFilter.check_config``). Options
    measured not to help are gone (``RETIRED_OPTIONS``); ``FilterConfig.from_dict`` reads a stored
    config that still holds them.
    """

    kind: str  # "DAOF-v1" | "DAOF-v2" | "SLF" | "KalmanNet"
    system: str
    scenario: str = "nominal"
    window: int = 20
    include_controls: bool = True
    num_cells: int = 256
    depth: int = 3
    #: DAOF-v1: the update is K̄_t ν_t + b_t ⊙ π(h_t), with K̄_t a UKF's mean Kalman gain at step t
    #: and ν_t the innovation of the prediction, bounded by b_t = correction_sigmas · a UKF's estimate
    #: error std √diag P⁺_t, the size of what is left to correct after a Kalman update (all three
    #: from ``set_schedules``). π(h_t) learns the residual of a gain-scheduled Kalman update
    #: (docs/linear_check.md). DAOF-v1 also reads ν_t / √diag S_t where its frame allows (``DAOFv1``).
    correction_sigmas: float = 4.0
    #: DAOF-v1: False is the paper's own form x̂_t = f(x̂_{t−1}, u_{t−1}) + b_t ⊙ π(h_t), the whole update
    #: learned, with b_t = correction_sigmas · the UKF's prediction error std √diag P⁻_t (it covers any
    #: update a Kalman-type filter makes); a report row of its own beside the default's residual on
    #: K̄_t ν_t, to show what the reference gain buys (docs/experiment1.md)
    reference_gain: bool = True
    #: closed-loop filters also read the start-up feature ρ_t (see ``startup_feature``)
    startup_input: bool = True
    #: the policy's GELU: "tanh" (its tanh approximation) or "none" (exact, erf). Same function to
    #: ~1e-3; the exact one costs ~5x more at batch 1 on CPU (3 of them per estimate), see
    #: docs/benchmarks/learned.md. Checkpoints saved before the field existed are exact.
    gelu_approximate: str = "tanh"
    #: SLF, DAOF-v2: each frame also carries one 0/1 flag per measurement channel, 1 where the
    #: channel is missing (its value then holds the last present one). Meant for filters trained
    #: through random gaps (``dropout`` in the recipes' configs, ``daof.envs.gaps``); docs/missing_data.md
    missing_mask: bool = False
    #: KalmanNet's gain network: the width multipliers of its input and output layers (the authors' 5 and 40)
    kalmannet_in_mult: int = 5
    kalmannet_out_mult: int = 40

    def __post_init__(self):
        from daof.filters.learned.base import filter_class  # the classes import this module

        cls = filter_class(self)  # refuses an unknown kind
        if not isinstance(self.window, int) or self.window < 1:
            raise ValueError(f"window must be an integer N >= 1, got {self.window!r}")
        if self.gelu_approximate not in ("tanh", "none"):
            raise ValueError(f"gelu_approximate must be 'tanh' or 'none', got {self.gelu_approximate!r}")
        cls.check_config(self)

    @classmethod
    def from_dict(cls, fields: Mapping) -> FilterConfig:
        """The config of stored ``fields`` (``asdict`` of a config, as checkpoints hold it).

        A config stored before the options were retired may hold them: see ``retire_options``.
        """
        return cls(**retire_options(str(fields.get("kind")), fields))

    @classmethod
    def from_training(cls, cfg: Mapping, state_dict: Mapping | None = None) -> FilterConfig:
        """The filter config of a training run's config (``checkpoint.pt``'s ``config``, a dict or DictConfig).

        The kind is the config's ``kind``, or from its ``version`` (v1/v2: DSAC-T) or, with neither,
        the SLF (the supervised recipe's config). Options a kind does not take are dropped (a config
        shared by v1 and v2 runs may set them). A config written before the options were retired may
        hold them (``retire_options``); so may the filter's ``state_dict`` where it is given: a
        DAOF-v1 with no innovation input where its frame allows one was built with a retired option,
        and is refused with one line, as is one whose ``reference_gain`` table contradicts its config.
        """
        kind = cfg.get("kind") or ("SLF" if cfg.get("version") is None else _VERSIONS.get(cfg.get("version")))
        if kind is None:
            raise ValueError(f"training config has version {cfg.get('version')!r}; known: {sorted(_VERSIONS)}")
        net = retire_options(str(kind), dict(cfg.get("network") or {}))
        default = {f.name: f.default for f in fields(cls) if f.default is not MISSING}
        options = ("num_cells", "depth", "correction_sigmas", "startup_input", "missing_mask",
                   "kalmannet_in_mult", "kalmannet_out_mult")  # fmt: skip
        if kind == "DAOF-v1":  # the other kinds have no reference update: a shared config's setting is not theirs
            options += ("reference_gain",)
        config = cls(
            kind=str(kind),
            system=str(cfg["system"]),
            scenario=str(cfg.get("scenario", default["scenario"])),
            window=int(cfg.get("window", default["window"])),
            include_controls=bool(cfg.get("include_controls", default["include_controls"])),
            **{f: type(default[f])(net.get(f, default[f])) for f in options},
        )
        if state_dict is not None and config.kind == "DAOF-v1":  # its buffers say which inputs it was built with
            if ("reference_gain" in state_dict) != config.reference_gain:
                raise ValueError(
                    f"the training config says network.reference_gain={config.reference_gain}, but the weights "
                    f"{'have' if config.reference_gain is False else 'lack'} the reference gain table"
                )
            built = {}
            scale = state_dict.get("policy.innovation_scale")
            if scale is not None and scale.shape[-1] == 0:  # no innovation input: retired unless the frame has no room
                from daof.envs.registry import make_system

                built["innovation_input"] = not (config.include_controls or make_system(config.system).control_dim == 0)
            retire_options(config.kind, built)
        return config
