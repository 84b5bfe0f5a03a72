"""``resireg-ros2``'s node: a live :class:`resireg.mapping.SemanticMap` fed by an RGB-D camera
(rclpy; docs/robot.md).

Inputs (topics and frames: the ``source.*`` parameters, as ``resireg-map``'s): colour
(``sensor_msgs/Image`` or ``CompressedImage``), depth (``Image`` ``16UC1`` millimetres or
``32FC1`` metres, or a ``compressedDepth`` PNG), the depth image's ``CameraInfo``, and the
camera pose at each depth stamp: from tf (``source.world_frame`` -> ``source.camera_frame`` or
the depth image's frame, through a ``tf2_ros.Buffer``) where ``tf2_ros`` can be imported (a ROS
install; it is not on PyPI), else from a ``geometry_msgs/PoseStamped`` or ``nav_msgs/Odometry``
topic (``source.pose_topic``) times ``camera_offset`` (the camera's optical frame in the pose's
body frame). The image and pose topics are subscribed to once a publisher appears (their type
is read from the graph). Pairing, keyframes and the mapping thread: :mod:`.pipeline`; mapping
never runs in a callback.

Outputs, in ``source.world_frame``:

- ``~/map/rgb``, ``~/map/pca`` (``PointCloud2``: voxel centres, mean colour / the PCA of the
  features as ``rgb``), at most ``publish_rate`` Hz when the map changed (transient local: a
  late RViz gets the last one); a map of more than ``max_points`` voxels is published
  downsampled (every n-th voxel in index order), as is the query cloud;
- ``~/query`` (``std_msgs/String``) in: ``~/query/cloud`` (``PointCloud2`` with ``rgb`` from
  blue to red and the ``similarity`` field, :meth:`SemanticMap.query`), ``~/query/top_k``
  (``PoseArray``: the ``top_k`` best voxel centres, best first) and ``~/query/markers``
  (``MarkerArray``: them as cubes);
- ``~/status`` (``std_msgs/String``, JSON): depth images received, frames used, dropped by
  reason, the queue, the map's voxels and bytes, the last window's seconds and latency;
- services ``~/save_map`` and ``~/clear_map`` (``std_srvs/Trigger``).

The map (``storage``: ``exact`` or ``compact``, as ``resireg-map``'s) is saved to
``<output_dir>/map`` every ``save_every`` windows, on ``~/save_map`` and when the node closes
(SIGINT or SIGTERM: the queued keyframes are mapped, the map saved, then published once more,
before the ROS context ends); a save copies the map under its lock and writes it outside, so
mapping waits only for the copy. ``~/clear_map`` empties the map and republishes every latched
output empty. ``resume:=true`` continues a saved map (refused, naming the settings, if they
differ: the map's, the source's, the encoder entry or its weights' digest).
``rerun.*``: the live Rerun stream (:class:`RerunView`), the same entities as ``resireg-map``'s
recording.
"""

from __future__ import annotations

import array
import json
import math
import threading
import time
from pathlib import Path
from typing import Any

import numpy as np
from rcl_interfaces.msg import ParameterDescriptor
from rclpy.node import Node
from rclpy.qos import (
    DurabilityPolicy,
    HistoryPolicy,
    QoSProfile,
    ReliabilityPolicy,
    qos_profile_sensor_data,
)

from resireg.errors import ResiregError
from resireg.ros2.clouds import cloud_message
from resireg.ros2.pipeline import FramePairer, KeyframeFilter, MapWorker, PoseBuffer
from resireg.ros2.settings import (
    SOURCE_KEYS,
    SettingsError,
    check,
    compact_settings,
    encoder_entry,
    parameters,
    variant_params,
)
from resireg.sources.frames import RGBDFrame, SkippedFrame
from resireg.sources.messages import (
    camera_intrinsics,
    camera_size,
    decode_colour,
    decode_depth,
    pose_msg_matrix,
    stamp_seconds,
    transform_matrix,
)
from resireg.sources.pairing import pose_matrix

__all__ = ["ResiregMapNode", "TfPoses", "input_qos", "pose_source", "subscribe_published"]

_IMAGE, _COMPRESSED = "sensor_msgs/msg/Image", "sensor_msgs/msg/CompressedImage"
_POSE, _ODOMETRY = "geometry_msgs/msg/PoseStamped", "nav_msgs/msg/Odometry"


