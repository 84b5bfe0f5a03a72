"""The map's frame sources by ``kind``: one entry each, the only list of them.

``resireg-map`` selects a source with its config group (``resireg-map source=tum
source.path=...``; ``conf/map.yaml``'s defaults list holds ``- source: rosbag``), looks the
block's ``kind`` up here, checks the block's keys and values against the entry
(:func:`source_errors`, before torch loads), and calls the entry's ``target`` with the block's
keys as keywords (:meth:`SourceSpec.arguments`): the target returns a
:class:`~resireg.sources.frames.FrameSource`, which opens and checks the recording at once.

The keys every kind shares (:data:`COMMON_RULES`: ``path``, ``tolerance``, ``max_pose_gap``,
``frame_skip``, ``limit``, ``max_depth``) are in ``conf/source/_common.yaml``, which each
``conf/source/<kind>.yaml`` pulls in through its ``defaults``; ``frame_skip``, ``limit`` and
``max_depth`` are the windows' (:func:`resireg.sources.frames.windows`), the others the source's
where it takes them (:attr:`SourceSpec.common`). ``path`` is required of a kind that reads a
recording; a kind that takes none (``ros2``: live topics) has ``path: null`` in its file, and
any other value is refused. A kind's own keys and their rules are its entry's
:attr:`SourceSpec.keys`. The ``conf/source/`` files of a kind are found by scanning the folder
for their ``kind`` (:meth:`~resireg.specs.table.SpecTable.configs`); a kind's file may pull in
another kind's (``ros2.yaml``: ``defaults: [rosbag, _self_]``, the topics and frames of a bag
with their defaults typed once).

``ros2``, the live source, is an entry like the others: its reader is the ROS 2 side's
(:class:`resireg.ros2.source.LiveSource`, the ``robot`` extra), and the live node
``resireg-ros2`` reads its pairing keys (``max_wait``, ``buffer_size``, ``camera_offset``,
``qos``) from the same ``conf/source/ros2.yaml``. Another installed package adds kinds with an
entry point in the group ``resireg.sources`` naming a :class:`SourceSpec` (looked up only for a
kind the built-in table lacks).

Adding a map source:

1. one module in ``resireg/sources/`` with the reader: a class (or a function) that takes the
   recording's ``path`` (unless it reads none) and the kind's keys as keywords, checks them when called (errors derive
   from :class:`resireg.errors.ResiregError` and name the argument: ``path='x': ...``), and
   yields :class:`~resireg.sources.frames.RGBDFrame` / :class:`~resireg.sources.frames.SkippedFrame`
   records (a file or message that cannot be used is a counted, named skip, never fatal);
2. one :class:`SourceSpec` below: its ``kind``, its ``target`` (``"resireg.sources.<module>:
   <Class>"``), the common keys it takes, its own keys with their rules
   (:mod:`resireg.specs.rules`), a one-line summary;
3. one ``conf/source/<kind>.yaml``: ``defaults: [_common, _self_]``, ``kind: <kind>`` and its
   own keys with their defaults and a comment each.

``tests/resireg/sources/test_sources.py`` checks every entry against its file and its rules; ``resireg-map
source=<kind>`` then works.

Torch-free: this module imports nothing but :mod:`resireg.specs` (the readers load with
:meth:`SourceSpec.load`).
"""

from __future__ import annotations

import math
from collections.abc import Callable, Mapping
from dataclasses import dataclass, field
from typing import Any

from resireg.specs.rules import Rule, integer, is_num, number, one_of, optional_int
from resireg.specs.table import SpecTable

__all__ = [
    "COMMON_RULES",
    "LIVE_RULES",
    "NO_PATH",
    "SOURCE_ENTRY_POINTS",
    "SOURCE_SPECS",
    "TUM_CAMERAS",
    "WINDOW_KEYS",
    "SourceSpec",
    "source_errors",
]

#: The entry-point group of source kinds from other packages.
SOURCE_ENTRY_POINTS = "resireg.sources"

#: ``[fx, fy, cx, cy]`` of the TUM RGB-D cameras (TUM's file_formats page, "Intrinsic Camera
#: Calibration"); ``ros_default`` is what the depth registration used.
TUM_CAMERAS: dict[str, tuple[float, float, float, float]] = {
    "ros_default": (525.0, 525.0, 319.5, 239.5),
    "fr1": (517.3, 516.5, 318.6, 255.3),
    "fr2": (520.9, 521.0, 325.1, 249.7),
    "fr3": (535.4, 539.2, 320.1, 247.6),
}


