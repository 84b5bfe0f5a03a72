"""The camera pose at a depth image's stamp, for the live node and the live source: from a
``geometry_msgs/PoseStamped`` or ``nav_msgs/Odometry`` topic times a fixed camera offset
(:class:`PoseBuffer`, no rclpy), or from tf (:class:`TfPoses`, through a ``tf2_ros.Buffer``
where ``tf2_ros`` can be imported: a ROS install, it is not on PyPI); :func:`pose_source` picks
one from the ``source.pose_topic`` parameter. Every pose source answers
``lookup(t, frame_id) -> (pose or None, why not, final)``.

Imported by :mod:`resireg.ros2.node`, :mod:`resireg.ros2.source` and
:mod:`resireg.ros2.pipeline`'s callers; rclpy and tf2 are imported when tf is used.
"""

from __future__ import annotations

from collections import deque
from typing import TYPE_CHECKING, Any

import numpy as np

from resireg.sources.messages import pose_msg_matrix, transform_matrix
from resireg.sources.pairing import PoseTrack, pose_matrix

if TYPE_CHECKING:
    from rclpy.node import Node

__all__ = ["PoseBuffer", "TfPoses", "pose_of", "pose_source"]


def pose_of(msg: Any) -> np.ndarray:
    """The pose of a ``PoseStamped`` or ``Odometry`` message, ``[4, 4]``."""
    return pose_msg_matrix(msg.pose.pose if hasattr(msg, "child_frame_id") else msg.pose)


class PoseBuffer:
    """The body poses of a ``PoseStamped`` / ``Odometry`` topic (the latest ``maxlen``), times a
    fixed ``offset`` (the camera in the body frame): ``lookup(t)`` interpolates as
    :class:`PoseTrack` does over the whole stream (only the samples around ``t`` take part)."""

    def __init__(self, topic: str, offset: np.ndarray, tolerance: float, max_gap: float,
                 maxlen: int = 600) -> None:  # fmt: skip
        self.topic, self.offset = topic, np.asarray(offset, dtype=np.float64)
        self.tolerance, self.max_gap = float(tolerance), float(max_gap)
        self.stamps: deque[float] = deque(maxlen=maxlen)
        self.poses: deque[np.ndarray] = deque(maxlen=maxlen)
        self.bad_stamps = 0

    def add(self, stamp: float, body: np.ndarray) -> None:
        if self.stamps and stamp <= self.stamps[-1]:
            self.bad_stamps += 1  # goes back or repeats: left out, as in a bag
            return
        self.stamps.append(float(stamp))
        self.poses.append(np.asarray(body, dtype=np.float64))

    def lookup(self, t: float, frame_id: str = "") -> tuple[np.ndarray | None, str, bool]:
        """``(camera pose or None, why not, final)``: final once a sample at or after ``t``
        has arrived (no later sample can change the answer)."""
        if not self.stamps:
            return None, f"no message on {self.topic} yet", False
        stamps = np.fromiter(self.stamps, dtype=np.float64, count=len(self.stamps))
        i = int(np.searchsorted(stamps, t, side="left"))
        lo, hi = max(i - 1, 0), min(i + 1, stamps.size)
        track = PoseTrack(stamps[lo:hi], np.stack([self.poses[j] for j in range(lo, hi)]),
                          self.tolerance, self.max_gap)  # fmt: skip
        body = track.at(t)
        final = bool(stamps[-1] >= t)
        if body is None:
            return None, f"no pose on {self.topic} at {t:.6f} (gap or end of the stream)", final
        return body @ self.offset, "", final


class TfPoses:
    """The camera pose from tf (``tf2_ros.Buffer`` and ``TransformListener``): ``lookup`` as
    :class:`PoseBuffer`'s, final once tf2 can answer (it interpolates
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
