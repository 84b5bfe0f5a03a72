"""Posed RGB-D frame sources for the semantic map, on the robot side: ``pip install
"resireg[robot]"`` is all they need (no Lightning, Hydra or ``datasets``).

- :mod:`~resireg.sources.frames`: the records (:class:`RGBDFrame`, :class:`SkippedFrame`), their
  tally (:class:`FrameCounts`), what a source is (:class:`FrameSource`, :class:`MessageSource`)
  and :func:`windows`, the ``[B, ...]`` tensors :meth:`resireg.mapping.SemanticMap.add` takes;
- :mod:`~resireg.sources.pairing`: timestamp pairing, pose tracks, the tf tree, stamp faults;
- :mod:`~resireg.sources.messages`: ROS message -> numpy (rosbags' and rclpy's messages alike);
- the readers: :mod:`~resireg.sources.rosbag` (ROS 1 / ROS 2 bags), :mod:`~resireg.sources.tum`
  (TUM RGB-D), :mod:`~resireg.sources.scannet` (a ScanNet scene export),
  :mod:`~resireg.sources.nerfstudio` (a Nerfstudio ``transforms.json`` folder).

The kinds of source, their settings and their rules are the table
:data:`resireg.specs.sources.SOURCE_SPECS` (its docstring: adding a source). The library's
messages name its own arguments (``path='run.bag': no such bag``); ``resireg-map`` adds the
config path (``source.path=...``).

The names below load on first use (PEP 562).

Imports ``resireg.specs``, ``resireg.errors`` and ``resireg.models``' image helpers. May be
imported by ``resireg.mapping``, ``resireg.ros2`` (the live source shares the bag reader's
keyword set, :class:`~resireg.sources.rosbag.RosKeys`) and ``resireg_train`` (``resireg-map``,
the datasets).
"""

from __future__ import annotations

from resireg import lazy_names

__all__ = [
    "BagSource",
    "BagTopics",
    "FrameCounts",
    "FrameSource",
    "MessageSource",
    "NerfstudioSource",
    "RGBDFrame",
    "RosKeys",
    "ScanNetSource",
    "SkippedFrame",
    "TumSource",
    "windows",
]

_NAMES = {
    "RGBDFrame": "resireg.sources.frames",
    "SkippedFrame": "resireg.sources.frames",
    "FrameCounts": "resireg.sources.frames",
    "FrameSource": "resireg.sources.frames",
    "MessageSource": "resireg.sources.frames",
    "windows": "resireg.sources.frames",
    "BagSource": "resireg.sources.rosbag",
    "BagTopics": "resireg.sources.rosbag",
    "RosKeys": "resireg.sources.rosbag",
    "TumSource": "resireg.sources.tum",
    "ScanNetSource": "resireg.sources.scannet",
    "NerfstudioSource": "resireg.sources.nerfstudio",
}


__getattr__ = lazy_names("resireg.sources", _NAMES)
