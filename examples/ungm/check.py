"""A first look at the UNGM before any training: simulate it and run the classical filters on it.

python -m examples.ungm.check        # from the repository root (so that ``examples`` imports)
"""

from daof.envs import make_system

from daof.evaluate.metrics import pooled_rmse
from daof.filters import EKF, UKF, ParticleFilter

system = make_system("examples.ungm.system:UNGM")
data = system.simulate(runs=20, steps=100, seed=0)  # TensorDict[20, 100]: state, measurement, control, ...
print("x over the first steps of run 0:", [round(v, 2) for v in data["state"][0, :8, 0].tolist()])
for name, filt in {"EKF": EKF(system), "UKF": UKF(system), "PF": ParticleFilter(system, 1000, seed=1)}.items():
    print(f"{name}: RMSE {pooled_rmse(filt.run(data), data['state']).tolist()}")
