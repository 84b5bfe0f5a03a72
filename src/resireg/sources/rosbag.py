"""Posed RGB-D frames from a ROS 2 bag (sqlite3 or MCAP) or a ROS 1 bag, read with ``rosbags``
(pure Python, no ROS install; ``rosbags.highlevel.AnyReader``), for ``resireg-map``
(docs/maps.md#robot-maps-semanticmap).

Topics (:class:`BagTopics`; :func:`open_bag` takes them as keywords, the keys of
``conf/source/rosbag.yaml`` that the live source shares, :class:`RosKeys`), decoded by
:mod:`resireg.sources.messages`:

- colour: ``sensor_msgs/Image`` (``rgb8``, ``bgr8``, ``rgba8``, ``bgra8``, ``mono8``) or
  ``sensor_msgs/CompressedImage`` (JPEG / PNG);
- depth: ``sensor_msgs/Image`` ``16UC1`` (millimetres, ``depth_scale`` 0.001) or ``32FC1``
  (metres), or a ``CompressedImage`` of ``compressedDepth`` PNG; 0 and non-finite depths are
  "no depth";
- ``sensor_msgs/CameraInfo`` of the *depth* image: its ``K`` (rectified images assumed: the
  distortion is not applied);
- the camera pose at the depth image's stamp: ``/tf`` + ``/tf_static``, the chain from
  ``world_frame`` to the camera frame (``camera_frame``, default the depth image's
  ``header.frame_id``, an optical frame: x right, y down, z forward), or a
  ``geometry_msgs/PoseStamped`` / ``nav_msgs/Odometry`` topic (the pose of its body frame in
  the world; the tf chain from that body frame to the camera frame is applied when the bag has
  it).

Every depth message is a candidate frame (stamp = its ``header.stamp``): the colour image of
the nearest stamp within ``tolerance`` seconds (:func:`resireg.sources.pairing.pair_nearest`),
the latest ``CameraInfo`` received up to then (else the first), the pose interpolated at its
stamp (:class:`~resireg.sources.pairing.PoseTrack`, each tf edge its own track, interpolated
across gaps of up to ``max_pose_gap`` seconds; static edges hold at every time). A candidate
without a colour image within the tolerance is ``unpaired``, one without a pose ``no_pose``,
one whose depth or colour message cannot be decoded ``undecodable`` (named ``topic@stamp``,
with the reason), one whose header stamp goes back or repeats on its topic ``bad_stamp`` (a
colour image with such a stamp is never paired), one whose depth image is not of its
``CameraInfo``'s size ``size_mismatch`` (K is not rescaled), one after the point where a
damaged bag's read failed ``damaged``; each is counted and skipped. Colour messages no depth
message took are counted in :attr:`BagSource.unpaired_colour`, messages that cannot be
deserialised by topic in :attr:`BagSource.corrupt`.

The bag is read twice: once for the stamps, the camera info and the poses, then for the
images of the paired frames in time order, holding only the images still awaited; a message is
found again by its (bag time, header stamp), as bag times alone may collide.
"""

from __future__ import annotations

import inspect
from collections import Counter, defaultdict
from collections.abc import Callable, Iterator, Sequence
from dataclasses import MISSING, asdict, dataclass, fields
from pathlib import Path
from typing import Any

import numpy as np

from resireg.errors import DataError
from resireg.sources.frames import RGBDFrame, SkippedFrame, SourceNotFoundError
from resireg.sources.messages import (
    camera_intrinsics,
    camera_size,
    decode_colour,
    decode_depth,
    pose_msg_matrix,
    stamp_seconds,
    transform_matrix,
)
from resireg.sources.pairing import PoseTrack, TfTree, pair_nearest, stamp_faults

__all__ = ["BagSource", "BagTopics", "DamagedBagError", "MissingTopicError", "RosKeys",
           "open_bag", "takes_ros_keys", "decode_colour", "decode_depth"]  # fmt: skip

_IMAGE = ("sensor_msgs/msg/Image",)
_COMPRESSED = ("sensor_msgs/msg/CompressedImage",)
_INFO = ("sensor_msgs/msg/CameraInfo",)
_TF = ("tf2_msgs/msg/TFMessage",)
_POSES = ("geometry_msgs/msg/PoseStamped", "nav_msgs/msg/Odometry")


