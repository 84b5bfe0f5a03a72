"""What a run writes while it runs: its record, provenance, trackers, system metrics, epochs.

- :mod:`~resireg_train.record.run_record`: :class:`~resireg_train.record.run_record.RunRecord`,
  the one writer of a run folder's ``results.json`` for the run's whole life (start, fields,
  final status), and its reader for many records; :mod:`~resireg_train.record.settings`: the
  settings a record starts with, read once from the job's config (``RecordSettings``);
- :mod:`~resireg_train.record.heartbeat`: the heartbeat a live run touches, and the doubt a
  reader casts on a run whose heartbeat went stale; :mod:`~resireg_train.record.masking`: the
  config as a run's files and trackers keep it (URL passwords masked);
- :mod:`~resireg_train.record.provenance`: what produced a run, one module per idea (the code's
  git state, the inputs' identities, the machine) and the block that joins them;
- :mod:`~resireg_train.record.trackers`: the tracker table (``TRACKER_SPECS``, ``tracker=``),
  the shared base (``Tracker``, ``RunTrackers``) and one module per tracker;
- :mod:`~resireg_train.record.system`: the system metrics every run samples (``system.csv``,
  the peaks in ``results.json``); :mod:`~resireg_train.record.epochs`: what training records
  every epoch; :mod:`~resireg_train.record.cards`: the model card of an export.

The tools that act on finished runs (index, plots, gc, registry, rerun, reproduce) read these
files from :mod:`resireg_train.runs`, above. Imported by the CLIs, the jobs, the evaluation,
the training, the search, the report and the run tools; it imports only ``resireg``,
``resireg_train.config``'s ground, ``resireg_train.data`` and (inside functions) the trackers'
libraries.
"""
