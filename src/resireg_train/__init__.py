"""Training, evaluation and sweeps for ReSiReg (Lightning + Hydra). Imports `resireg`, never the reverse.

Its libraries are the ``train`` extra (``pip install -e ".[train]"``; ``dev`` includes it); the
core install (``resireg``'s inference) does not carry them, so a missing one is named here, once,
instead of surfacing as a bare ``ModuleNotFoundError`` deep inside a command.
"""

from importlib.util import find_spec as _find_spec

#: import name -> distribution of the ``train`` extra (pyproject.toml) that resireg_train needs
TRAIN_MODULES = {"lightning": "lightning", "hydra": "hydra-core", "omegaconf": "hydra-core",
                 "datasets": "datasets", "pandas": "pandas", "matplotlib": "matplotlib"}  # fmt: skip

_missing = sorted({dist for module, dist in TRAIN_MODULES.items() if _find_spec(module) is None})
if _missing:
    raise ImportError(
        f"resireg_train needs the 'train' extra ({', '.join(_missing)} not installed): "
        'pip install -e ".[train]" -c constraints.txt'
    )
