"""Deprecated: the TUM RGB-D reader moved to :mod:`resireg.sources.tum` (the robot side
installs it without Lightning or Hydra; ``TumSource`` takes no ``key`` any more). This module
re-exports the old names, with a ``DeprecationWarning``, for one release."""

from __future__ import annotations

import importlib
import warnings
from typing import Any

#: old name -> the module that holds it now
_MOVED = {
    "CAMERAS": "resireg.sources.tum",
    "DEPTH_SCALE": "resireg.sources.tum",
    "TumSource": "resireg.sources.tum",
    "read_list": "resireg.sources.tum",
    "read_trajectory": "resireg.sources.tum",
}
__all__ = list(_MOVED)


def __getattr__(name: str) -> Any:
    if name in _MOVED:
        warnings.warn(
            f"resireg_train.data.tum.{name} moved to {_MOVED[name]}.{name}; "
            "this alias goes in the next release",
            DeprecationWarning,
            stacklevel=2,
        )
        return getattr(importlib.import_module(_MOVED[name]), name)
    raise AttributeError(f"module 'resireg_train.data.tum' has no attribute {name!r}")
