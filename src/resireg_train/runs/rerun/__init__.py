"""``resireg-runs rerun``: a run rebuilt from its record (its job, its recorded overrides
checked as a search worker checks them, its seed and inputs), refused or recorded where the
code, data or models drifted, run in a new folder and compared with the original: one verdict
(identical, within tolerance, differs).

- :mod:`.plan`: the job to run again, its overrides and command;
- :mod:`.drift`: what changed since (code, config, data, models);
- :mod:`.verdict`: the two runs' scores and outputs compared;
- :mod:`.command`: the command itself (plan, check the drift, run, compare, record).

Imported by ``resireg_train.cli.runs`` and :mod:`resireg_train.runs.reproduce` (its job
composition); imports the record, the index, the search's override check and the config.
"""
