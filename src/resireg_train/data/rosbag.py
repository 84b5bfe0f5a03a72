"""Deprecated: the ROS bag reader moved to :mod:`resireg.sources.rosbag` and its message
decoders to :mod:`resireg.sources.messages` (the robot side installs them without Lightning or
Hydra; ``BagSource`` takes no ``key`` any more). This module re-exports the old names, with a
``DeprecationWarning``, for one release."""

from resireg.deprecation import moved

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
__getattr__ = moved("resireg_train.data.rosbag", _MOVED)
