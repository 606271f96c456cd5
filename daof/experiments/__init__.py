"""Running experiments: training jobs (reused when finished, resumed when interrupted), then the study and report.

One entry serves every experiment: ``python -m daof.experiments experiment=NAME [key=value ...]``
(``daof.experiments.experiment``), configured by ``daof/conf/experiment/NAME.yaml`` over the schema
in ``daof.experiments.config`` (docs/experiments.md).
"""
