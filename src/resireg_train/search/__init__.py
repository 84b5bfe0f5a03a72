"""Optuna searches (``hparams_search=<name>``): everything between a search's command line and
its report. The Hydra sweeper plugin (``hydra_plugins.resireg_sweeper``) is only a door onto
:func:`.loop.run_search`.

- :mod:`.loop`: the ask-and-tell loop every process of a search runs, and the first process's
  part (record the search, start its workers);
- :mod:`.space`: the search space from Hydra's sweep syntax, the optimised metric's check;
- :mod:`.trials`: a trial's worker, heartbeat and outcome; the trials of dead workers;
- :mod:`.storage`: the study's storage (journal or database) and the storage URL's password,
  never written down; :mod:`.journal`: the journal file, repaired or refused after a crash;
- :mod:`.workers`: ``search.json`` (checked data, never a command) and the workers started
  from it (the ``resireg-search`` command: :mod:`resireg_train.cli.search`);
- :mod:`.pruning`: the Lightning callback a training trial reports to its study with (rank 0
  decides, every rank learns it);
- :mod:`.ranks`: the ranks of a DDP trial (``trainer=ddp``), started and watched by its worker;
- :mod:`.report`: the search's part of ``resireg-report`` (trials table, plots; the plots
  of ``resireg-runs plot``: :mod:`resireg_train.runs.search_plots`).

May import :mod:`resireg`, :mod:`resireg_train.config` and :mod:`resireg_train.record` (and
the report, :mod:`resireg_train.report.jobs`); imported by the CLIs (``resireg_train.cli``), the
run tools, the training (pruning), the report (by name) and the Hydra plugin, never by the
library or the evaluation.
"""
