"""The run record (``RunRecord``), provenance, the run index, model cards and the trackers.

Every job writes its run folder's ``results.json`` through its record; ``resireg-runs`` lists
and compares run folders (:mod:`.index`); the trackers (CSV, TensorBoard, MLflow, W&B) get each
finished run. Imports ``resireg`` and the config helpers only. May be imported by every package
of ``resireg_train`` above it: ``evaluation``, ``report``, ``sweeps``, ``training``, the CLIs.
"""
