"""The Optuna search, its workers, pruning and the search report.

``hparams_search=<name>`` (``conf/hparams_search/``) runs :mod:`.search` (also
``resireg-search``), started by the Hydra sweeper plugin
(:mod:`hydra_plugins.resireg_sweeper`, a thin door); :mod:`.report` writes the search's section
of ``resireg-report``. Imports ``resireg_train.report`` (the sweep's jobs), ``runs`` and the
config helpers. May be imported by ``resireg_train.training`` (a trial's pruning callback), the
CLIs and the Hydra plugin; the report's section table names its report by path.
"""
