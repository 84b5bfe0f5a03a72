"""Deprecated: the dense-encoder interface moved to :mod:`resireg.models.interface`. This module re-exports its names, with a
``DeprecationWarning``, for one release."""

from __future__ import annotations

import importlib
import warnings
from typing import Any

_NAMES = ("InputRule", "DenseOutput", "DenseEncoder", "block_index", "block_indices")


def __getattr__(name: str) -> Any:
    if name in _NAMES:
        warnings.warn(f"resireg.models.encoder.{name} moved to resireg.models.interface.{name}",
                      DeprecationWarning, stacklevel=2)  # fmt: skip
        return getattr(importlib.import_module("resireg.models.interface"), name)
    raise AttributeError(f"module 'resireg.models.encoder' has no attribute {name!r}")
