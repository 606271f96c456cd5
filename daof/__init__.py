"""daof: learned state estimators (DAOF) and the Monte Carlo evaluator."""

__version__ = "0.1.0"
