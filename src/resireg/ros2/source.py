"""Live ROS 2 topics as a map source: ``resireg-map source=ros2`` (``conf/source/ros2.yaml``, the
``ros2`` entry of :data:`resireg.specs.sources.SOURCE_SPECS`).

:class:`LiveSource` is a :class:`~resireg.sources.frames.MessageSource` whose frames come from a
running ROS 2 graph (a camera driver, or a bag played with ``ros2 bag play``) instead of a file:
iterating it starts its own rclpy context, node and executor thread, subscribes to the colour,
depth and camera-info topics and the pose (``pose_topic``: ``PoseStamped`` / ``Odometry`` times
``camera_offset``; or tf, through ``tf2_ros``, where it can be imported), and pairs them with the
live node's :class:`~resireg.ros2.pipeline.FramePairer` (the same rules as a bag's reader: the
frames it yields, in stamp order as they are decided, are the ones a bag of the same messages
gives). Image and pose topics are subscribed to once a publisher shows their type, as the node
does (:func:`~resireg.ros2.topics.subscribe_published`).

The stream ends (the depth images still waiting are then paired with what has arrived, and the
executor, node and context are shut down):

- when the consumer stops iterating: ``resireg-map``'s ``source.limit`` kept frames (the windows
  stop), or :meth:`LiveSource.close`, or the iterator is closed or garbage-collected;
- ``idle`` seconds after the latest depth image, when no new one came (before the first one
  the source waits, saying every 10 s which topic it waits for: start the camera or
  ``ros2 bag play`` when you like); ``idle=None``: never;
- at Ctrl-C (SIGINT, when iterated in the main thread): the first one ends the stream, so the
  frames received are mapped and saved as at the end of a bag; a second one interrupts as
  usual.

rclpy is imported when a source is made; without it, making one is a
:class:`~resireg.errors.ConfigError` naming the ``robot`` extra. Like the node, it opens no
socket of its own: the RMW and its profile (``RMW_IMPLEMENTATION``,
``FASTRTPS_DEFAULT_PROFILES_FILE``, ``ROS_DOMAIN_ID``) are the environment's.
"""

from __future__ import annotations

import logging
import math
import signal
import threading
import time
from collections import deque
from collections.abc import Iterator, Sequence
from typing import Any

from resireg.errors import ConfigError
from resireg.sources.frames import RGBDFrame, SkippedFrame
from resireg.sources.rosbag import RosKeys, takes_ros_keys

__all__ = ["LiveSource"]

log = logging.getLogger(__name__)

_ROBOT = ('pip install "resireg[robot]" (in a clone: pip install -e ".[robot]" -c '
          "constraints.txt), or source a ROS 2 Jazzy install")  # fmt: skip


