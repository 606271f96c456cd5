"""The classical filters predict with u_{t-1} and update with y_t at u_t (docs/design.md time convention).

On the linear system g does not depend on u, so u_t ("control") enters no correct filter's estimate
of x_t: replacing it by anything leaves every estimate bit for bit the same. A filter that predicted
with u_t would move.
"""

import pytest
import torch

from daof.filters import EKF, UKF, KalmanFilter, ParticleFilter

FILTERS = {
    "KF": KalmanFilter,
    "EKF": EKF,
    "UKF": UKF,
    "PF": lambda s: ParticleFilter(s, 200, seed=3),
}


@pytest.mark.parametrize("name", FILTERS)
def test_u_t_does_not_enter_the_estimate_of_x_t_on_linear(lin, name):
    data = lin.simulate(4, 40, seed=11)
    moved = data.clone()
    moved["control"] = moved["control"] + 5.0  # the force doubles back ~5x its amplitude
    assert not torch.equal(moved["control"], data["control"])
    torch.testing.assert_close(FILTERS[name](lin).run(moved), FILTERS[name](lin).run(data), rtol=0, atol=0)
