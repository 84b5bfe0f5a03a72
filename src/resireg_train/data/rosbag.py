"""Posed RGB-D frames from a ROS 2 bag (sqlite3 or MCAP) or a ROS 1 bag, read with ``rosbags``
(pure Python, no ROS install; ``rosbags.highlevel.AnyReader``), for ``resireg-map``
(docs/design.md section 10.3).

Topics (:class:`BagTopics`, the ``source.*`` keys of ``conf/map.yaml``):

- colour: ``sensor_msgs/Image`` (``rgb8``, ``bgr8``, ``rgba8``, ``bgra8``, ``mono8``) or
  ``sensor_msgs/CompressedImage`` (JPEG / PNG, decoded by PIL);
- depth: ``sensor_msgs/Image`` ``16UC1`` (millimetres, ``depth_scale`` 0.001) or ``32FC1``
  (metres), or a ``CompressedImage`` of ``compressedDepth`` PNG (16UC1; its 12-byte header is
  skipped); 0 and non-finite depths are "no depth";
- ``sensor_msgs/CameraInfo`` of the *depth* image: its ``K`` (rectified images assumed: the
  distortion is not applied);
- the camera pose at the depth image's stamp: ``/tf`` + ``/tf_static``, the chain from
  ``world_frame`` to the camera frame (``camera_frame``, default the depth image's
  ``header.frame_id``, an optical frame: x right, y down, z forward), or a
  ``geometry_msgs/PoseStamped`` / ``nav_msgs/Odometry`` topic (the pose of its body frame in
  the world; the tf chain from that body frame to the camera frame is applied when the bag has
  it).

Every depth message is a candidate frame (stamp = its ``header.stamp``): the colour image of
the nearest stamp within ``tolerance`` seconds (:func:`resireg_train.data.rgbd.pair_nearest`),
the latest ``CameraInfo`` received up to then (else the first), the pose interpolated at its
stamp (:class:`~resireg_train.data.rgbd.PoseTrack`, each tf edge its own track, interpolated
across gaps of up to ``max_pose_gap`` seconds; static edges hold at every time). A candidate without a colour image within the tolerance is ``unpaired``,
one without a pose ``no_pose``, one whose depth or colour message cannot be decoded
``undecodable`` (named ``topic@stamp``, with the reason); each is counted and skipped.
Colour messages no depth message took are counted in :attr:`BagSource.unpaired_colour`.

The bag is read twice: once for the stamps, the camera info and the poses (small messages;
image messages are not deserialised, only their headers), then for the images of the paired
frames in time order, holding only the images still awaited.
"""

from __future__ import annotations

import io
from collections import defaultdict, deque
from collections.abc import Iterator, Sequence
from dataclasses import dataclass
from pathlib import Path
from typing import Any

import numpy as np
from PIL import Image

from resireg_train.data.rgbd import (
    PoseTrack,
    RGBDFrame,
    SkippedFrame,
    pair_nearest,
    pose_matrix,
)

__all__ = ["BagSource", "BagTopics", "MissingTopicError", "decode_colour", "decode_depth"]

_IMAGE = ("sensor_msgs/msg/Image",)
_COMPRESSED = ("sensor_msgs/msg/CompressedImage",)
_INFO = ("sensor_msgs/msg/CameraInfo",)
_TF = ("tf2_msgs/msg/TFMessage",)
_POSES = ("geometry_msgs/msg/PoseStamped", "nav_msgs/msg/Odometry")


class MissingTopicError(ValueError):
    """A configured topic is not in the bag (or has another type); the message lists the bag's
    topics and types."""


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


def _stamp(header: Any) -> float:
    return float(header.stamp.sec) + 1e-9 * float(header.stamp.nanosec)


