"""The trackers a run reports to (``tracker=<name>``, ``conf/tracker/<name>.yaml``).

- :mod:`.specs`: the table (``TRACKER_SPECS``): each tracker's name, class and network rule;
- :mod:`.base`: what every tracker shares (:class:`~.base.Tracker`, the trackers of one run
  :class:`~.base.RunTrackers`, the process state a tracker leaves behind, metric keys);
- one module per tracker: :mod:`.csv`, :mod:`.tensorboard`, :mod:`.mlflow`, :mod:`.wandb`.

Imported by the run record (:mod:`resireg_train.record.run_record`), the CLIs and the run
tools (the registry's MLflow key and artifact location); imports each tracker's library only
inside its functions.
"""
