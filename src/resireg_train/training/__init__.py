"""Training the 25M VLM: the LightningModule (:mod:`.module`), its losses (:mod:`.losses`), the
distillation teachers (:mod:`.teacher`) and their table (:mod:`.specs`, torch-free),
checkpoints (:mod:`.checkpoints`), the console (:mod:`.console`) and the pruning callback of a
search (:mod:`.pruning`).

Imports ``resireg``, ``runs``, ``sweeps`` (pruning) and the config helpers. May be imported by
the CLIs and the config checks (the teacher table).
"""
