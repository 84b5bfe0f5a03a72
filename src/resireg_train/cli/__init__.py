"""The console entry points (``[project.scripts]`` of pyproject.toml): ``resireg-train``,
``resireg-eval``, ``resireg-map``, ``resireg-report``, ``resireg-runs``,
``resireg-playground``: the doors. :mod:`.job` is the one entry point every Hydra command goes
through (a renamed key's old spelling read, then Hydra) and the wrapper every job runs in (its
record); what each command does is :mod:`resireg_train.jobs`'s.

The top floor: imports every package of ``resireg_train``; may be imported by nothing in
``resireg_train`` (tests and the benchmarks call its entry points).
"""