def _msg_type(name: str):
    from geometry_msgs.msg import PoseStamped
    from nav_msgs.msg import Odometry
    from sensor_msgs.msg import CompressedImage, Image

    return {_IMAGE: Image, _COMPRESSED: CompressedImage, _POSE: PoseStamped,
            _ODOMETRY: Odometry}[name]  # fmt: skip


def pose_of(msg: Any) -> np.ndarray:
    """The pose of a ``PoseStamped`` or ``Odometry`` message, ``[4, 4]``."""
    return pose_msg_matrix(msg.pose.pose if hasattr(msg, "child_frame_id") else msg.pose)


def _plain(value: Any) -> Any:
    """A parameter's value as YAML would give it (arrays as lists)."""
    if isinstance(value, array.array | tuple):
        return list(value)
    return value


class TfPoses:
    """The camera pose from tf (``tf2_ros.Buffer`` and ``TransformListener``): ``lookup`` as
    :class:`~resireg.ros2.pipeline.PoseBuffer`'s, final once tf2 can answer (it interpolates
    and does not extrapolate)."""

    def __init__(self, node: Node, world_frame: str, cache_seconds: float = 30.0) -> None:
        import tf2_ros
        from rclpy.duration import Duration

        self.world = world_frame
        self.buffer = tf2_ros.Buffer(cache_time=Duration(seconds=cache_seconds))
        self.listener = tf2_ros.TransformListener(self.buffer, node)

    def lookup(self, t: float, frame_id: str) -> tuple[np.ndarray | None, str, bool]:
        from rclpy.time import Time

        try:
            tr = self.buffer.lookup_transform(self.world, frame_id,
                                              Time(nanoseconds=int(round(t * 1e9))))  # fmt: skip
        except Exception as err:  # tf2's lookup, connectivity and extrapolation errors
            return None, f"no tf {self.world} -> {frame_id} at {t:.6f}: {err}", False
        return transform_matrix(tr.transform), "", True


def pose_source(node: Node, pose_topic: str | None, camera_offset: Any, tolerance: float,
                max_pose_gap: float, buffer_size: int, world_frame: str) -> Any:  # fmt: skip
    """The camera pose source of ``node``'s inputs: a :class:`PoseBuffer` of ``pose_topic``
    (``PoseStamped`` / ``Odometry``, the latest ``20 * buffer_size`` samples) times
    ``camera_offset`` (x y z qx qy qz qw), or without a topic tf (:class:`TfPoses`; ImportError
    without ``tf2_ros``). Shared by the node and :class:`resireg.ros2.source.LiveSource`."""
    if pose_topic is not None:
        o = list(camera_offset)
        offset = pose_matrix(o[:3], o[3:])
        return PoseBuffer(pose_topic, offset, tolerance, max_pose_gap, 20 * int(buffer_size))
    return TfPoses(node, world_frame)


def input_qos(qos: str, buffer_size: int) -> QoSProfile:
    """The QoS of the image, camera-info and pose subscriptions: ``sensor_data`` (best effort,
    as camera drivers publish) or ``reliable`` (keep the last ``buffer_size``)."""
    if qos == "sensor_data":
        return qos_profile_sensor_data
    return QoSProfile(depth=int(buffer_size), reliability=ReliabilityPolicy.RELIABLE,
                      history=HistoryPolicy.KEEP_LAST)  # fmt: skip


def subscribe_published(node: Node, wanted: dict[str, tuple[str, tuple[str, ...]]],
                        subscribed: dict[str, str], handlers: dict[str, Any],
                        qos: QoSProfile) -> None:  # fmt: skip
    """Subscribe ``node`` to each input of ``wanted`` (``key -> (topic, accepted types)``) once
    a publisher shows its type on the graph (an image topic is ``Image`` or
    ``CompressedImage``); ``subscribed`` (``key -> type``) records those done."""
    if len(subscribed) == len(wanted):
        return
    graph = dict(node.get_topic_names_and_types())
    for key, (topic, types) in wanted.items():
        if key in subscribed:
            continue
        found = [t for t in graph.get(node.resolve_topic_name(topic), []) if t in types]
        if found:
            node.create_subscription(_msg_type(found[0]), topic, handlers[key], qos)
            subscribed[key] = found[0]
            node.get_logger().info(f"subscribed to {topic} ({found[0]})")


