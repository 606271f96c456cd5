"""Experiment I: the 2-DOF vehicle (SLF, DAOF-v1/v2 and the window study against EKF/UKF/PF/PF-oracle).

    python recipes/veh2dof/experiment.py [profile=tiny|quick|paper] [key=value ...]

The same as ``python -m daof.experiments experiment=veh2dof ...``: the config is daof/conf/experiment/veh2dof.yaml,
the keys are in docs/experiments.md.
"""

import sys

from daof.experiments.experiment import main

if __name__ == "__main__":
    main(sys.argv[1:], experiment="veh2dof", program="recipes/veh2dof/experiment.py")