def _text(what: str) -> Rule:
    return (lambda v: isinstance(v, str) and v.strip() != ""), what


def _optional_text(what: str) -> Rule:
    return (lambda v: v is None or (isinstance(v, str) and v.strip() != "")), f"null or {what}"


def _optional_positive(what: str) -> Rule:
    def check(v: Any) -> bool:
        return v is None or (is_num(v) and math.isfinite(v) and v > 0)

    return check, f"null or {what}"


def _camera_offset(v: Any) -> bool:
    if not isinstance(v, (list, tuple)) or len(v) != 7 or not all(is_num(x) for x in v):
        return False
    return all(math.isfinite(x) for x in v) and math.hypot(*v[3:]) > 1e-9


def _intrinsics(v: Any) -> bool:
    if v is None:
        return True
    if not isinstance(v, (list, tuple)) or len(v) != 4:
        return False
    return all(is_num(x) and math.isfinite(x) for x in v) and v[0] > 0 and v[1] > 0


#: The keys every source block holds (``conf/source/_common.yaml``), with their rules.
COMMON_RULES: dict[str, Rule] = {
    "path": ((lambda v: isinstance(v, str) and v.strip() not in ("", "???")),
             "a path: the recording to map"),
    "tolerance": number(0, strict=True, finite=True),
    "max_pose_gap": number(0, strict=True, finite=True),
    "frame_skip": integer(0),
    "limit": optional_int(1),
    "max_depth": _optional_positive("metres > 0 (finite)"),
}  # fmt: skip
#: The common keys the windows take (:func:`resireg.sources.frames.windows`), not the source.
WINDOW_KEYS = ("frame_skip", "limit", "max_depth")
#: ``path``'s rule for a kind that reads no recording (``path`` not in its
#: :attr:`SourceSpec.common`).
NO_PATH: Rule = ((lambda v: v is None),
                 "null: this source reads live topics, no recording (a bag: source=rosbag "
                 "source.path=...)")  # fmt: skip


@dataclass(frozen=True)
class SourceSpec:
    """One kind of map source.

    Attributes:
        kind: ``source.kind`` of its ``conf/source/`` block.
        target: its reader, ``"module:attribute"``: a callable taking :meth:`arguments` as
            keywords and returning a :class:`~resireg.sources.frames.FrameSource`.
        summary: one line: what it reads.
        keys: its own keys (beyond :data:`COMMON_RULES`) and their rules.
        common: the common keys its target takes (``path`` where it reads a recording: a
            kind without it must have ``path: null``, :data:`NO_PATH`; ``tolerance`` and
            ``max_pose_gap`` where it pairs stamps or interpolates poses).
    """

    kind: str
    target: str
    summary: str
    keys: Mapping[str, Rule] = field(default_factory=dict)
    common: tuple[str, ...] = ("path",)

    @property
    def rules(self) -> dict[str, Rule]:
        """Every key of its block (but ``kind``) and its rule."""
        rules = {**COMMON_RULES, **self.keys}
        if "path" not in self.common:
            rules["path"] = NO_PATH
        return rules

    @property
    def configs(self) -> tuple[str, ...]:
        """Its ``conf/source/<name>.yaml`` files (their ``kind`` is this one)."""
        return SOURCE_SPECS.configs(self.kind)

    def arguments(self, block: Mapping[str, Any]) -> dict[str, Any]:
        """The keywords of its target from a source block."""
        return {name: block[name] for name in (*self.common, *self.keys) if name in block}

    def load(self) -> Callable[..., Any]:
        """The reader (imports it)."""
        from resireg.specs.table import load

        return load(self.target)


