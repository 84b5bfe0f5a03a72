"""Deprecated: the frame record, the pairing and the windows moved to
:mod:`resireg.sources.frames` and :mod:`resireg.sources.pairing` (the robot side installs them
without Lightning or Hydra). This module re-exports the old names, with a ``DeprecationWarning``,
for one release."""

from resireg.deprecation import moved

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
__getattr__ = moved("resireg_train.data.rgbd", _MOVED)
