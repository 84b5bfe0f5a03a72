"""Deprecated: the TUM RGB-D reader moved to :mod:`resireg.sources.tum` (the robot side
installs it without Lightning or Hydra; ``TumSource`` takes no ``key`` any more). This module
re-exports the old names, with a ``DeprecationWarning``, for one release."""

from resireg.deprecation import moved

#: old name -> the module that holds it now
_MOVED = {
    "CAMERAS": "resireg.sources.tum",
    "DEPTH_SCALE": "resireg.sources.tum",
    "TumSource": "resireg.sources.tum",
    "read_list": "resireg.sources.tum",
    "read_trajectory": "resireg.sources.tum",
}
__all__ = list(_MOVED)
__getattr__ = moved("resireg_train.data.tum", _MOVED)
