"""Filters: every one offers ``run(data) -> estimates [runs, steps, state_dim]`` (see ``base``).

Classical baselines: ``KalmanFilter`` and ``StationaryKalmanFilter`` (linear system), ``EKF`` and
``UKF`` (filterpy), the batched bootstrap ``ParticleFilter`` and ``JointParameterPF``, which also
infers a scenario's uncertain model parameters, and ``ProposalParticleFilter``, whose proposal uses the
measurement (for references where the bootstrap PF's weights degenerate).
"""

from daof.filters.base import Filter
from daof.filters.kalman import EKF, UKF, CovarianceRepair, KalmanFilter
from daof.filters.particle import JointParameterPF, ParticleFilter, systematic_resample
from daof.filters.proposal import ProposalParticleFilter
from daof.filters.stationary_kalman import StationaryKalmanFilter

__all__ = [
    "Filter",
    "KalmanFilter",
    "StationaryKalmanFilter",
    "EKF",
    "UKF",
    "CovarianceRepair",
    "ParticleFilter",
    "JointParameterPF",
    "ProposalParticleFilter",
    "systematic_resample",
]
