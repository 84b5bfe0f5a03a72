"""``resireg-eval``: the task table (:mod:`.specs`: what ``task=`` picks, torch-free), the
task base class ``EvalTask`` and the results writing (:mod:`.base`), the shared engine (:mod:`.engine`:
batches, class prototypes, autocast), the protocol record (:mod:`.protocol`), the feature cache
(:mod:`.cache`), and one subpackage per task's engine: :mod:`.ovss` (2D, and the training
callback) and :mod:`.mapping` (3D).

A task is what the user picks, an engine what runs it, a protocol the settings it follows.
Imports ``resireg``, ``resireg_train.data``, ``runs`` and the config helpers. May be imported by
``resireg_train.report`` (the task table, the protocol record), the config checks (the task
table) and the CLIs (``resireg-train``'s evaluation callback among them).
"""
