"""The history window h_t^N that a learned filter reads, and its one description: ``FrameLayout``.

h_t^N = (x̂_{t−N}, y_{t−N+1}, …, x̂_{t−1}, y_t): the last N frames, oldest first, each the fed-back
estimate x̂_{t−1} (closed-loop filters only), the measurement y_t, optionally the controls
(u_t, u_{t−1}) and, with missing flags, the 0/1 ``missing`` flags of a system with sensor gaps
(``daof.envs.gaps``). A ``FrameLayout`` says which keys form a frame, in what order and how wide,
the window length N; everything that builds or reads a window uses it:

* the TorchRL env: ``layout.transform()`` is TorchRL's own ``CatTensors`` (one frame per step)
  followed by ``CatFrames`` (the last N frames along the last dim); ``with_window(env, layout)``;
* the learned filters' offline and streaming paths (``first_window``, ``slide``, ``sliding_windows``)
  and their reads of one field of the newest frame (``field``);
* the gymnasium env's window (``daof.envs.gym_env``).

Reset padding: right after a reset the window holds the first frame (the prior mean and the
first measurement) and N − 1 copies of it in front (CatFrames' ``padding="same"``; zero padding
was measured not to help and was retired, docs/log/2026-12-07-retired-options.md). Partial
resets pad only the runs that were reset. The env stores the window once per step (``history`` and its ``next``
twin, as every TorchRL observation), so a replay buffer needs no frame-stacking transform of its
own and must not be given one.
"""

from __future__ import annotations

from collections.abc import Mapping
from dataclasses import dataclass

import torch
from daof.envs.gaps import MISSING_KEY
from torchrl.envs import CatFrames, CatTensors, Compose, TransformedEnv

__all__ = [
    "FIELD_ORDER",
    "FRAME_KEY",
    "HISTORY_KEY",
    "FrameLayout",
    "sliding_windows",
    "with_window",
]

HISTORY_KEY = "history"
FRAME_KEY = "frame"
#: every per-step key a frame may hold, in frame order (a layout holds a subset, in this order)
FIELD_ORDER = ("prev_estimate", "measurement", "control", "prev_control", MISSING_KEY)


def sliding_windows(frames: torch.Tensor, window: int) -> torch.Tensor:
    """[..., steps, F] frames -> [..., steps, N·F] windows, oldest first, padded like CatFrames:
    the first frame repeated N−1 times in front."""
    lead, width = frames.shape[:-2], frames.shape[-1]
    pad = frames[..., :1, :].expand(*lead, window - 1, width)
    padded = torch.cat([pad, frames], -2)  # [..., steps + N − 1, F]
    return padded.unfold(-2, window, 1).transpose(-1, -2).flatten(-2)


