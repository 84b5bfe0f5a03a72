"""The project's Optuna sweeper for Hydra (``hydra/sweeper=resireg_optuna``, set by
``hparams_search=<name>``); "sweeper" is Hydra's word for it (it implements Hydra's
``Sweeper`` interface), the project's is "search". Hydra instantiates sweepers only from the
``hydra_plugins`` package; the search itself lives in :mod:`resireg_train.search` (this plugin only calls
:func:`resireg_train.search.loop.run_search`).

May be imported by Hydra only (its plugin discovery); it imports :mod:`resireg_train.search`.
"""
