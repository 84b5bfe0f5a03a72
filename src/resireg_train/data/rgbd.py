"""Deprecated: the frame record, the pairing and the windows moved to
:mod:`resireg.sources.frames` and :mod:`resireg.sources.pairing` (the robot side installs them
without Lightning or Hydra). This module re-exports the old names, with a ``DeprecationWarning``,
for one release."""

from __future__ import annotations

import importlib
import warnings
from typing import Any

#: old name -> the module that holds it now
_MOVED = {
    "RGBDFrame": "resireg.sources.frames",
    "SkippedFrame": "resireg.sources.frames",
    "FrameCounts": "resireg.sources.frames",
    "windows": "resireg.sources.frames",
    "pair_nearest": "resireg.sources.pairing",
    "pose_matrix": "resireg.sources.pairing",
    "PoseTrack": "resireg.sources.pairing",
}
__all__ = list(_MOVED)


def __getattr__(name: str) -> Any:
    if name in _MOVED:
        warnings.warn(
            f"resireg_train.data.rgbd.{name} moved to {_MOVED[name]}.{name}; "
            "this alias goes in the next release",
            DeprecationWarning,
            stacklevel=2,
        )
        return getattr(importlib.import_module(_MOVED[name]), name)
    raise AttributeError(f"module 'resireg_train.data.rgbd' has no attribute {name!r}")
