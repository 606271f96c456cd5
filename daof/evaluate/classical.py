"""The model-based filters of a study and the reference its ratios are taken to."""

from __future__ import annotations

from daof.evaluate.study import ORACLE
from daof.filters import EKF, UKF, JointParameterPF, ParticleFilter

__all__ = ["classical_filters"]


def classical_filters(system, particles: int, oracle_particles: int) -> tuple[dict, str]:
    """The model-based filters of a veh2dof-type study (name -> filter) and the name of its reference.

    EKF, UKF, PF and PF-oracle on the system's nominal model; on a scenario with uncertain model
    parameters (``mismatch``) also PF-joint, which infers them, and it is then the reference the
    ratios and the diverged-run rule are relative to (the scenario's Bayes filter); else PF-oracle.
    """
    filters = {
        "EKF": EKF(system),
        "UKF": UKF(system),
        "PF": ParticleFilter(system, int(particles), seed=1),
        ORACLE: ParticleFilter(system, int(oracle_particles), seed=2),
    }
    if not system.uncertain_parameters():
        return filters, ORACLE
    filters[JointParameterPF.name] = JointParameterPF(system, int(oracle_particles), seed=4)
    return filters, JointParameterPF.name