def decode_colour(msg: Any) -> np.ndarray:
    """``sensor_msgs/Image`` or ``CompressedImage`` -> uint8 RGB ``[H, W, 3]`` (ValueError when
    it cannot be decoded)."""
    if hasattr(msg, "format"):  # CompressedImage
        try:
            with Image.open(io.BytesIO(bytes(msg.data))) as im:
                return np.asarray(im.convert("RGB"), dtype=np.uint8).copy()
        except Exception as err:  # PIL raises many types for corrupt data
            raise ValueError(f"compressed colour ({msg.format!r}) not decodable: {err}") from None
    enc = str(msg.encoding).lower()
    channels = {"rgb8": 3, "bgr8": 3, "rgba8": 4, "bgra8": 4, "mono8": 1}
    if enc not in channels:
        raise ValueError(f"colour encoding {msg.encoding!r}: expected one of {sorted(channels)}")
    h, w, c = int(msg.height), int(msg.width), channels[enc]
    data = np.frombuffer(bytes(msg.data), dtype=np.uint8)
    step = int(msg.step) or w * c
    if data.size < h * step or step < w * c:
        raise ValueError(f"colour {enc} {w}x{h}: {data.size} bytes for step {step}")
    px = data[: h * step].reshape(h, step)[:, : w * c].reshape(h, w, c)
    if enc == "mono8":
        return np.repeat(px, 3, axis=2).copy()
    if enc.startswith("bgr"):
        px = px[..., [2, 1, 0]]
    return np.ascontiguousarray(px[..., :3])


def decode_depth(msg: Any, depth_scale: float = 0.001) -> np.ndarray:
    """``sensor_msgs/Image`` ``16UC1`` (``depth_scale`` metres per unit) or ``32FC1`` (metres),
    or a ``compressedDepth`` PNG -> float32 ``[H, W]`` metres, 0 where there is no depth."""
    if hasattr(msg, "format"):  # CompressedImage: compressedDepth (16UC1 PNG after a header)
        raw = bytes(msg.data)
        start = raw.find(b"\x89PNG")
        if "compresseddepth" not in str(msg.format).lower() or start < 0:
            raise ValueError(
                f"compressed depth format {msg.format!r}: expected compressedDepth png"
            )
        try:
            with Image.open(io.BytesIO(raw[start:])) as im:
                units = np.asarray(im).astype(np.float32)
        except Exception as err:
            raise ValueError(f"compressedDepth png not decodable: {err}") from None
        return units * np.float32(depth_scale)
    enc = str(msg.encoding).upper()
    dtypes = {"16UC1": np.uint16, "MONO16": np.uint16, "32FC1": np.float32}
    if enc not in dtypes:
        raise ValueError(f"depth encoding {msg.encoding!r}: expected 16UC1 or 32FC1")
    h, w = int(msg.height), int(msg.width)
    dt = np.dtype(dtypes[enc]).newbyteorder(">" if msg.is_bigendian else "<")
    step = int(msg.step) or w * dt.itemsize
    data = np.frombuffer(bytes(msg.data), dtype=np.uint8)
    if data.size < h * step or step < w * dt.itemsize:
        raise ValueError(f"depth {enc} {w}x{h}: {data.size} bytes for step {step}")
    rows = data[: h * step].reshape(h, step)[:, : w * dt.itemsize]
    values = np.ascontiguousarray(rows).view(dt).reshape(h, w).astype(np.float32)
    if enc == "32FC1":
        return np.where(np.isfinite(values) & (values > 0), values, 0).astype(np.float32)
    return values * np.float32(depth_scale)


def _intrinsics(info: Any) -> np.ndarray:
    k = getattr(info, "k", None)
    if k is None:
        k = info.K  # ROS 1 field name
    return np.asarray(k, dtype=np.float64).reshape(3, 3)


def _transform(t: Any) -> np.ndarray:
    tr, q = t.translation, t.rotation
    return pose_matrix((tr.x, tr.y, tr.z), (q.x, q.y, q.z, q.w))


def _pose(p: Any) -> np.ndarray:
    return pose_matrix((p.position.x, p.position.y, p.position.z),
                       (p.orientation.x, p.orientation.y, p.orientation.z, p.orientation.w))  # fmt: skip


