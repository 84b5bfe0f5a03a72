"""The console entry points (``[project.scripts]`` of pyproject.toml): ``resireg-train``,
``resireg-eval``, ``resireg-map``, ``resireg-report``, ``resireg-runs``, ``resireg-search``,
``resireg-playground``; :mod:`.job` is the wrapper every Hydra command runs in (the run folder's
lock, its record, the failed-job summary of a sweep, the resolvers of ``conf/``).

The top floor: imports every package of ``resireg_train``; may be imported by nothing in
``resireg_train`` (tests and the benchmarks call its entry points).
"""
