"""A run's record: ``results.json`` and what surrounds it.

- :mod:`~resireg_train.runs.record`: :class:`~resireg_train.runs.record.RunRecord`, the one
  writer of a run folder's ``results.json`` for the run's whole life (start, fields, final
  status), and its reader for many records;
- :mod:`~resireg_train.runs.provenance`: what produced a run (code, data, models, machine);
- :mod:`~resireg_train.runs.trackers`: the tracker table (``TRACKER_SPECS``, ``tracker=``) and
  the trackers of one run, driven by its record; :mod:`~resireg_train.runs.loggers`: the four
  trackers' code; :mod:`~resireg_train.runs.epochs`: what training records every epoch;
- :mod:`~resireg_train.runs.index` (``resireg-runs``) and :mod:`~resireg_train.runs.cards`
  (model cards of exports);
- :mod:`~resireg_train.runs.system`: the system metrics every run samples (``system.csv``,
  the peaks in ``results.json``);
- ``resireg-runs``' commands that act on runs: :mod:`~resireg_train.runs.registry`
  (``register``: an export into MLflow's model registry), :mod:`~resireg_train.runs.plots`
  (``plot``; a search folder's plots: :mod:`resireg_train.sweeps.plots`) and
  :mod:`~resireg_train.runs.gc` (``gc``). ``rerun`` and ``reproduce`` run other commands:
  :mod:`resireg_train.replay`, above the layers they use.

Imported by the CLIs, the evaluation, the training, the sweeps and the replay; it imports only
``resireg``, ``resireg_train.config``'s lower modules, ``resireg_train.data`` and (inside
functions) the trackers' libraries.
"""