class LiveSource:
    """Frames of live ROS 2 topics (module docstring). The keywords are those of
    ``conf/source/ros2.yaml`` (checked by the ``ros2`` entry's rules when it is made; errors
    name them: ``idle=-1: expected ...``).

    Args:
        colour_topic / depth_topic / camera_info_topic: the inputs (``Image`` or
            ``CompressedImage``; ``16UC1`` / ``32FC1`` depth or ``compressedDepth``; the depth
            image's ``CameraInfo``).
        pose_topic: ``PoseStamped`` / ``Odometry``; ``None``: tf (needs ``tf2_ros``).
        tf_topic / tf_static_topic: the topics tf2_ros listens to (remapped to these names).
        world_frame / camera_frame: tf's root and the camera's frame (``None``: the depth
            image's ``header.frame_id``).
        depth_scale: metres per unit of ``16UC1`` depth.
        tolerance: seconds between a depth image and its colour image, and beyond a pose
            stream's samples; max_pose_gap: the longest gap between pose samples interpolated.
        idle: seconds without a new depth image, after the first, that end the stream
            (``None``: never).
        max_wait: seconds a depth image waits for what would decide its pairing.
        buffer_size: messages kept per input while pairing (a depth image past it: ``overflow``).
        camera_offset: x y z qx qy qz qw of the camera in the pose's body frame.
        qos: ``sensor_data`` or ``reliable`` (the input subscriptions).
        node_name: the name of the source's node on the graph.

    Attributes (a :class:`~resireg.sources.frames.MessageSource`'s, as of the last stream):
        unpaired_colour: colour images no depth image took (those left at the end included).
        corrupt / corrupt_examples: always empty (rclpy delivers only deserialised messages).
        colour_stamp_faults: the colour images left out for their stamps, each named.
        damage: always ``None``.
        ended: why the last stream ended (``None`` while one runs or before any).
        live: true: every stream is new (``resireg-map resume=true`` adds its frames to the
            map, where a recording's first frames, already in it, are skipped).
    """

    live = True

    @takes_ros_keys  # colour_topic ... max_pose_gap: the keys a bag's reader takes too
    def __init__(
        self,
        *,
        idle: float | None = 5.0,
        max_wait: float = 0.5,
        buffer_size: int = 30,
        camera_offset: Sequence[float] = (0.0, 0.0, 0.0, 0.0, 0.0, 0.0, 1.0),
        qos: str = "sensor_data",
        node_name: str = "resireg_map_source",
        **keys: Any,
    ) -> None:
        from resireg.specs.sources import SOURCE_SPECS

        given = {**RosKeys(**keys).as_dict(), "idle": idle, "max_wait": max_wait,
                 "buffer_size": buffer_size, "camera_offset": camera_offset, "qos": qos}  # fmt: skip
        rules = SOURCE_SPECS.get("ros2").rules
        errors = [f"{k}={v!r}: expected {rules[k][1]}" for k, v in given.items()
                  if not rules[k][0](v)]  # fmt: skip
        if errors:
            raise ConfigError("; ".join(errors))
        missing = missing_rclpy()
        if missing is not None:
            raise ConfigError(f"the ros2 source needs the 'robot' extra ({missing} not "
                              f"installed): {_ROBOT}")  # fmt: skip
        if given["pose_topic"] is None:
            import importlib.util

            if importlib.util.find_spec("tf2_ros") is None:
                raise ConfigError(
                    "pose_topic=None: the camera pose from tf needs tf2_ros, which a ROS 2 "
                    "install provides (it is not on PyPI): source the ROS setup, or give "
                    "pose_topic=<PoseStamped or Odometry topic> and camera_offset=[x, y, z, qx, "
                    "qy, qz, qw]"
                )
        self.settings = given
        self.node_name = node_name
        self.unpaired_colour = 0
        self.corrupt: dict[str, int] = {}
        self.corrupt_examples: list[str] = []
        self.colour_stamp_faults: list[str] = []
        self.damage: str | None = None
        self.ended: str | None = None
        self._close = threading.Event()
        self._interrupted = False

    def __repr__(self) -> str:
        s = self.settings
        return (f"LiveSource(depth_topic={s['depth_topic']!r}, colour_topic={s['colour_topic']!r}, "
                f"idle={s['idle']!r})")  # fmt: skip

    def __iter__(self) -> Iterator[RGBDFrame | SkippedFrame]:
        self._close.clear()
        return self._stream()

    def close(self) -> None:
        """End the running stream (from any thread): the iterator pairs what it holds, yields
        it and stops."""
        self._close.set()

    # ------------------------------------------------------------------ the stream
    def _stream(self) -> Iterator[RGBDFrame | SkippedFrame]:
        import rclpy
        from rclpy.executors import SingleThreadedExecutor
        from rclpy.node import Node
        from sensor_msgs.msg import CameraInfo

        from resireg.ros2.pipeline import FramePairer
        from resireg.ros2.poses import pose_of, pose_source
        from resireg.ros2.topics import input_qos, subscribe_published
        from resireg.sources.messages import (
            camera_intrinsics,
            camera_size,
            decode_colour,
            decode_depth,
            stamp_seconds,
        )

        s = self.settings
        self.unpaired_colour, self.ended, self._interrupted = 0, None, False
        self.colour_stamp_faults = []
        wake = threading.Event()
        dropped: deque[SkippedFrame] = deque()  # refused on arrival (bad_stamp, overflow)
        last: dict[str, float | None] = {"depth": None}
        context = rclpy.Context()
        rclpy.init(args=[], context=context)  # not the default context: no signal handlers
        node = executor = thread = pairer = sigint = None
        stop = threading.Event()
        try:
            node = Node(self.node_name, context=context, start_parameter_services=False,
                        cli_args=["--ros-args", "-r", f"/tf:={s['tf_topic']}", "-r",
                                  f"/tf_static:={s['tf_static_topic']}"])  # fmt: skip
            poses = pose_source(node, s["pose_topic"], s["camera_offset"], s["tolerance"],
                                s["max_pose_gap"], s["buffer_size"], s["world_frame"])  # fmt: skip
            pairer = FramePairer(
                poses, {"colour": s["colour_topic"], "depth": s["depth_topic"],
                        "camera_info": s["camera_info_topic"]}, s["tolerance"], s["max_wait"],
                s["depth_scale"], decode_colour, decode_depth, s["buffer_size"],
                s["camera_frame"])  # fmt: skip
            pairer.on_colour_fault = self.colour_stamp_faults.append

            def on_colour(msg: Any) -> None:
                pairer.colour(stamp_seconds(msg.header), msg)
                wake.set()

            def on_depth(msg: Any) -> None:
                now = time.monotonic()
                last["depth"] = now
                dropped.extend(pairer.depth(stamp_seconds(msg.header), msg, msg.header.frame_id,
                                            now))  # fmt: skip
                wake.set()

            def on_info(msg: Any) -> None:
                pairer.info(stamp_seconds(msg.header), camera_intrinsics(msg), camera_size(msg))
                wake.set()

            def on_pose(msg: Any) -> None:
                poses.add(stamp_seconds(msg.header), pose_of(msg))
                wake.set()

            qos = input_qos(s["qos"], s["buffer_size"])
            node.create_subscription(CameraInfo, s["camera_info_topic"], on_info, qos)
            image = ("sensor_msgs/msg/Image", "sensor_msgs/msg/CompressedImage")
            wanted = {"colour": (s["colour_topic"], image), "depth": (s["depth_topic"], image)}
            if s["pose_topic"] is not None:
                wanted["pose"] = (s["pose_topic"], ("geometry_msgs/msg/PoseStamped",
                                                    "nav_msgs/msg/Odometry"))  # fmt: skip
            subscribed: dict[str, str] = {}
            handlers = {"colour": on_colour, "depth": on_depth, "pose": on_pose}

            def discover() -> None:
                subscribe_published(node, wanted, subscribed, handlers, qos)

            discover()
            node.create_timer(0.25, discover)
            executor = SingleThreadedExecutor(context=context)
            executor.add_node(node)
            thread = threading.Thread(target=_spin, args=(executor, context, stop),
                                      name="resireg-live-source", daemon=True)  # fmt: skip
            thread.start()
            sigint = self._catch_sigint(wake)
            log.info("listening to %s and %s (%s); the stream ends %s s after the latest "
                     "depth image, or at Ctrl-C", s["depth_topic"], s["colour_topic"],
                     s["pose_topic"] or f"tf to {s['world_frame']}", s["idle"])  # fmt: skip
            period = max(0.01, s["max_wait"] / 4)
            started = said = time.monotonic()
            while True:
                wake.clear()  # before polling: a message after it wakes the wait below
                while dropped:
                    yield dropped.popleft()
                for record, _ in pairer.poll(time.monotonic()):
                    yield record
                if self._close.is_set():
                    self.ended = "Ctrl-C" if self._interrupted else "closed"
                    break
                now, latest = time.monotonic(), last["depth"]
                left = period
                if latest is None:
                    if now - said >= 10.0:
                        said = now
                        seen = "subscribed" if "depth" in subscribed else "no publisher yet"
                        log.warning("waiting for %s (%s) for %.0f s", s["depth_topic"], seen,
                                    now - started)  # fmt: skip
                elif s["idle"] is not None:
                    if now - latest >= s["idle"]:
                        self.ended = (f"idle: no new depth image on {s['depth_topic']} for "
                                      f"{s['idle']} s")  # fmt: skip
                        break
                    left = min(period, s["idle"] - (now - latest))
                wake.wait(max(left, 0.001))
            stop.set()  # no more messages: pair what waits with what has arrived
            thread.join(5.0)
            while dropped:
                yield dropped.popleft()
            for record, _ in pairer.poll(math.inf):
                yield record
            log.info("the live stream ended: %s", self.ended)
        finally:
            if self.ended is None:
                self.ended = "the consumer stopped"
            _restore_sigint(sigint)
            stop.set()
            if thread is not None:
                thread.join(5.0)
            if pairer is not None:
                with pairer.lock:
                    left = sum(1 for c in pairer.colours if not c.used)
                    self.unpaired_colour = pairer.counts.unpaired_colour + left
            if executor is not None:
                executor.shutdown()
            if node is not None:
                node.destroy_node()
            rclpy.try_shutdown(context=context)

    def _catch_sigint(self, wake: threading.Event) -> tuple[Any, Any] | None:
        """In the main thread: the first SIGINT ends the stream (and puts the previous handler
        back, so a second one interrupts as before). Returns ``(handler, previous)``."""
        if threading.current_thread() is not threading.main_thread():
            return None
        previous = signal.getsignal(signal.SIGINT)
        if previous is None:  # installed outside Python: the default is Python's
            previous = signal.default_int_handler

        def handler(signum: int, frame: Any) -> None:
            signal.signal(signal.SIGINT, previous)
            self._interrupted = True
            self._close.set()
            wake.set()
            log.warning("Ctrl-C: the live stream ends (the frames received are mapped and "
                        "saved); Ctrl-C again interrupts")  # fmt: skip

        signal.signal(signal.SIGINT, handler)
        return handler, previous


def _restore_sigint(installed: tuple[Any, Any] | None) -> None:
    """The SIGINT handler before :meth:`LiveSource._catch_sigint`'s, if its own is still set."""
    if installed is None or threading.current_thread() is not threading.main_thread():
        return
    handler, previous = installed
    if signal.getsignal(signal.SIGINT) is handler:
        signal.signal(signal.SIGINT, previous)


def missing_rclpy() -> str | None:
    """The first module of the ``robot`` extra's ROS side that cannot be found, or ``None``."""
    from resireg.ros2.cli import missing_rclpy as missing

    return missing()


def _spin(executor: Any, context: Any, stop: threading.Event) -> None:
    """The source's executor thread: callbacks until ``stop`` (a failing callback is logged,
    the first few times, and the stream goes on)."""
    failures = 0
    while not stop.is_set() and context.ok():
        try:
            executor.spin_once(timeout_sec=0.05)
        except Exception as err:  # a callback's: the message is left out
            if stop.is_set() or not context.ok():
                return
            failures += 1
            if failures <= 5:
                log.warning("live source: a message could not be taken: %r", err)
