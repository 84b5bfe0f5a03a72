"""Training, evaluation and searches for ReSiReg (Lightning + Hydra). Imports `resireg`, never the reverse.

Its libraries are the ``train`` extra (``pip install -e ".[train]"``; ``dev`` includes it); the
core install (``resireg``'s inference) does not carry them, so a missing one is named here, once
(by a ``resireg-*`` console script in one line, no traceback),
instead of surfacing as a bare ``ModuleNotFoundError`` deep inside a command.

Its subpackages (the top level holds no other module): ``cli``, ``runs``, ``config``,
``training``, ``search``, ``report``, ``playground``, ``evaluation``, ``record``, ``data``
(docs/architecture.md).
May be imported by the Hydra sweeper plugin, the benchmarks and the tests; never by ``resireg``.
"""

from importlib.util import find_spec as _find_spec

#: import name -> distribution of the ``train`` extra (pyproject.toml) that resireg_train needs
TRAIN_MODULES = {"lightning": "lightning", "hydra": "hydra-core", "omegaconf": "hydra-core",
                 "datasets": "datasets", "pandas": "pandas", "matplotlib": "matplotlib"}  # fmt: skip

_missing = sorted({dist for module, dist in TRAIN_MODULES.items() if _find_spec(module) is None})
if _missing:
    _message = (
        f"the 'train' extra ({', '.join(_missing)} not installed): "
        'pip install "resireg[train]" (in a clone: pip install -e ".[train]" -c constraints.txt)'
    )
    import sys as _sys
    from pathlib import Path as _Path

    _prog = _Path(_sys.argv[0]).name if _sys.argv and _sys.argv[0] else ""
    if _prog.startswith("resireg-"):  # a console script (pyproject.toml): one line, no traceback
        raise SystemExit(f"{_prog}: error: needs {_message}")
    raise ImportError(f"resireg_train needs {_message}")
