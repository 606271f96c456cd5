"""The optimality check: DAOF-v1 and DAOF-v2 against the Kalman filter on the linear system.

    python recipes/linear/experiment.py [profile=tiny|quick|paper] [key=value ...]

The same as ``python -m daof.experiments experiment=linear ...``: the config is daof/conf/experiment/linear.yaml,
the keys are in docs/experiments.md.
"""

import sys

from daof.experiments.experiment import main

if __name__ == "__main__":
    main(sys.argv[1:], experiment="linear", program="recipes/linear/experiment.py")
