"""ReSiReg: spatially consistent dense vision-language features (method, encoders, inference).

The top-level names load on first use (PEP 562), so importing a light submodule such as
``resireg.specs`` does not import torch.

Imports neither ``resireg_train`` nor Lightning, Hydra or ``datasets``
(``[tool.importlinter]``). May be imported by anything: ``resireg_train``, the benchmarks,
the tests, ``hubconf.py`` and other packages.
"""

from __future__ import annotations

import importlib
from collections.abc import Callable
from typing import Any

__all__ = [
    "ReSiRegFull",
    "ReSiRegLite",
    "PrototypeHeuristic",
    "SegmentationResult",
    "VARIANTS",
    "build_variant",
    "segment",
]
__version__ = "0.1.0"

_SOURCES = {
    "ReSiRegFull": "resireg.method.full",
    "ReSiRegLite": "resireg.method.lite",
    "PrototypeHeuristic": "resireg.method.heuristic",
    "VARIANTS": "resireg.specs.variants",
    "build_variant": "resireg.method.variants",
    "segment": "resireg.deploy.segment",  # one image, a few labels (resireg-segment)
    "SegmentationResult": "resireg.deploy.segment",
}


def lazy_names(package: str, sources: dict[str, str]) -> Callable[[str], Any]:
    """A PEP 562 module ``__getattr__`` for ``package`` that imports ``sources[name]`` (a
    module path) on first use of ``name``, so importing the package stays light."""

    def __getattr__(name: str) -> Any:
        if name in sources:
            return getattr(importlib.import_module(sources[name]), name)
        raise AttributeError(f"module {package!r} has no attribute {name!r}")

    return __getattr__


__getattr__ = lazy_names("resireg", _SOURCES)