class _TfTree:
    """The tf graph: per (parent, child) edge a :class:`PoseTrack`; :meth:`lookup` composes the
    chain from one frame to another at a time (edges walked either way, inverted backwards)."""

    def __init__(self, tolerance: float, max_gap: float) -> None:
        self.tolerance, self.max_gap = tolerance, max_gap
        self.samples: dict[tuple[str, str], list[tuple[float, np.ndarray]]] = defaultdict(list)
        self.static: set[tuple[str, str]] = set()
        self.tracks: dict[tuple[str, str], PoseTrack] = {}

    def add(self, parent: str, child: str, stamp: float, m: np.ndarray, static: bool) -> None:
        edge = (parent.lstrip("/"), child.lstrip("/"))
        self.samples[edge].append((stamp, m))
        if static:
            self.static.add(edge)

    def build(self) -> None:
        for edge, items in self.samples.items():
            stamps, poses = zip(*items, strict=True)
            self.tracks[edge] = PoseTrack(stamps, np.stack(poses), self.tolerance, self.max_gap,
                                          static=edge in self.static)  # fmt: skip

    @property
    def frames(self) -> set[str]:
        return {f for edge in self.tracks for f in edge}

    def chain(self, source: str, target: str) -> list[tuple[tuple[str, str], bool]] | None:
        """Edges from ``source`` to ``target`` (breadth first), each with ``True`` if walked
        parent -> child."""
        source, target = source.lstrip("/"), target.lstrip("/")
        nbrs: dict[str, list[tuple[str, tuple[str, str], bool]]] = defaultdict(list)
        for parent, child in self.tracks:
            nbrs[parent].append((child, (parent, child), True))
            nbrs[child].append((parent, (parent, child), False))
        prev: dict[str, tuple[str, tuple[str, str], bool] | None] = {source: None}
        todo = deque([source])
        while todo:
            node = todo.popleft()
            if node == target:
                break
            for nxt, edge, forward in nbrs[node]:
                if nxt not in prev:
                    prev[nxt] = (node, edge, forward)
                    todo.append(nxt)
        if target not in prev:
            return None
        path, node = [], target
        while prev[node] is not None:
            node_prev, edge, forward = prev[node]
            path.append((edge, forward))
            node = node_prev
        return path[::-1]

    def lookup(self, chain, t: float) -> np.ndarray | None:
        """``T_source_target`` at ``t`` along ``chain`` (``None`` if an edge has no pose)."""
        out = np.eye(4)
        for edge, forward in chain:
            m = self.tracks[edge].at(t)
            if m is None:
                return None
            out = out @ (m if forward else np.linalg.inv(m))
        return out


