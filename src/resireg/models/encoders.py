"""Deprecated: the encoder builder moved to :mod:`resireg.models.factory`. This module re-exports its names, with a
``DeprecationWarning``, for one release."""

from __future__ import annotations

import importlib
import warnings
from typing import Any

_NAMES = (
    "ENCODERS",
    "build_encoder",
    "count_parameters",
    "encoder_arguments",
    "encoder_modules",
    "load_resireg_vlm",
)


def __getattr__(name: str) -> Any:
    if name in _NAMES:
        warnings.warn(f"resireg.models.encoders.{name} moved to resireg.models.factory.{name}",
                      DeprecationWarning, stacklevel=2)  # fmt: skip
        return getattr(importlib.import_module("resireg.models.factory"), name)
    raise AttributeError(f"module 'resireg.models.encoders' has no attribute {name!r}")