class MissingTopicError(DataError):
    """Topics that are not in the bag (or have another type), all of them in one message that
    names each argument (``colour_topic='/cam': ...``) and lists the bag's topics and types
    once."""


class DamagedBagError(DataError):
    """The bag cannot be opened (truncated, overwritten, not a bag): names ``path``."""


@dataclass(frozen=True)
class BagTopics:
    """Where the frames are in a bag (module docstring)."""

    colour: str
    depth: str
    camera_info: str
    pose: str | None = None
    tf: str = "/tf"
    tf_static: str = "/tf_static"
    world_frame: str = "map"
    camera_frame: str | None = None


@dataclass(frozen=True, kw_only=True)
class RosKeys:
    """The keys a ROS recording (``rosbag``) and live ROS 2 topics (``ros2``,
    :class:`resireg.ros2.source.LiveSource`) share, with their defaults: where the frames are
    and how they pair (``conf/source/rosbag.yaml``, which ``conf/source/ros2.yaml`` pulls in;
    their rules are the source table's, :data:`resireg.specs.sources.SOURCE_SPECS`). The one
    list of them: both readers take them as keywords through :func:`takes_ros_keys`. The
    topics and frames are a bag's :class:`BagTopics` (:attr:`topics`), whose defaults they
    take."""

    colour_topic: str
    depth_topic: str
    camera_info_topic: str
    pose_topic: str | None = BagTopics.pose
    tf_topic: str = BagTopics.tf
    tf_static_topic: str = BagTopics.tf_static
    world_frame: str = BagTopics.world_frame
    camera_frame: str | None = BagTopics.camera_frame
    depth_scale: float = 0.001
    tolerance: float = 0.02
    max_pose_gap: float = 0.5

    def as_dict(self) -> dict[str, Any]:
        """``keyword -> value``."""
        return asdict(self)

    @property
    def topics(self) -> BagTopics:
        """Where a bag's frames are."""
        return BagTopics(colour=self.colour_topic, depth=self.depth_topic,
                         camera_info=self.camera_info_topic, pose=self.pose_topic,
                         tf=self.tf_topic, tf_static=self.tf_static_topic,
                         world_frame=self.world_frame, camera_frame=self.camera_frame)  # fmt: skip


def takes_ros_keys(function: Callable[..., Any]) -> Callable[..., Any]:
    """``function(..., **keys)`` shown as taking :class:`RosKeys`' fields as keyword-only
    parameters (its ``inspect.signature``, which ``help()`` and the source table's checks
    read), after its own; ``function`` builds ``RosKeys(**keys)`` itself. Hand-written because
    a signature cannot be shared otherwise: the keyword set is typed once, in :class:`RosKeys`."""
    signature = inspect.signature(function)
    own = [p for p in signature.parameters.values() if p.kind is not p.VAR_KEYWORD]
    empty = inspect.Parameter.empty
    keys = [inspect.Parameter(f.name, inspect.Parameter.KEYWORD_ONLY, annotation=f.type,
                              default=empty if f.default is MISSING else f.default)
            for f in fields(RosKeys)]  # fmt: skip
    function.__signature__ = signature.replace(parameters=[*own, *keys])  # type: ignore[attr-defined]
    return function


@takes_ros_keys
def open_bag(path: str | Path, **keys: Any) -> BagSource:
    """The :class:`BagSource` of a bag, from the keys of ``conf/source/rosbag.yaml`` as keywords
    (:class:`RosKeys`; the ``rosbag`` entry of :data:`resireg.specs.sources.SOURCE_SPECS`); it
    opens the bag and checks every topic now, naming each wrong one by its keyword."""
    ros = RosKeys(**keys)
    return BagSource(path, ros.topics, float(ros.tolerance), float(ros.depth_scale),
                     max_pose_gap=float(ros.max_pose_gap))  # fmt: skip