_TOPIC = "a topic name"
#: The topics and frames of a ROS recording or a live ROS 2 graph (``rosbag``, ``ros2``).
_ROS_KEYS: dict[str, Rule] = {
    "colour_topic": _text(_TOPIC), "depth_topic": _text(_TOPIC),
    "camera_info_topic": _text(_TOPIC), "pose_topic": _optional_text(_TOPIC),
    "tf_topic": _text(_TOPIC), "tf_static_topic": _text(_TOPIC),
    "world_frame": _text("a tf frame"), "camera_frame": _optional_text("a tf frame"),
    "depth_scale": number(0, strict=True, finite=True),
}  # fmt: skip
#: The live source's own keys (``conf/source/ros2.yaml``); ``resireg-ros2`` reads ``max_wait``,
#: ``buffer_size``, ``camera_offset`` and ``qos`` from the same file, with these rules.
LIVE_RULES: dict[str, Rule] = {
    "idle": _optional_positive("seconds > 0 (finite)"),
    "max_wait": number(0, strict=True, finite=True),
    "buffer_size": integer(2),
    "camera_offset": (_camera_offset,
                      "[x, y, z, qx, qy, qz, qw]: 7 finite numbers, a non-zero quaternion"),
    "qos": one_of(("sensor_data", "reliable")),
}  # fmt: skip
#: ``kind -> spec``.
SOURCE_SPECS: SpecTable[SourceSpec] = SpecTable(
    "map source kind",
    (
        SourceSpec(
            "rosbag", "resireg.sources.rosbag:open_bag",
            "a ROS 2 bag (sqlite3 or MCAP) or a ROS 1 bag: colour, depth, CameraInfo, /tf or a "
            "pose topic",
            _ROS_KEYS,
            common=("path", "tolerance", "max_pose_gap"),
        ),
        SourceSpec(
            "tum", "resireg.sources.tum:TumSource",
            "a TUM RGB-D sequence folder: rgb.txt, depth.txt, groundtruth.txt",
            {"camera": ((lambda v: isinstance(v, str) and v in TUM_CAMERAS),
                        f"one of {list(TUM_CAMERAS)}"),
             "intrinsics": (_intrinsics, "null or [fx, fy, cx, cy] (finite, fx and fy > 0)")},
            common=("path", "tolerance", "max_pose_gap"),
        ),
        SourceSpec(
            "scannet", "resireg.sources.scannet:ScanNetSource",
            "a ScanNet scene export folder: color/, depth/, pose/, intrinsic/",
        ),
        SourceSpec(
            "nerfstudio", "resireg.sources.nerfstudio:NerfstudioSource",
            "a Nerfstudio folder: transforms.json with depth_file_path per frame",
            {"depth_unit_scale_factor": _optional_positive("metres per depth unit > 0")},
        ),
        SourceSpec(
            "ros2", "resireg.ros2.source:LiveSource",
            "live ROS 2 topics (a camera driver, or ros2 bag play): colour, depth, CameraInfo, "
            "tf or a pose topic; ends after limit frames, idle seconds or Ctrl-C",
            {**_ROS_KEYS, **LIVE_RULES},
            common=("tolerance", "max_pose_gap"),
        ),
    ),
    name="kind",
    where="resireg.specs.sources",
    conf="source",
    entry_points=SOURCE_ENTRY_POINTS,
)  # fmt: skip


def source_errors(block: Mapping[str, Any]) -> list[str]:
    """What is wrong with a source block (a composed ``conf/source/<kind>.yaml``), each message
    naming the block's key as the library names an argument (``path='x': expected ...``; a
    config's boundary writes it ``source.path=...``, ``resireg_train.config.errors.
    block_errors``): an unknown kind (with the closest kinds), a block whose keys are another
    kind's (``kind=tum`` set on the rosbag block: select the source with its config group,
    ``source=tum``), keys the kind lacks or does not know, and values that break their rules.
    Empty when the block can be opened."""
    group = SOURCE_SPECS.conf  # the config group that selects a source: source=<kind>
    kind = block.get("kind")
    spec = SOURCE_SPECS.find(kind)
    if spec is None:
        return [SOURCE_SPECS.unknown(kind, "kind") + f" (select a source with {group}=<kind>)"]
    have = set(block) - {"kind"}
    want = set(spec.rules)
    if have != want:
        other = [s.kind for s in SOURCE_SPECS.everything().values()
                 if s.kind != kind and set(s.rules) == have]  # fmt: skip
        if other:
            theirs = sorted(have - want)  # none where the kind's file pulls the other's in (ros2)
            keys = f" (its keys: {theirs})" if theirs else ""
            return [
                f"kind={kind!r} is set on the block of {other[0]!r}{keys}: select the "
                f"source with {group}={kind} (not kind={kind})"
            ]
        errors = []
        if have - want:
            errors.append(f"unknown key(s) {sorted(have - want)} for kind {kind!r} "
                          f"(its keys: {sorted(want)})")  # fmt: skip
        if want - have:
            errors.append(f"no {', '.join(sorted(want - have))} (kind {kind!r}; select "
                          f"the source with {group}={kind})")  # fmt: skip
        return errors
    rules = spec.rules
    return [f"{name}={block[name]!r}: expected {rules[name][1]}"
            for name in rules if not rules[name][0](block[name])]  # fmt: skip
