"""The configs of the commands, checked before anything heavy loads, and the helpers every
package uses to read them.

- :mod:`.train`, :mod:`.eval`: the checks of ``resireg-train``'s and ``resireg-eval``'s configs
  (and of ``conf/sweep/``); they read every table (``resireg.specs``, the dataset, task,
  teacher and report-section tables) and may be imported only by the CLIs
  (``resireg_train.cli``) and tests;
- :mod:`.errors` (the config path added to the library's errors), :mod:`.keys` (reading a
  config key by key, keys nothing reads), :mod:`.machine` (the devices, files and packages a
  config asks of this machine), :mod:`.paths` (``conf/``, the run id), :mod:`.moves` (class
  paths that moved between releases), :mod:`.secrets` (what a record never keeps): the bottom
  floor of ``resireg_train``, importing only ``resireg`` and OmegaConf.

May be imported by every package of ``resireg_train`` (the helpers) and by the CLIs (the
checks); the layers are ``[tool.importlinter]`` in pyproject.toml.
"""
