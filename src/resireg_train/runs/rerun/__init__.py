"""Runs done again: ``resireg-runs rerun`` and ``resireg-runs reproduce``.

- :mod:`~resireg_train.replay.rerun`: a run rebuilt from its record (its job, its recorded
  overrides checked as a search worker checks them, its seed and inputs), refused or recorded
  where the code, data or models drifted, run in a new folder and compared with the original:
  one verdict (identical, within tolerance, differs);
- :mod:`~resireg_train.replay.reproduce`: the jobs behind one row of the paper's tables, the
  figures beside the paper's.

They start other commands as subprocesses and read the records those write, so they sit just
under the CLIs: imported by ``resireg_train.cli.runs`` only; they import the config checks, the
search's override check, the report's paper figures, the run record and the data table.
"""
