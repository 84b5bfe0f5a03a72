"""The ground of ``resireg_train``: the helpers every package uses to read a config.

- :mod:`.errors` (the config path added to the library's errors), :mod:`.keys` (reading a
  config key by key, keys nothing reads), :mod:`.machine` (the devices, files and packages a
  config asks of this machine), :mod:`.paths` (``conf/``, the run id), :mod:`.moves` (class
  paths and config keys that moved between releases, and the deprecation of a key's old
  spelling). What a record never keeps is :mod:`resireg.secrets`'s.

The bottom floor of ``resireg_train``: it imports only ``resireg``, Hydra's override parser and
OmegaConf, and may be imported by every package of ``resireg_train``. The checks of whole commands (train, eval, map,
resume) read every table and live above them, in :mod:`resireg_train.checks`; the layers are
``[tool.importlinter]`` in pyproject.toml.
"""
