"""The 14-DOF passenger-car simulator of Experiment II (docs/design.md, "veh14dof").

Modules: ``params`` (every number), ``tyre`` (MF 5.2 combined slip), ``dynamics`` (the 28-state
ODE), ``integrate`` (RK4 at h = 1 ms), ``manoeuvre`` (steering profile and PI speed holder),
``sensors`` (15 channels + GNSS flag), ``system`` (the ``StochasticSystem``).
"""

from daof.envs.vehicle14dof.params import TyreCoeffs, Vehicle14DOFParams
from daof.envs.vehicle14dof.system import Vehicle14DOF

__all__ = ["Vehicle14DOF", "Vehicle14DOFParams", "TyreCoeffs"]
