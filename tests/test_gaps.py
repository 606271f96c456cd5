"""Training through sensor gaps (envs/gaps.py): the gappy system, its env and a flagged DAOF-v2.

Pins down: a missing channel holds its last present value and is flagged, the first measurement
is never missing, the gaps leave the trajectory and ``simulate`` untouched; the env passes its specs
check; a DAOF-v2 with missing flags filters the rollout's data offline (gaps as NaN) exactly as it
did in the env; the DSAC-T trainer runs on it; bad options fail clearly.
"""

import pytest
import torch
from daof.envs import make_system
from daof.envs.filtering_env import FilteringEnv
from daof.envs.gaps import MISSING_KEY, GappySystem
from daof.envs.history import with_window
from torchrl.envs.utils import check_env_specs

from daof.filters.learned import FilterConfig, LearnedFilter


def gappy_env(p_max=0.3, blackout_s=0.2, window=4, steps=15, seed=11, flags=True):
    system = GappySystem(make_system("veh2dof"), p_max, blackout_s, steps)
    return with_window(FilteringEnv(system, 3, steps, seed=seed), window, True, missing_flags=flags)


def test_missing_channels_hold_their_last_value_and_are_flagged():
    env = gappy_env(steps=40)
    check_env_specs(env)
    plain = with_window(FilteringEnv(make_system("veh2dof"), 3, 40, seed=11), 4, True)
    with torch.no_grad():
        rollout = env.rollout(40, break_when_any_done=False)
        complete = plain.rollout(40, break_when_any_done=False)
    y, flags = rollout["measurement"], rollout[MISSING_KEY]
    assert set(flags.unique().tolist()) == {0.0, 1.0} and not flags[:, 0].any()
    missing = flags.bool()
    held = torch.cat([y[:, :1], y[:, :-1]], 1)  # a missing entry equals the step before
    assert torch.equal(y[missing], held[missing])
    # the frame of the window ends with the flags
    torch.testing.assert_close(rollout["history"][..., -2:], flags, rtol=0, atol=0)
    # the gaps draw their own numbers, so the trajectories differ from a gap-free env's, but
    # simulate (validation, normaliser) is the base system's, complete
    assert not torch.equal(rollout["true_state"], complete["true_state"])
    gappy = GappySystem(make_system("veh2dof"), 0.3, 0.2, 40)
    torch.testing.assert_close(gappy.simulate(2, 10, 3), make_system("veh2dof").simulate(2, 10, 3), rtol=0, atol=0)


def test_a_flagged_daof_v2_filters_the_gaps_offline_as_in_the_env():
    """The rollout's data with its gaps as NaN, filtered by ``run``: the env's estimates exactly."""
    f = LearnedFilter(FilterConfig(kind="DAOF-v2", system="veh2dof", window=4, num_cells=16, missing_mask=True))
    f.fit_normalizer(runs=4, steps=50)
    f.eval()
    env = gappy_env()
    with torch.no_grad():
        rollout = env.rollout(15, f.filter_module(), break_when_any_done=False)
    data = rollout.select("measurement", "control", "prev_control", "true_state").clone()
    data["measurement"] = data["measurement"].masked_fill(rollout[MISSING_KEY].bool(), float("nan"))
    data.rename_key_("true_state", "state")
    assert torch.isnan(data["measurement"]).any()
    torch.testing.assert_close(f.run(data), rollout["action"], rtol=0, atol=0)


def test_bad_gap_options_fail_clearly():
    with pytest.raises(ValueError, match="training dropout"):
        GappySystem(make_system("veh2dof"), 1.5, 0.0, 10)
    with pytest.raises(ValueError, match="steps >= 1"):
        GappySystem(make_system("veh2dof"), 0.1, 0.0, 0)
    with pytest.raises(ValueError, match="DAOF-v1 reads a gap as its prediction"):
        FilterConfig(kind="DAOF-v1", system="veh2dof", missing_mask=True)