class ResiregMapNode(Node):
    """The live mapping node (module docstring).

    Args:
        encoder: a built dense encoder (tests, benchmarks); ``None`` builds the ``encoder`` /
            ``model_path`` parameters' one.
        node_name, context, parameter_overrides: rclpy's (``--ros-args -p`` also sets them).

    Raises :class:`~resireg.ros2.settings.SettingsError` (one line) for a bad parameter, a
    missing model or a refused resume.
    """

    def __init__(self, encoder: Any = None, node_name: str = "resireg_map", *,
                 context: Any = None, parameter_overrides: list | None = None) -> None:  # fmt: skip
        super().__init__(node_name, context=context, parameter_overrides=parameter_overrides)
        table = parameters()
        for name, p in table.items():
            self.declare_parameter(name, p.default,
                                   ParameterDescriptor(dynamic_typing=True, description=p.origin))  # fmt: skip
        unknown = sorted(n for n in self._parameter_overrides if n not in table
                         and not self.has_parameter(n))  # fmt: skip
        given = {n: _plain(self.get_parameter(n).value) for n in table}
        self.values = v = check(given, table, unknown)
        self.world_frame = v["source.world_frame"]
        self.folder = Path(v["output_dir"]).expanduser() / "map"
        self.encoder = encoder if encoder is not None else self._build_encoder()
        self.smap = self._open_map()
        self.keyframes = KeyframeFilter(v["keyframe.translation"], v["keyframe.rotation"])
        self.worker = MapWorker(self.smap, self._new_map, v["window"], v["queue_size"],
                                v["window_timeout"], v["source.max_depth"],
                                self._on_window)  # fmt: skip
        self.pairer = FramePairer(self._pose_source(), {
            "colour": v["source.colour_topic"], "depth": v["source.depth_topic"],
            "camera_info": v["source.camera_info_topic"]}, v["source.tolerance"], v["max_wait"],
            v["source.depth_scale"], decode_colour, decode_depth, v["buffer_size"],
            v["source.camera_frame"])  # fmt: skip
        self.view = self._rerun()
        self.changed = threading.Event()
        self.wake = threading.Event()
        self.queries: list[str] = []
        self.published: dict[str, Any] = {"map": 0.0}
        self.timing: dict[str, float] = {"ros_seconds": 0.0, "cloud_seconds": 0.0}
        self._closing = False
        self._saved_windows = 0
        self._save_lock = threading.Lock()  # one write of the map folder at a time
        self._publish_lock = threading.Lock()  # the output thread's and the services' publishes
        self._make_io()
        self.worker.start()
        self._output = threading.Thread(target=self._output_loop, name="resireg-output",
                                        daemon=True)  # fmt: skip
        self._output.start()
        self.get_logger().info(
            f"mapping {v['source.depth_topic']} + {v['source.colour_topic']} into "
            f"{self.world_frame} ({v['configuration']}, window {v['window']}, voxel "
            f"{v['voxel_size']} m); map folder {self.folder}"
        )

    # ------------------------------------------------------------------ set-up
    def _build_encoder(self) -> Any:
        import torch

        from resireg.models import build_encoder
        from resireg.models.factory import resolve_device

        v = self.values
        entry = encoder_entry(v)
        device = resolve_device(v["device"])
        torch.manual_seed(int(v["seed"]))
        try:
            return build_encoder(**entry, device=device)
        except (OSError, ValueError, TypeError) as err:
            raise SettingsError(f"encoder={v['encoder']!r} (model_path={v['model_path']!r}): "
                                f"{err}") from err  # fmt: skip

    def _new_map(self) -> Any:
        """An empty map of the parameters (as resireg-map's ``make_map``)."""
        from resireg.mapping import SemanticMap

        v = self.values
        try:
            return SemanticMap(self.encoder, v["configuration"], float(v["voxel_size"]),
                               params=variant_params(v), points=v["points"],
                               lattice=v["lattice"], sum_dtype=v["sum_dtype"],
                               max_voxels=v["max_voxels"], short_side=v["short_side"],
                               storage=v["storage"], compact=compact_settings(v))  # fmt: skip
        except (ValueError, OSError, ResiregError) as err:
            raise SettingsError(str(err)) from err

    def _identity(self) -> dict[str, Any]:
        """What a resumed map must share with the node (besides the map's own settings): the
        encoder entry (its path resolved), a digest of the encoder's weights (as resireg-map
        keys its maps: another model at the same path differs) and the source parameters."""
        from resireg.models.factory import weights_fingerprint

        entry = dict(encoder_entry(self.values)) if self.values["model_path"] else {}
        path = entry.get("path")
        if isinstance(path, str) and Path(path).expanduser().exists():
            entry["path"] = str(Path(path).expanduser().resolve())
        return {"encoder": entry, "weights": weights_fingerprint(self.encoder),
                "source": {k: self.values[f"source.{k}"] for k in SOURCE_KEYS}}  # fmt: skip

    def _open_map(self) -> Any:
        from resireg.mapping import SemanticMap

        fresh = self._new_map()
        identity = self._identity()
        if not (self.folder / "map.json").is_file():
            fresh.meta = {"identity": identity, "kept_frames": 0}
            return fresh
        if not self.values["resume"]:
            raise SettingsError(f"{self.folder} holds a map: -p resume:=true continues it, or "
                                "set another -p output_dir:=...")  # fmt: skip
        smap = SemanticMap.load(self.folder, self.encoder, max_voxels=self.values["max_voxels"])
        saved = {k: x for k, x in smap.settings().items() if k != "max_voxels"}
        now = {k: x for k, x in fresh.settings().items() if k != "max_voxels"}
        differ = [f"{k}: {saved.get(k)!r} in the map, {now.get(k)!r} now"
                  for k in sorted(set(saved) | set(now)) if saved.get(k) != now.get(k)]  # fmt: skip
        old = (smap.meta or {}).get("identity") or {}
        differ += [f"{k}: {old.get(k)!r} in the map, {identity[k]!r} now"
                   for k in identity if k in old and old[k] != identity[k]]  # fmt: skip
        if differ:
            raise SettingsError(f"resume:=true: {self.folder} was made with other settings ("
                                f"{len(differ)} differ): " + "; ".join(differ))  # fmt: skip
        smap.meta = {**smap.meta, "identity": identity}
        self.get_logger().info(f"resuming {self.folder}: {smap.frames} frames, {len(smap)} voxels")
        return smap

    def _pose_source(self) -> Any:
        v = self.values
        try:
            return pose_source(self, v["source.pose_topic"], v["camera_offset"],
                               v["source.tolerance"], v["source.max_pose_gap"],
                               v["buffer_size"], self.world_frame)  # fmt: skip
        except ImportError:
            raise SettingsError(
                "source.pose_topic=None: the camera pose from tf needs tf2_ros, which a ROS 2 "
                "install provides (it is not on PyPI): source the ROS setup, or give -p "
                "source.pose_topic:=<PoseStamped or Odometry topic> and -p camera_offset:=[x, y, "
                "z, qx, qy, qz, qw]"
            ) from None

    def _rerun(self) -> Any:
        v = self.values
        if not (v["rerun.save"] or v["rerun.spawn"] or v["rerun.serve"] or v["rerun.connect"]):
            return None
        from resireg.mapping.viewer import RerunView

        view = RerunView(v["rerun.save"], v["rerun.spawn"], v["rerun.query"],
                         connect=v["rerun.connect"], serve=v["rerun.serve"],
                         application="resireg-ros2")  # fmt: skip
        if view.url:
            self.get_logger().info(f"Rerun stream: rerun --connect {view.url}")
        return view

    def _qos(self) -> QoSProfile:
        return input_qos(self.values["qos"], self.values["buffer_size"])

    def _make_io(self) -> None:
        from geometry_msgs.msg import PoseArray
        from sensor_msgs.msg import CameraInfo, PointCloud2
        from std_msgs.msg import String
        from std_srvs.srv import Trigger
        from visualization_msgs.msg import MarkerArray

        v = self.values
        latched = QoSProfile(depth=1, reliability=ReliabilityPolicy.RELIABLE,
                             durability=DurabilityPolicy.TRANSIENT_LOCAL)  # fmt: skip
        self.pub = {
            "rgb": self.create_publisher(PointCloud2, "~/map/rgb", latched),
            "pca": self.create_publisher(PointCloud2, "~/map/pca", latched),
            "query": self.create_publisher(PointCloud2, "~/query/cloud", latched),
            "top_k": self.create_publisher(PoseArray, "~/query/top_k", latched),
            "markers": self.create_publisher(MarkerArray, "~/query/markers", latched),
            "status": self.create_publisher(String, "~/status", 10),
        }
        self.create_subscription(CameraInfo, v["source.camera_info_topic"], self._on_info,
                                 self._qos())  # fmt: skip
        self.create_subscription(String, "~/query", self._on_query, 10)
        self.create_service(Trigger, "~/save_map", self._on_save)
        self.create_service(Trigger, "~/clear_map", self._on_clear)
        self.wanted = {"colour": (v["source.colour_topic"], (_IMAGE, _COMPRESSED)),
                       "depth": (v["source.depth_topic"], (_IMAGE, _COMPRESSED))}  # fmt: skip
        if isinstance(self.pairer.poses, PoseBuffer):
            self.wanted["pose"] = (v["source.pose_topic"], (_POSE, _ODOMETRY))
        self.subscribed: dict[str, str] = {}
        self._discover()
        self.create_timer(0.25, self._discover)
        self.create_timer(max(0.01, v["max_wait"] / 4), self._poll)
        self.create_timer(1.0 / v["status_rate"], self._publish_status)

    def _discover(self) -> None:
        """Subscribe to each input topic once a publisher shows its type."""
        handlers = {"colour": self._on_colour, "depth": self._on_depth, "pose": self._on_pose}
        subscribe_published(self, self.wanted, self.subscribed, handlers, self._qos())

    # ------------------------------------------------------------------ inputs (callbacks)
    def _on_colour(self, msg: Any) -> None:
        t0 = time.perf_counter()
        self.pairer.colour(stamp_seconds(msg.header), msg)
        self._drain(time.monotonic(), t0)

    def _on_depth(self, msg: Any) -> None:
        t0 = time.perf_counter()
        self.pairer.depth(stamp_seconds(msg.header), msg, msg.header.frame_id, time.monotonic())
        self._drain(time.monotonic(), t0)

    def _on_info(self, msg: Any) -> None:
        self.pairer.info(stamp_seconds(msg.header), camera_intrinsics(msg), camera_size(msg))
        self._drain(time.monotonic(), time.perf_counter())

    def _on_pose(self, msg: Any) -> None:
        self.pairer.poses.add(stamp_seconds(msg.header), pose_of(msg))
        self._drain(time.monotonic(), time.perf_counter())

    def _poll(self) -> None:
        self._drain(time.monotonic(), time.perf_counter())

    def _drain(self, now: float, t0: float) -> None:
        """Decided frames: keyframes to the mapping thread, the others counted."""
        for record, received in self.pairer.poll(now):
            if isinstance(record, RGBDFrame):
                if self.keyframes(record.pose):
                    self.worker.put(record, received)
                else:
                    with self.pairer.lock:
                        self.pairer.counts.skip(SkippedFrame(
                            record.name, "moved less than keyframe.translation and turned less "
                            "than keyframe.rotation since the last keyframe", "not_keyframe"))  # fmt: skip
        self.timing["ros_seconds"] += time.perf_counter() - t0

    def _on_query(self, msg: Any) -> None:
        self.queries.append(str(msg.data))
        self.wake.set()

    def _on_save(self, request: Any, response: Any) -> Any:
        try:
            folder = self.save()
            response.success = True
            response.message = f"saved {len(self.worker.smap)} voxels to {folder}"
        except Exception as err:  # the reply says why (a full disk, a read-only folder)
            response.success, response.message = False, f"save failed: {err}"
        return response

    def _on_clear(self, request: Any, response: Any) -> Any:
        removed = self.worker.clear()
        self.keyframes.reset()
        self.clear_outputs()
        response.success, response.message = True, f"cleared {removed} voxels"
        return response

    def clear_outputs(self) -> None:
        """Republish every latched output for the empty map: the map clouds and the query
        cloud without points, no top-k pose, the markers deleted (a late subscriber no
        longer gets the cleared map's answer)."""
        from geometry_msgs.msg import PoseArray
        from visualization_msgs.msg import Marker, MarkerArray

        with self._publish_lock:
            header = self._header()
            empty = cloud_message(header, np.zeros((0, 3), np.float32), np.zeros((0, 3)))
            self.pub["rgb"].publish(empty)
            self.pub["pca"].publish(empty)
            self.pub["query"].publish(cloud_message(header, np.zeros((0, 3), np.float32),
                                                    np.zeros((0, 3)),
                                                    similarity=np.zeros(0, np.float32)))  # fmt: skip
            self.pub["top_k"].publish(PoseArray(header=header))
            self.pub["markers"].publish(MarkerArray(markers=[Marker(
                header=header, ns="query", id=0, action=Marker.DELETEALL)]))  # fmt: skip
            self.published["map"] = time.monotonic()
        self.changed.clear()

    # ------------------------------------------------------------------ mapping thread
    def _on_window(self, batch: dict, record: dict) -> None:
        v = self.values
        with self.worker.lock:
            self.worker.smap.meta["kept_frames"] = self.worker.smap.frames
            if self.view is not None:
                self.view.log_window(batch, self.worker.smap.frames - len(batch["name"]))
                if self.worker.windows % v["rerun.map_every"] == 0:
                    self.view.log_map(self.worker.smap)
            due = v["save_every"] and self.worker.windows % v["save_every"] == 0
        if due:
            self.save()
        self.changed.set()
        self.wake.set()

    def save(self) -> Path:
        """Save the map to ``<output_dir>/map``: a copy of it taken under the map's lock
        (:meth:`SemanticMap.snapshot`), written outside it, one save at a time."""
        with self._save_lock:
            with self.worker.lock:
                self.worker.smap.meta["kept_frames"] = self.worker.smap.frames
                snapshot = self.worker.smap.snapshot(copy=True)
            return snapshot.write(self.folder)

    # ------------------------------------------------------------------ outputs
    def _header(self) -> Any:
        from std_msgs.msg import Header

        return Header(stamp=self.get_clock().now().to_msg(), frame_id=self.world_frame)

    def _output_loop(self) -> None:
        period = 1.0 / self.values["publish_rate"]
        while not self._closing:
            self.wake.wait(period)
            self.wake.clear()
            try:
                while self.queries and not self._closing:
                    self.answer(self.queries.pop(0))
                due = time.monotonic() - self.published["map"] >= period
                if self.changed.is_set() and due and not self._closing:
                    self.changed.clear()
                    self.publish_map()
            except Exception as err:  # a failed publish must not end the loop
                if not self._closing:
                    self.get_logger().error(f"publishing failed: {err}")

    def _stride(self, voxels: int) -> int:
        """Every how many voxels a cloud takes one: at most ``max_points`` points."""
        return max(1, math.ceil(voxels / self.values["max_points"]))

    def publish_map(self) -> None:
        """``~/map/rgb`` and ``~/map/pca`` of the map as it is (every n-th voxel past
        ``max_points``)."""
        from resireg.mapping import pca_colours

        t0 = time.perf_counter()
        with self.worker.lock:
            smap = self.worker.smap
            if not len(smap):
                centres, feats, rgb = np.zeros((0, 3), np.float32), None, np.zeros((0, 3))
            else:
                centres, feats, colours = smap.subsample(self._stride(len(smap)))
                centres = centres.cpu().numpy()
                rgb = colours.numpy() if colours is not None else np.zeros((len(centres), 3))
        pca = pca_colours(feats).numpy() if feats is not None else np.zeros((0, 3))
        with self._publish_lock:
            if self.worker.smap is not smap:  # cleared meanwhile: clear_outputs published
                return
            header = self._header()
            self.pub["rgb"].publish(cloud_message(header, centres, rgb))
            self.pub["pca"].publish(cloud_message(header, centres, pca))
            self.published["map"] = time.monotonic()
        self.timing["cloud_seconds"] += time.perf_counter() - t0

    def answer(self, text: str) -> None:
        """The similarity cloud and the best voxels of a text query."""
        from geometry_msgs.msg import Pose, PoseArray
        from visualization_msgs.msg import Marker, MarkerArray

        from resireg.mapping.colours import diverging_ramp

        with self.worker.lock:
            smap = self.worker.smap
            if not len(smap):
                self.get_logger().warning(f"query {text!r}: the map is empty")
                return
            sim = smap.query(text)
            centres = smap.centres().cpu().numpy()
            voxel = smap.voxel_size
        t0 = time.perf_counter()
        take = slice(None, None, self._stride(sim.shape[0]))
        header = self._header()
        cloud = cloud_message(header, centres[take], diverging_ramp(sim[take]).numpy(),
                              similarity=sim[take].cpu().numpy())  # fmt: skip
        k = min(self.values["top_k"], sim.shape[0])
        best = np.argsort(-sim.cpu().numpy(), kind="stable")[:k]
        poses = PoseArray(header=header)
        markers = MarkerArray(markers=[Marker(header=header, ns="query", id=0,
                                              action=Marker.DELETEALL)])  # fmt: skip
        cubes = Marker(header=header, ns="query", id=1, type=Marker.CUBE_LIST, action=Marker.ADD)
        cubes.scale.x = cubes.scale.y = cubes.scale.z = float(voxel)
        cubes.color.r, cubes.color.a = 1.0, 0.8
        cubes.pose.orientation.w = 1.0
        for i in best:
            p = Pose()
            p.position.x, p.position.y, p.position.z = (float(c) for c in centres[i])
            p.orientation.w = 1.0
            poses.poses.append(p)
            cubes.points.append(p.position)
        markers.markers.append(cubes)
        with self._publish_lock:
            if self.worker.smap is not smap:  # cleared meanwhile: clear_outputs published
                return
            self.pub["query"].publish(cloud)
            self.pub["top_k"].publish(poses)
            self.pub["markers"].publish(markers)
        self.timing["cloud_seconds"] += time.perf_counter() - t0

    def status(self) -> dict[str, Any]:
        """What ``~/status`` publishes."""
        w = self.worker.stats()
        with self.pairer.lock:
            c = self.pairer.counts
            dropped = dict(c.dropped)
            received, unpaired = c.received, c.unpaired_colour
            colour_faults = c.colour_stamp_faults
        for kind, n in w["dropped"].items():
            dropped[kind] = dropped.get(kind, 0) + n
        smap = self.worker.smap
        last = w["last"]
        return {
            "frames": {"received": received, "used": w["used"], "dropped": dropped},
            "unpaired_colour": unpaired,
            "colour_stamp_faults": colour_faults,
            "queue": len(self.worker.queue),
            "pairing": self.pairer.sizes(),
            "map": {
                "voxels": len(smap),
                "bytes": smap.nbytes,
                "frames": smap.frames,
                "windows": smap.windows,
            },  # fmt: skip
            "last_window": {
                "frames": last.get("frames"),
                "seconds": last.get("seconds"),
                "latency": last.get("latency"),
                "stamp_latency": (self.get_clock().now().nanoseconds * 1e-9 - last["stamp"])
                if last
                else None,
            },  # fmt: skip
            "subscribed": dict(self.subscribed),
            "error": None if self.worker.error is None else repr(self.worker.error),
        }

    def _publish_status(self) -> None:
        from std_msgs.msg import String

        self.pub["status"].publish(String(data=json.dumps(self.status())))

    # ------------------------------------------------------------------ end
    def close(self, save: bool = True) -> Path | None:
        """Pair what is pending, map every queued keyframe, stop the output thread, save the
        map (``save``) and publish it once more (while the ROS context is valid: resireg-ros2
        ends the context after this), in that order. Safe after rclpy's shutdown."""
        if self._closing:
            return None
        self._drain(math.inf, time.perf_counter())
        self.worker.stop()
        self._closing = True
        self.wake.set()
        self._output.join(5.0)
        folder = None
        if save and (self.worker.smap.frames or (self.folder / "map.json").is_file()):
            folder = self.save()
            self.get_logger().info(f"map saved to {folder}")
        if self.context.ok() and self.worker.smap.frames:
            self.publish_map()
            self.get_logger().info(f"published the final map ({len(self.worker.smap)} voxels)")
        if self.view is not None:
            with self.worker.lock:
                self.view.log_map(self.worker.smap)
            self.view.close()
        return folder
