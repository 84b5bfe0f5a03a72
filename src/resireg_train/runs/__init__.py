"""The tools for finished runs: ``resireg-runs``' commands, which read what
:mod:`resireg_train.record` wrote.

- :mod:`~resireg_train.runs.index`: the runs under a root (``ls``, ``show``, ``diff``,
  ``lineage``);
- :mod:`~resireg_train.runs.plots` (``plot``) and :mod:`~resireg_train.runs.search_plots` (a
  search folder's plots);
- :mod:`~resireg_train.runs.gc` (``gc``) and :mod:`~resireg_train.runs.registry` (``register``:
  an export into MLflow's model registry);
- :mod:`~resireg_train.runs.rerun`: a run again from its record (``rerun``: plan, drift,
  verdict) and :mod:`~resireg_train.runs.reproduce` (``reproduce``: a paper row's jobs).

``rerun`` and ``reproduce`` start other commands as subprocesses and read the records those
write, so this package sits just under the CLIs: imported by ``resireg_train.cli.runs`` only;
it imports the config checks, the search's override check, the report's paper figures, the run
record and the data table.
"""
