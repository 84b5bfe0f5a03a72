"""ReSiReg: spatially consistent dense vision-language features (method, encoders, inference).

The top-level names load on first use (PEP 562), so importing a light submodule such as
``resireg.variant_names`` does not import torch.
"""

from __future__ import annotations

import importlib
from typing import Any

__all__ = ["ReSiRegFull", "ReSiRegLite", "PrototypeHeuristic", "VARIANTS", "build_variant"]
__version__ = "0.1.0"

_SOURCES = {
    "ReSiRegFull": "resireg.reconstruct",
    "ReSiRegLite": "resireg.reconstruct",
    "PrototypeHeuristic": "resireg.heuristic",
    "VARIANTS": "resireg.variant_names",
    "build_variant": "resireg.variants",
}


def __getattr__(name: str) -> Any:
    if name in _SOURCES:
        return getattr(importlib.import_module(_SOURCES[name]), name)
    raise AttributeError(f"module 'resireg' has no attribute {name!r}")