class BagSource:
    """The posed RGB-D frames of a bag (module docstring); iterate for
    :class:`~resireg.sources.frames.RGBDFrame` / :class:`~resireg.sources.frames.SkippedFrame`
    (a :class:`~resireg.sources.frames.MessageSource`). Made by :func:`open_bag` from keywords.
    Errors name this class's arguments and :class:`BagTopics`' as :func:`open_bag` spells them
    (``path='run.bag': no such bag``, ``colour_topic='/cam' is not in the bag``).

    Args:
        path: the bag (a ROS 2 bag folder, an ``.mcap`` / ``.db3`` file's folder, or a ROS 1
            ``.bag`` file).
        topics: :class:`BagTopics`.
        tolerance: seconds between a depth image and its colour image, and beyond the ends of
            a pose stream.
        depth_scale: metres per unit of ``16UC1`` depth.
        max_pose_gap: the longest interval between two pose samples interpolated across.
    """

    def __init__(
        self,
        path: str | Path,
        topics: BagTopics,
        tolerance: float = 0.02,
        depth_scale: float = 0.001,
        *,
        max_pose_gap: float = 0.5,
    ) -> None:
        from rosbags.highlevel import AnyReader

        self.path = Path(path).expanduser()
        if not self.path.exists():
            raise SourceNotFoundError(f"path={str(path)!r}: no such bag")
        if not tolerance > 0:
            raise DataError(f"tolerance={tolerance!r}: expected seconds > 0")
        self.topics, self.tolerance, self.depth_scale = topics, tolerance, depth_scale
        self.max_pose_gap = float(max_pose_gap)
        self._reader_cls = AnyReader
        self.unpaired_colour = 0
        self._scan()

    def _open(self):
        """The opened reader; a bag that cannot be opened (truncated, overwritten, not a bag) is
        a :class:`DamagedBagError` naming ``path`` and what the reader found."""
        reader = self._reader_cls([self.path])
        try:
            reader.open()
        except Exception as err:  # rosbags' ReaderError, apsw's CorruptError, OSError...
            raise DamagedBagError(
                f"path={str(self.path)!r}: the bag cannot be opened: {err} (a "
                "truncated or damaged file, or not a ROS 1 / ROS 2 bag)"
            ) from None
        return reader

    def _connections(self, reader, topic: str | None, types: Sequence[str], name: str,
                     problems: list[str], required: bool = True) -> list:  # fmt: skip
        """The connections of ``topic``; a missing or mistyped one is added to ``problems``
        (all of them are reported together, :meth:`_scan`)."""
        if topic is None:
            return []
        conns = [c for c in reader.connections if c.topic == topic]
        if not conns or conns[0].msgtype not in types:
            if not required and not conns:
                return []
            what = f"has type {conns[0].msgtype}" if conns else "is not in the bag"
            problems.append(f"{name}={topic!r} {what} (expected {' or '.join(types)})")
            return []
        return conns

    def _scan(self) -> None:
        reader = self._open()
        try:
            self._scan_reader(reader)
        finally:
            reader.close()

    def _scan_reader(self, reader) -> None:
        t = self.topics
        problems: list[str] = []
        self.colour_conns = self._connections(reader, t.colour, _IMAGE + _COMPRESSED,
                                              "colour_topic", problems)  # fmt: skip
        self.depth_conns = self._connections(reader, t.depth, _IMAGE + _COMPRESSED,
                                             "depth_topic", problems)  # fmt: skip
        info_conns = self._connections(reader, t.camera_info, _INFO, "camera_info_topic", problems)
        pose_conns = self._connections(reader, t.pose, _POSES, "pose_topic", problems)
        tf_conns = self._connections(reader, t.tf, _TF, "tf_topic", problems, required=False)
        static_conns = self._connections(reader, t.tf_static, _TF, "tf_static_topic", problems,
                                         required=False)  # fmt: skip
        if (
            t.pose is None
            and not (tf_conns or static_conns)
            and not any("tf_topic" in p for p in problems)
        ):
            self._connections(reader, t.tf, _TF, "tf_topic", problems)
        if problems:  # every wrong topic at once, the bag's topics listed once
            present = {c.topic: c.msgtype for c in reader.connections}
            listing = ", ".join(f"{n} ({m})" for n, m in sorted(present.items())) or "none"
            raise MissingTopicError("; ".join(problems) + f". The bag {self.path} has: {listing}")
        self.tf = TfTree(self.tolerance, self.max_pose_gap)
        infos: list[tuple[float, np.ndarray, tuple[int, int]]] = []
        poses: list[tuple[float, np.ndarray]] = []
        self.pose_frame: str | None = None
        # in bag order: (stamp, bag time, frame_id, reason it cannot be used or None)
        depth: list[tuple[float, int, str, str | None]] = []
        colour: list[tuple[float, int]] = []
        self.message_counts: Counter = Counter()  # per topic, messages read
        self.corrupt: Counter = Counter()  # per topic, messages that could not be deserialised
        self.corrupt_examples: list[str] = []
        self.damage: str | None = None  # what stopped the read, for a bag damaged midway
        watched = [*self.colour_conns, *self.depth_conns, *info_conns, *pose_conns,
                   *tf_conns, *static_conns]  # fmt: skip
        static_topic = t.tf_static
        try:
            for conn, bag_time, raw in reader.messages(connections=watched):
                self.message_counts[conn.topic] += 1
                try:
                    msg = reader.deserialize(raw, conn.msgtype)
                    if conn.topic == t.camera_info:
                        k = camera_intrinsics(msg)
                        if not np.isfinite(k).all():
                            raise ValueError(f"non-finite K {k.reshape(-1).tolist()}")
                except Exception as err:  # any deserialisation failure: a corrupt message
                    why = f"not deserialisable: {err}"
                    self.corrupt[conn.topic] += 1
                    if len(self.corrupt_examples) < 20:
                        self.corrupt_examples.append(f"{conn.topic}@bag time {bag_time}: {why}")
                    if conn.topic == t.depth:
                        depth.append((bag_time * 1e-9, bag_time, "", why))
                    continue
                if conn.topic == t.depth:
                    depth.append((stamp_seconds(msg.header), bag_time, msg.header.frame_id, None))
                elif conn.topic == t.colour:
                    colour.append((stamp_seconds(msg.header), bag_time))
                elif conn.topic == t.camera_info:
                    infos.append((stamp_seconds(msg.header), k, camera_size(msg)))
                elif conn.topic == t.pose:
                    p = msg.pose.pose if hasattr(msg, "child_frame_id") else msg.pose
                    poses.append((stamp_seconds(msg.header), pose_msg_matrix(p)))
                    if self.pose_frame is None:
                        self.pose_frame = getattr(msg, "child_frame_id", None) or None
                else:
                    for tr in msg.transforms:
                        self.tf.add(tr.header.frame_id, tr.child_frame_id, stamp_seconds(tr.header),
                                    transform_matrix(tr.transform), conn.topic == static_topic)  # fmt: skip
        except Exception as err:  # the reader failed midway: keep what came before
            self.damage = (f"path={str(self.path)!r} is damaged after "
                           f"{sum(self.message_counts.values())} messages: {err}")  # fmt: skip
        indexed = sum(int(getattr(c, "msgcount", 0) or 0) for c in self.depth_conns)
        self.unread_depth = max(0, indexed - self.message_counts[t.depth]) if self.damage else 0
        self.tf.build()
        if not infos:
            why = f" ({self.corrupt[t.camera_info]} corrupt)" if self.corrupt[t.camera_info] else ""
            raise MissingTopicError(f"camera_info_topic={t.camera_info!r}: no usable message{why}")
        infos.sort(key=lambda x: x[0])
        self.info_stamps = np.array([s for s, _, _ in infos])
        self.infos = [k for _, k, _ in infos]
        self.info_sizes = [hw for _, _, hw in infos]
        self.pose_track = None
        if t.pose is not None:
            if not poses:
                raise MissingTopicError(f"pose_topic={t.pose!r}: no message")
            self.pose_track = PoseTrack([s for s, _ in poses], np.stack([m for _, m in poses]),
                                        self.tolerance, self.max_pose_gap)  # fmt: skip
        # Header stamps that go back or repeat (a restamped or replayed stream): such messages
        # are left out (the frames skipped as bad_stamp, the colour images never paired).
        # (a message that could not be deserialised has no stamp: it takes no part)
        readable = [i for i, d in enumerate(depth) if d[3] is None]
        depth_faults = {readable[j]: why for j, why in stamp_faults(
            [depth[i][:2] for i in readable], t.depth).items()}  # fmt: skip
        self.depth_stamps = sorted(
            ((s, b, f, why if why is not None else depth_faults.get(i))
             for i, (s, b, f, why) in enumerate(depth)), key=lambda x: x[:2])  # fmt: skip
        colour_faults = stamp_faults(colour, t.colour)
        self.colour_stamp_faults = [f"{t.colour}@{colour[i][0]:.6f}: {why}"
                                    for i, why in sorted(colour_faults.items())]  # fmt: skip
        self.colour_stamps = sorted(c for i, c in enumerate(colour) if i not in colour_faults)

    def _camera_pose(self, stamp: float, frame_id: str) -> tuple[np.ndarray | None, str]:
        t = self.topics
        camera = (t.camera_frame or frame_id).lstrip("/")
        if self.pose_track is not None:
            body = self.pose_track.at(stamp)
            if body is None:
                return None, f"no pose on {t.pose} at {stamp:.6f} (gap or end of the stream)"
            if self.pose_frame and self.pose_frame.lstrip("/") != camera:
                chain = self.tf.chain(self.pose_frame, camera)
                if chain is not None:
                    offset = self.tf.lookup(chain, stamp)
                    if offset is None:
                        return None, f"no tf {self.pose_frame} -> {camera} at {stamp:.6f}"
                    body = body @ offset
            return body, ""
        chain = self.tf.chain(t.world_frame, camera)
        if chain is None:
            frames = sorted(self.tf.frames)
            empty = [f"{n} has no message" + (f" ({self.corrupt[n]} corrupt)" if self.corrupt[n]
                                               else "")
                     for n in (t.tf, t.tf_static) if not self.message_counts[n] - self.corrupt[n]]  # fmt: skip
            return None, (f"no tf chain {t.world_frame} -> {camera}"
                          + (f": {', '.join(empty)}" if empty else "")
                          + f" (frames: {frames}; set world_frame / camera_frame)")  # fmt: skip
        pose = self.tf.lookup(chain, stamp)
        if pose is None:
            return (
                None,
                f"no tf {t.world_frame} -> {camera} at {stamp:.6f} (gap or end of a stream)",
            )
        return pose, ""

    def __iter__(self) -> Iterator[RGBDFrame | SkippedFrame]:
        t = self.topics
        colour_times = np.array([s for s, _ in self.colour_stamps])
        match = pair_nearest(np.array([s for s, _, _, _ in self.depth_stamps]), colour_times,
                             self.tolerance)  # fmt: skip
        self.unpaired_colour = int(len(self.colour_stamps) - np.unique(match[match >= 0]).size)
        # stamp, depth (bag time, stamp), colour (bag time, stamp) or None, frame_id
        plan: list[tuple[float, tuple[int, float], tuple[int, float] | None, str]] = []
        out: dict[int, RGBDFrame | SkippedFrame] = {}  # position -> record, emitted in order
        for pos, ((stamp, bag_time, frame_id, why), m) in enumerate(
            zip(self.depth_stamps, match, strict=True)
        ):
            name = f"{t.depth}@{stamp:.6f}"
            if why is not None:
                kind = "bad_stamp" if why.startswith("header stamp") else "undecodable"
                out[pos] = SkippedFrame(name, why, kind)
            elif m < 0:
                out[pos] = SkippedFrame(name, self._unpaired_reason(stamp, colour_times),
                                        "unpaired")  # fmt: skip
            colour_key = None if m < 0 else self.colour_stamps[m][::-1]
            plan.append((stamp, (bag_time, stamp), colour_key, frame_id))
        # Messages are found again by (bag time, header stamp): bag times alone may collide
        # (two messages received in the same nanosecond), and a (bag time, stamp) pair shared
        # by two messages is a duplicate stamp, left out above.
        need_colour: dict[tuple[int, float], list[int]] = defaultdict(list)
        need_depth: dict[tuple[int, float], int] = {}
        for pos, (_, depth_key, colour_key, _) in enumerate(plan):
            if pos not in out:
                need_depth[depth_key] = pos
                need_colour[colour_key].append(pos)
        depth_times = {b for b, _ in need_depth}
        colour_times_needed = {b for b, _ in need_colour}
        colours: dict[int, np.ndarray | str] = {}  # position -> decoded colour or the reason
        depths: dict[int, tuple[np.ndarray, Any]] = {}
        next_pos = 0
        missing = "message missing on the second read"

        def ready(pos: int) -> bool:
            return pos in out or (pos in colours and pos in depths)

        reader = self._open()  # a new reader: its own connection objects, by topic
        try:
            conns = [c for c in reader.connections if c.topic in (t.colour, t.depth)]
            for conn, bag_time, raw in reader.messages(connections=conns):
                is_depth = conn.topic == t.depth
                if not (bag_time in depth_times if is_depth else bag_time in colour_times_needed):
                    continue
                try:
                    msg = reader.deserialize(raw, conn.msgtype)
                except Exception as err:  # read fine the first time: reported as undecodable
                    msg, error = None, err
                key = (bag_time, stamp_seconds(msg.header)) if msg is not None else None
                if is_depth and key in need_depth:
                    pos = need_depth.pop(key)
                    try:
                        if msg is None:
                            raise ValueError(str(error))
                        depths[pos] = (decode_depth(msg, self.depth_scale), msg)
                    except Exception as err:
                        out[pos] = SkippedFrame(f"{t.depth}@{plan[pos][0]:.6f}", str(err),
                                                "undecodable")  # fmt: skip
                elif not is_depth and key in need_colour:
                    waiting = need_colour.pop(key)
                    try:
                        image: np.ndarray | str = decode_colour(msg)
                    except Exception as err:
                        image = f"{t.colour}@{key[1]:.6f}: {err}"
                    for pos in waiting:
                        colours[pos] = image
                while next_pos < len(plan) and ready(next_pos):
                    yield self._record(next_pos, plan, out, colours, depths)
                    next_pos += 1
        except Exception as err:  # damaged midway: the frames after it are counted as damaged
            missing = f"not read: path={str(self.path)!r} is damaged there ({err})"
            self.damage = self.damage or missing
        finally:
            reader.close()
        while next_pos < len(plan):  # messages never seen (a damaged bag)
            if not ready(next_pos):
                kind = "undecodable" if missing.startswith("message") else "damaged"
                out[next_pos] = SkippedFrame(f"{t.depth}@{plan[next_pos][0]:.6f}", missing, kind)
            yield self._record(next_pos, plan, out, colours, depths)
            next_pos += 1
        for i in range(self.unread_depth):  # in the bag's index, after the damage
            yield SkippedFrame(f"{t.depth}#unread-{i + 1}", self.damage or "", "damaged")

    def _unpaired_reason(self, stamp: float, colour_times: np.ndarray) -> str:
        t = self.topics
        why = f"no {t.colour} image within {self.tolerance} s"
        if colour_times.size:
            nearest = colour_times[np.abs(colour_times - stamp).argmin()]
            return f"{why} (the nearest is {nearest - stamp:+.3f} s away)"
        faults = len(self.colour_stamp_faults)
        return f"{why} ({t.colour} has no usable message" + (
            f": {faults} left out for their stamps)" if faults else ")"
        )

    def _record(self, pos, plan, out, colours, depths) -> RGBDFrame | SkippedFrame:
        if pos in out:
            colours.pop(pos, None), depths.pop(pos, None)
            return out.pop(pos)
        stamp, _, _, frame_id = plan[pos]
        name = f"{self.topics.depth}@{stamp:.6f}"
        image = colours.pop(pos)
        depth, _ = depths.pop(pos)
        if isinstance(image, str):
            return SkippedFrame(name, f"colour {image}", "undecodable")
        pose, why = self._camera_pose(stamp, frame_id)
        if pose is None:
            return SkippedFrame(name, why, "no_pose")
        i = max(int(np.searchsorted(self.info_stamps, stamp, side="right")) - 1, 0)
        k, (h, w) = self.infos[i], self.info_sizes[i]
        if h and w and depth.shape != (h, w):  # (0 x 0: a CameraInfo that does not say)
            return SkippedFrame(
                name,
                f"depth image {depth.shape[1]}x{depth.shape[0]} but {self.topics.camera_info}"
                f"@{self.info_stamps[i]:.6f} is for {w}x{h}: its K is of another resolution "
                "(give the depth image's own camera info)",
                "size_mismatch",
            )
        return RGBDFrame(image, depth, k, pose, stamp, name)