@dataclass(frozen=True)
class FrameLayout:
    """Which per-step keys form a frame (in order, with their widths) and the window length N.

    Build one with ``for_system`` (from a system's dimensions) or read an env's with ``of_env``.
    The fed-back estimate, where there is one, is the first field of every frame.
    """

    #: (key, width) per field, in frame order
    fields: tuple[tuple[str, int], ...]
    #: N, the number of frames in a window
    window: int

    def __post_init__(self):
        if not isinstance(self.window, int) or isinstance(self.window, bool) or self.window < 1:
            raise ValueError(f"window must be an integer N >= 1, got {self.window!r}")
        fields = tuple((str(key), int(width)) for key, width in self.fields)
        keys = [key for key, _ in fields]
        unknown = [key for key in keys if key not in FIELD_ORDER]
        if unknown or not keys or keys != sorted(keys, key=FIELD_ORDER.index) or len(set(keys)) != len(keys):
            raise ValueError(f"a frame holds distinct keys of {FIELD_ORDER}, in that order; got {keys}")
        if any(width < 0 for _, width in fields):
            raise ValueError(f"field widths must be >= 0, got {dict(fields)}")
        object.__setattr__(self, "fields", fields)
        # where each field sits in a frame (read on every filter step: computed once)
        starts = [sum(width for _, width in fields[:i]) for i in range(len(fields))]
        slices = {key: slice(start, start + width) for (key, width), start in zip(fields, starts)}
        object.__setattr__(self, "_slices", slices)
        object.__setattr__(self, "_keys", tuple(keys))
        object.__setattr__(self, "_frame_dim", sum(width for _, width in fields))

    # ----------------------------------------------------------------- construction
    @classmethod
    def for_system(
        cls,
        system,
        window: int,
        *,
        closed_loop: bool = True,
        include_controls: bool = True,
        missing_flags: bool = False,
    ) -> FrameLayout:
        """The layout of ``system``'s frames: [x̂_{t−1} (closed loop), y_t, (u_t, u_{t−1}), (missing flags)].

        The controls are in only when ``include_controls`` and the system has any.
        """
        n, m, c = system.state_dim, system.measurement_dim, system.control_dim
        fields = [("prev_estimate", n)] if closed_loop else []
        fields.append(("measurement", m))
        if include_controls and c > 0:
            fields += [("control", c), ("prev_control", c)]
        if missing_flags:
            fields.append((MISSING_KEY, m))
        return cls(tuple(fields), window)

    @classmethod
    def of_env(cls, env) -> FrameLayout:
        """The layout of the window an env's transforms build (``ValueError`` if it builds none)."""
        cat = frames = None
        for transform in _transforms(env.transform if isinstance(env, TransformedEnv) else None):
            if isinstance(transform, CatTensors) and list(transform.out_keys) == [FRAME_KEY]:
                cat = transform
            elif isinstance(transform, CatFrames) and list(transform.out_keys) == [HISTORY_KEY]:
                frames = transform
        if cat is None or frames is None:
            raise ValueError(f"the env builds no {HISTORY_KEY!r} window (CatTensors + CatFrames; see with_window)")
        spec = env.observation_spec
        fields = tuple((key, spec[key].shape[-1]) for key in cat.in_keys)
        if frames.padding != "same":
            raise ValueError(
                f"the env's window is padded with {frames.padding!r} ({frames.padding_value}), not with copies "
                "of the first frame ('same'; docs/log/2026-12-07-retired-options.md)"
            )
        return cls(fields, int(frames.N))

    def without(self, *keys: str) -> FrameLayout:
        """The same layout with ``keys`` left out of every frame (e.g. the fed-back estimate)."""
        return FrameLayout(tuple(f for f in self.fields if f[0] not in keys), self.window)

    # ----------------------------------------------------------------- sizes
    @property
    def keys(self) -> tuple[str, ...]:
        return self._keys

    @property
    def widths(self) -> dict[str, int]:
        return dict(self.fields)

    @property
    def frame_dim(self) -> int:
        """F, the width of one frame."""
        return self._frame_dim

    @property
    def width(self) -> int:
        """N·F, the width of a window."""
        return self.window * self.frame_dim

    @property
    def closed_loop(self) -> bool:
        """Whether frames carry the fed-back estimate x̂_{t−1}."""
        return "prev_estimate" in self._slices

    @property
    def uses_controls(self) -> bool:
        return "control" in self._slices

    @property
    def missing_flags(self) -> bool:
        return MISSING_KEY in self._slices

    def __contains__(self, key: str) -> bool:
        return key in self._slices

    def describe(self) -> str:
        """One line: N and the frame's fields with their widths."""
        fields = ", ".join(f"{key}[{width}]" for key, width in self.fields)
        return f"N={self.window} frames of ({fields})"

    # ----------------------------------------------------------------- reading
    def offset(self, key: str) -> slice:
        """Where ``key`` sits inside one frame."""
        if key not in self._slices:
            raise KeyError(f"{key!r} is not in this frame layout {list(self.keys)}")
        return self._slices[key]

    def newest(self, window: torch.Tensor) -> torch.Tensor:
        """The newest frame [..., F] of a window [..., N·F]."""
        return window[..., -self.frame_dim :]

    def unstack(self, window: torch.Tensor) -> torch.Tensor:
        """A window [..., N·F] as its frames [..., N, F], oldest first."""
        return window.unflatten(-1, (self.window, self.frame_dim))

    def field(self, x: torch.Tensor, key: str) -> torch.Tensor:
        """``key``'s entries of a frame [..., F], or of the newest frame of a window [..., N·F]."""
        size, frame = x.shape[-1], self._frame_dim
        if size != frame:
            if size != self.window * frame:
                raise ValueError(f"expected a frame ({frame}) or a window ({self.width}), got width {size}")
            x = x[..., -frame:]
        return x[..., self.offset(key)]

    # ----------------------------------------------------------------- building
    def frame(self, values: Mapping[str, torch.Tensor]) -> torch.Tensor:
        """One frame (or frames of any batch shape) from per-key values: their concatenation in layout order."""
        missing = [key for key in self.keys if key not in values]
        if missing:
            raise KeyError(f"a frame needs {list(self.keys)}; {missing} not given")
        return torch.cat([values[key] for key in self.keys], -1)

    def first_window(self, frame: torch.Tensor) -> torch.Tensor:
        """h_1 [..., N·F]: the first frame [..., F] after a reset behind N − 1 copies of it, as CatFrames pads."""
        return frame.repeat(*([1] * (frame.ndim - 1)), self.window)

    def slide(self, window: torch.Tensor, frame: torch.Tensor) -> torch.Tensor:
        """h_{t+1}: the window with its oldest frame dropped and ``frame`` appended."""
        return torch.cat([window[..., self.frame_dim :], frame], -1)

    def sliding_windows(self, frames: torch.Tensor) -> torch.Tensor:
        """Every window of offline frames at once: [..., steps, F] -> [..., steps, N·F], each episode
        starting after a reset (``sliding_windows`` with this layout's N)."""
        return sliding_windows(frames, self.window)

    def transform(self) -> Compose:
        """The TorchRL transforms that add ``frame`` and the N-step window ``history`` to an env's output."""
        return Compose(
            CatTensors(list(self.keys), out_key=FRAME_KEY, del_keys=False, sort=False),
            CatFrames(N=self.window, dim=-1, in_keys=[FRAME_KEY], out_keys=[HISTORY_KEY], padding="same"),
        )


def _transforms(transform):
    """Every transform inside ``transform`` (Compose flattened), in order."""
    if transform is None:
        return
    if isinstance(transform, Compose):
        for inner in transform.transforms:
            yield from _transforms(inner)
    else:
        yield transform


def with_window(
    env,
    layout: FrameLayout | int,
    include_controls: bool = True,
    *,
    missing_flags: bool = False,
) -> TransformedEnv:
    """Wrap ``env`` (a ``FilteringEnv``) so that its observations carry the window of ``layout``.

    The older form ``with_window(env, N, include_controls, missing_flags=...)`` builds the
    closed-loop layout of ``env.system`` from those arguments. A layout whose fields the env does not
    produce at their widths is refused with one line.
    """
    if not isinstance(layout, FrameLayout):
        layout = FrameLayout.for_system(
            env.system, layout, include_controls=include_controls, missing_flags=missing_flags
        )
    spec = env.observation_spec
    for key, width in layout.fields:
        if key not in spec.keys() or spec[key].shape[-1] != width:
            got = f"width {spec[key].shape[-1]}" if key in spec.keys() else "no such key"
            raise ValueError(f"the window's field {key!r} needs width {width}; the env has {got}")
    return TransformedEnv(env, layout.transform())
