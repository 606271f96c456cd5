"""``python -m daof.experiments experiment=veh2dof|linear|veh14dof|path/to/own.yaml [profile=...] [key=value ...]``."""

from daof.experiments.experiment import main

if __name__ == "__main__":
    main()
