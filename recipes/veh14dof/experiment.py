"""Experiment II: DAOF-v2 and the SLF on the 14-DOF vehicle (model-free, the paper's Table II units).

    python recipes/veh14dof/experiment.py [profile=tiny|quick|paper] [key=value ...]

The same as ``python -m daof.experiments experiment=veh14dof ...``: the config is daof/conf/experiment/veh14dof.yaml,
the keys are in docs/experiments.md.
"""

import sys

from daof.experiments.experiment import main

if __name__ == "__main__":
    main(sys.argv[1:], experiment="veh14dof", program="recipes/veh14dof/experiment.py")
