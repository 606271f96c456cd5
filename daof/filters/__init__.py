"""Filters: every one offers ``run(data) -> estimates [runs, steps, state_dim]`` (see ``base``).

Classical baselines: ``KalmanFilter`` (linear system), ``EKF`` and ``UKF`` (filterpy) and the
batched bootstrap ``ParticleFilter``.
"""

from daof.filters.base import Filter
from daof.filters.kalman import EKF, UKF, CovarianceRepair, KalmanFilter
from daof.filters.particle import ParticleFilter, systematic_resample

__all__ = ["Filter", "KalmanFilter", "EKF", "UKF", "CovarianceRepair", "ParticleFilter", "systematic_resample"]
