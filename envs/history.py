"""The history window h_t^N that a DAOF policy reads.

h_t^N = (x̂_{t−N}, y_{t−N+1}, …, x̂_{t−1}, y_t): the last N (previous estimate, measurement)
pairs, each optionally followed by the controls (u_t, u_{t−1}). It is TorchRL's own
``CatTensors`` (one frame per step, keys in the order given) followed by ``CatFrames`` (the last
N frames, oldest first, along the last dim). With ``missing_flags`` each frame ends with the
``missing`` flags of a system with sensor gaps (``daof.envs.gaps``).

Reset padding: right after a reset the window holds the first frame (the prior mean and the
first measurement) and N − 1 padding frames in front of it: copies of that frame (``"same"``,
the default) or zeros (``"zeros"``; for zero-mean channels zeros are the training mean, i.e.
frames that carry no measurement, while N copies look like N measurements that agree). Partial
resets pad only the runs that were reset. The env stores the window once per step (``history`` and its ``next``
twin, as every TorchRL observation), so a replay buffer needs no frame-stacking transform of its
own and must not be given one.
"""

from __future__ import annotations

from daof.envs.gaps import MISSING_KEY
from torchrl.envs import CatFrames, CatTensors, Compose, TransformedEnv

__all__ = ["FRAME_KEY", "HISTORY_KEY", "PADDINGS", "frame_keys", "history_dim", "window_transform", "with_window"]

HISTORY_KEY = "history"
FRAME_KEY = "frame"
#: how the window is filled in front of the first frame after a reset
PADDINGS = ("same", "zeros")


def frame_keys(include_controls: bool, missing_flags: bool = False) -> list[str]:
    """The per-step keys that form one frame of the window, in window order."""
    keys = ["prev_estimate", "measurement"]
    if include_controls:
        keys += ["control", "prev_control"]
    if missing_flags:  # envs.gaps.GappySystem's flags
        keys.append(MISSING_KEY)
    return keys


def window_transform(
    window: int, include_controls: bool = True, padding: str = "same", missing_flags: bool = False
) -> Compose:
    """Transforms that add ``frame`` and the N-step window ``history`` to an env's output."""
    if not isinstance(window, int) or window < 1:
        raise ValueError(f"window must be an integer N >= 1, got {window!r}")
    if padding not in PADDINGS:
        raise ValueError(f"window padding must be one of {PADDINGS}, got {padding!r}")
    pad = {"padding": "same"} if padding == "same" else {"padding": "constant", "padding_value": 0.0}
    return Compose(
        CatTensors(frame_keys(include_controls, missing_flags), out_key=FRAME_KEY, del_keys=False, sort=False),
        CatFrames(N=window, dim=-1, in_keys=[FRAME_KEY], out_keys=[HISTORY_KEY], **pad),
    )


def history_dim(system, window: int, include_controls: bool = True) -> int:
    """Length of h_t^N for ``system``."""
    frame = system.state_dim + system.measurement_dim + (2 * system.control_dim if include_controls else 0)
    return window * frame


def with_window(
    env, window: int, include_controls: bool = True, padding: str = "same", missing_flags: bool = False
) -> TransformedEnv:
    """Wrap ``env`` so that its observations carry the history window (``missing_flags``: and the
    ``missing`` flags of a system with gaps in every frame)."""
    return TransformedEnv(env, window_transform(window, include_controls, padding, missing_flags))
