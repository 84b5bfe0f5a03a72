"""Deprecated: the ROS bag reader moved to :mod:`resireg.sources.rosbag` and its message
decoders to :mod:`resireg.sources.messages` (the robot side installs them without Lightning or
Hydra; ``BagSource`` takes no ``key`` any more). This module re-exports the old names, with a
``DeprecationWarning``, for one release."""

from __future__ import annotations

import importlib
import warnings
from typing import Any

#: old name -> the module that holds it now
_MOVED = {
    "BagSource": "resireg.sources.rosbag",
    "BagTopics": "resireg.sources.rosbag",
    "DamagedBagError": "resireg.sources.rosbag",
    "MissingTopicError": "resireg.sources.rosbag",
    "decode_colour": "resireg.sources.messages",
    "decode_depth": "resireg.sources.messages",
}
__all__ = list(_MOVED)


def __getattr__(name: str) -> Any:
    if name in _MOVED:
        warnings.warn(
            f"resireg_train.data.rosbag.{name} moved to {_MOVED[name]}.{name}; "
            "this alias goes in the next release",
            DeprecationWarning,
            stacklevel=2,
        )
        return getattr(importlib.import_module(_MOVED[name]), name)
    raise AttributeError(f"module 'resireg_train.data.rosbag' has no attribute {name!r}")
