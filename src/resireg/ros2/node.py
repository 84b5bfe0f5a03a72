"""``resireg-ros2``'s node: a live :class:`resireg.mapping.SemanticMap` fed by an RGB-D camera
(rclpy; docs/robot.md).

Inputs (topics and frames: the ``source.*`` parameters, as ``resireg-map``'s): colour
(``sensor_msgs/Image`` or ``CompressedImage``), depth (``Image`` ``16UC1`` millimetres or
``32FC1`` metres, or a ``compressedDepth`` PNG), the depth image's ``CameraInfo``, and the
camera pose at each depth stamp: from tf (``source.world_frame`` -> ``source.camera_frame`` or
the depth image's frame, through a ``tf2_ros.Buffer``) where ``tf2_ros`` can be imported (a ROS
install; it is not on PyPI), else from a ``geometry_msgs/PoseStamped`` or ``nav_msgs/Odometry``
topic (``source.pose_topic``) times ``camera_offset`` (the camera's optical frame in the pose's
body frame): :mod:`.poses`. The image and pose topics are subscribed to once a publisher appears
(their type is read from the graph) with the ``qos`` parameter's profile: :mod:`.topics`.
Pairing, keyframes and the mapping thread: :mod:`.pipeline`; mapping never runs in a callback.
The encoder, the map opened or resumed, the mapping thread and the saves: :mod:`.session`.

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
differ: the map's, the source's, the window, the encoder entry or its weights' digest:
:func:`resireg.mapping.opening.open_map`, as ``resireg-map``).
``viewer.*``: the live Rerun stream (:class:`RerunView`), the same entities as ``resireg-map``'s
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
from rclpy.qos import QoSProfile

from resireg.ros2.clouds import cloud_message
from resireg.ros2.pipeline import FramePairer, KeyframeFilter
from resireg.ros2.poses import PoseBuffer, pose_of, pose_source
from resireg.ros2.session import MapSession
from resireg.ros2.settings import SettingsError, check, parameters
from resireg.ros2.topics import (
    IMAGE_TYPES,
    POSE_TYPES,
    input_qos,
    latched_qos,
    subscribe_published,
)
from resireg.sources.frames import RGBDFrame, SkippedFrame
from resireg.sources.messages import (
    camera_intrinsics,
    camera_size,
    decode_colour,
    decode_depth,
    stamp_seconds,
)

__all__ = ["ResiregMapNode"]


def _plain(value: Any) -> Any:
    """A parameter's value as YAML would give it (arrays as lists)."""
    if isinstance(value, array.array | tuple):
        return list(value)
    return value


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
        self.session = MapSession(v, encoder, self._on_window)
        self.encoder, self.folder, self.worker = (self.session.encoder, self.session.folder,
                                                  self.session.worker)  # fmt: skip
        if self.session.resumed:
            self.get_logger().info(f"resuming {self.folder}: {self.worker.smap.frames} frames, "
                                   f"{len(self.worker.smap)} voxels")  # fmt: skip
        self.keyframes = KeyframeFilter(v["keyframe.translation"], v["keyframe.rotation"])
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
        self._publish_lock = threading.Lock()  # the output thread's and the services' publishes
        self._make_io()
        self.worker.start()
        self._output = threading.Thread(target=self._output_loop, name="resireg-output",
                                        daemon=True)  # fmt: skip
        self._output.start()
        self.get_logger().info(
            f"mapping {v['source.depth_topic']} + {v['source.colour_topic']} into "
            f"{self.world_frame} ({v['variant']}, window {v['window']}, voxel "
            f"{v['voxel_size']} m); map folder {self.folder}"
        )

    # ------------------------------------------------------------------ set-up
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
        if not (v["viewer.save"] or v["viewer.spawn"] or v["viewer.serve"] or v["viewer.connect"]):
            return None
        from resireg.mapping.viewer import RerunView

        view = RerunView(v["viewer.save"], v["viewer.spawn"], v["viewer.query"],
                         connect=v["viewer.connect"], serve=v["viewer.serve"],
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
        latched = latched_qos()
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
        self.wanted = {"colour": (v["source.colour_topic"], IMAGE_TYPES),
                       "depth": (v["source.depth_topic"], IMAGE_TYPES)}  # fmt: skip
        if isinstance(self.pairer.poses, PoseBuffer):
            self.wanted["pose"] = (v["source.pose_topic"], POSE_TYPES)
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
                if self.worker.windows % v["viewer.map_every"] == 0:
                    self.view.log_map(self.worker.smap)
            due = v["save_every"] and self.worker.windows % v["save_every"] == 0
        if due:
            self.save()
        self.changed.set()
        self.wake.set()

    def save(self) -> Path:
        """Save the map to ``<output_dir>/map`` (:meth:`MapSession.save`)."""
        return self.session.save()

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
