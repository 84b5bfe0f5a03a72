"""Deprecated: the protocol record of a run moved to :mod:`resireg_train.protocol_record`. This module re-exports its names, with a
``DeprecationWarning``, for one release."""

from __future__ import annotations

import importlib
import warnings
from typing import Any

_NAMES = ("protocol_record", "protocol_text")


def __getattr__(name: str) -> Any:
    if name in _NAMES:
        warnings.warn(f"resireg_train.protocol.{name} moved to resireg_train.protocol_record.{name}",
                      DeprecationWarning, stacklevel=2)  # fmt: skip
        return getattr(importlib.import_module("resireg_train.protocol_record"), name)
    raise AttributeError(f"module 'resireg_train.protocol' has no attribute {name!r}")