class BagSource:
    """The posed RGB-D frames of a bag (module docstring); iterate for
    :class:`~resireg_train.data.rgbd.RGBDFrame` / :class:`~resireg_train.data.rgbd.SkippedFrame`.

    Args:
        path: the bag (a ROS 2 bag folder, an ``.mcap`` / ``.db3`` file's folder, or a ROS 1
            ``.bag`` file).
        topics: :class:`BagTopics`.
        tolerance: seconds between a depth image and its colour image, and beyond the ends of
            a pose stream.
        depth_scale: metres per unit of ``16UC1`` depth.
        max_pose_gap: the longest interval between two pose samples interpolated across.
        key: the config key named in errors.
    """

    def __init__(
        self,
        path: str | Path,
        topics: BagTopics,
        tolerance: float = 0.02,
        depth_scale: float = 0.001,
        key: str = "source",
        max_pose_gap: float = 0.5,
    ) -> None:
        from rosbags.highlevel import AnyReader

        self.path = Path(path).expanduser()
        if not self.path.exists():
            raise FileNotFoundError(f"{key}.path={str(path)!r}: no such bag")
        if not tolerance > 0:
            raise ValueError(f"{key}.tolerance={tolerance!r}: expected seconds > 0")
        self.topics, self.tolerance, self.depth_scale, self.key = (
            topics,
            tolerance,
            depth_scale,
            key,
        )
        self.max_pose_gap = float(max_pose_gap)
        self._reader_cls = AnyReader
        self.unpaired_colour = 0
        self._scan()

    def _open(self):
        return self._reader_cls([self.path])

    def _connections(self, reader, topic: str | None, types: Sequence[str], name: str,
                     required: bool = True) -> list:  # fmt: skip
        present = {c.topic: c.msgtype for c in reader.connections}
        if topic is None:
            return []
        conns = [c for c in reader.connections if c.topic == topic]
        if not conns or conns[0].msgtype not in types:
            if not required and not conns:
                return []
            listing = ", ".join(f"{t} ({m})" for t, m in sorted(present.items())) or "none"
            what = f"has type {conns[0].msgtype}" if conns else "is not in the bag"
            raise MissingTopicError(
                f"{self.key}.{name}={topic!r} {what} (expected {' or '.join(types)}); "
                f"the bag {self.path} has: {listing}"
            )
        return conns

    def _scan(self) -> None:
        t = self.topics
        with self._open() as reader:
            self.colour_conns = self._connections(reader, t.colour, _IMAGE + _COMPRESSED,
                                                  "colour_topic")  # fmt: skip
            self.depth_conns = self._connections(reader, t.depth, _IMAGE + _COMPRESSED,
                                                 "depth_topic")  # fmt: skip
            info_conns = self._connections(reader, t.camera_info, _INFO, "camera_info_topic")
            pose_conns = self._connections(reader, t.pose, _POSES, "pose_topic")
            tf_conns = self._connections(reader, t.tf, _TF, "tf_topic", required=False)
            static_conns = self._connections(reader, t.tf_static, _TF, "tf_static_topic",
                                             required=False)  # fmt: skip
            if t.pose is None and not (tf_conns or static_conns):
                self._connections(reader, t.tf, _TF, "tf_topic")  # the error, listing topics
            self.tf = _TfTree(self.tolerance, self.max_pose_gap)
            infos: list[tuple[float, np.ndarray]] = []
            poses: list[tuple[float, np.ndarray]] = []
            self.pose_frame: str | None = None
            self.depth_stamps: list[tuple[float, int, str]] = []  # (stamp, bag time, frame_id)
            self.colour_stamps: list[tuple[float, int]] = []
            self.bad: dict[tuple[str, int], str] = {}  # (topic, bag time) -> reason
            watched = [*self.colour_conns, *self.depth_conns, *info_conns, *pose_conns,
                       *tf_conns, *static_conns]  # fmt: skip
            static_topic = t.tf_static
            for conn, bag_time, raw in reader.messages(connections=watched):
                try:
                    msg = reader.deserialize(raw, conn.msgtype)
                except Exception as err:  # any deserialisation failure: a corrupt message
                    self.bad[(conn.topic, bag_time)] = f"not deserialisable: {err}"
                    if conn.topic == t.depth:
                        self.depth_stamps.append((bag_time * 1e-9, bag_time, ""))
                    continue
                if conn.topic == t.depth:
                    self.depth_stamps.append((_stamp(msg.header), bag_time, msg.header.frame_id))
                elif conn.topic == t.colour:
                    self.colour_stamps.append((_stamp(msg.header), bag_time))
                elif conn.topic == t.camera_info:
                    infos.append((_stamp(msg.header), _intrinsics(msg)))
                elif conn.topic == t.pose:
                    p = msg.pose.pose if hasattr(msg, "child_frame_id") else msg.pose
                    poses.append((_stamp(msg.header), _pose(p)))
                    if self.pose_frame is None:
                        self.pose_frame = getattr(msg, "child_frame_id", None) or None
                else:
                    for tr in msg.transforms:
                        self.tf.add(tr.header.frame_id, tr.child_frame_id, _stamp(tr.header),
                                    _transform(tr.transform), conn.topic == static_topic)  # fmt: skip
        self.tf.build()
        if not infos:
            raise MissingTopicError(f"{self.key}.camera_info_topic={t.camera_info!r}: no message")
        infos.sort(key=lambda x: x[0])
        self.info_stamps = np.array([s for s, _ in infos])
        self.infos = [k for _, k in infos]
        self.pose_track = None
        if t.pose is not None:
            if not poses:
                raise MissingTopicError(f"{self.key}.pose_topic={t.pose!r}: no message")
            self.pose_track = PoseTrack([s for s, _ in poses], np.stack([m for _, m in poses]),
                                        self.tolerance, self.max_pose_gap)  # fmt: skip
        self.colour_stamps.sort()
        self.depth_stamps.sort()

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
            return None, (f"no tf chain {t.world_frame} -> {camera!r} (frames: {frames}; set "
                          f"{self.key}.world_frame / {self.key}.camera_frame)")  # fmt: skip
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
        match = pair_nearest(np.array([s for s, _, _ in self.depth_stamps]), colour_times,
                             self.tolerance)  # fmt: skip
        self.unpaired_colour = int(len(self.colour_stamps) - np.unique(match[match >= 0]).size)
        plan: list[tuple[float, int, int | None, str]] = []  # stamp, depth time, colour time
        out: dict[int, RGBDFrame | SkippedFrame] = {}  # position -> record, emitted in order
        for pos, ((stamp, bag_time, frame_id), m) in enumerate(
            zip(self.depth_stamps, match, strict=True)
        ):
            name = f"{t.depth}@{stamp:.6f}"
            if (t.depth, bag_time) in self.bad:
                out[pos] = SkippedFrame(name, self.bad[(t.depth, bag_time)], "undecodable")
            elif m < 0:
                out[pos] = SkippedFrame(name, f"no {t.colour} image within {self.tolerance} s",
                                        "unpaired")  # fmt: skip
            plan.append((stamp, bag_time, None if m < 0 else self.colour_stamps[m][1], frame_id))
        need_colour: dict[int, list[int]] = defaultdict(list)  # colour bag time -> positions
        need_depth: dict[int, int] = {}
        for pos, (_, depth_time, colour_time, _) in enumerate(plan):
            if pos not in out:
                need_depth[depth_time] = pos
                need_colour[colour_time].append(pos)
        colours: dict[int, np.ndarray | str] = {}  # position -> decoded colour or the reason
        depths: dict[int, tuple[np.ndarray, Any]] = {}
        next_pos = 0

        def ready(pos: int) -> bool:
            return pos in out or (pos in colours and pos in depths)

        with self._open() as reader:  # a new reader: its own connection objects, by topic
            conns = [c for c in reader.connections if c.topic in (t.colour, t.depth)]
            for conn, bag_time, raw in reader.messages(connections=conns):
                is_depth = conn.topic == t.depth
                if is_depth and bag_time in need_depth:
                    pos = need_depth.pop(bag_time)
                    try:
                        msg = reader.deserialize(raw, conn.msgtype)
                        depths[pos] = (decode_depth(msg, self.depth_scale), msg)
                    except Exception as err:
                        out[pos] = SkippedFrame(f"{t.depth}@{plan[pos][0]:.6f}", str(err),
                                                "undecodable")  # fmt: skip
                elif not is_depth and bag_time in need_colour:
                    waiting = need_colour.pop(bag_time)
                    try:
                        image: np.ndarray | str = decode_colour(
                            reader.deserialize(raw, conn.msgtype)
                        )
                    except Exception as err:
                        stamp = next(s for s, b in self.colour_stamps if b == bag_time)
                        image = f"{t.colour}@{stamp:.6f}: {err}"
                    for pos in waiting:
                        colours[pos] = image
                while next_pos < len(plan) and ready(next_pos):
                    yield self._record(next_pos, plan, out, colours, depths)
                    next_pos += 1
        while next_pos < len(plan):  # messages never seen (a truncated bag)
            if not ready(next_pos):
                out[next_pos] = SkippedFrame(
                    f"{t.depth}@{plan[next_pos][0]:.6f}",
                    "message missing on the second read",
                    "undecodable",
                )
            yield self._record(next_pos, plan, out, colours, depths)
            next_pos += 1

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
        i = int(np.searchsorted(self.info_stamps, stamp, side="right")) - 1
        k = self.infos[max(i, 0)]
        return RGBDFrame(image, depth, k, pose, stamp, name)
