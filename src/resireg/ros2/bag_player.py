"""The bag player: recorded posed RGB-D frames published as a camera driver and an odometry
source would (rclpy), as ``ros2 bag play`` plays a recording: the tests' and the benchmark's
stand-in for a robot, and a way to try the node without one.

:func:`frame_messages` builds the messages of one frame: colour (``png``: ``CompressedImage``,
``rgb8`` / ``bgr8``: ``Image``) stamped ``colour_lag`` after the depth image (``16UC1`` mm or
``32FC1`` m), its ``CameraInfo`` and the body pose (``nav_msgs/Odometry``, ``odom`` ->
``base_link``) whose product with ``offset`` is the camera pose. :class:`BagPlayer` is a node
with those publishers.
"""

from __future__ import annotations

import io
from typing import Any

import numpy as np
from scipy.spatial.transform import Rotation

__all__ = ["BagPlayer", "frame_messages", "offset_parameter", "time_msg"]


def time_msg(t: float) -> Any:
    from builtin_interfaces.msg import Time

    sec = int(np.floor(t))
    return Time(sec=sec, nanosec=int(round((t - sec) * 1e9)))


def offset_parameter(offset: np.ndarray) -> list[float]:
    """A ``[4, 4]`` camera-in-body transform as the node's ``camera_offset`` (x y z qx qy qz
    qw)."""
    q = Rotation.from_matrix(offset[:3, :3]).as_quat()
    return [float(x) for x in (*offset[:3, 3], *q)]


def colour_message(rgb: np.ndarray, t: float, encoding: str = "png",
                   frame: str = "camera_optical") -> Any:  # fmt: skip
    from PIL import Image as PILImage
    from sensor_msgs.msg import CompressedImage, Image
    from std_msgs.msg import Header

    header = Header(stamp=time_msg(t), frame_id=frame)
    if encoding == "png":
        buf = io.BytesIO()
        PILImage.fromarray(rgb).save(buf, format="PNG", compress_level=1)
        return CompressedImage(header=header, format="png", data=buf.getvalue())
    px = rgb[..., ::-1] if encoding == "bgr8" else rgb
    h, w = rgb.shape[:2]
    return Image(header=header, height=h, width=w, encoding=encoding, is_bigendian=0, step=w * 3,
                 data=np.ascontiguousarray(px).tobytes())  # fmt: skip


def depth_message(depth: np.ndarray, t: float, encoding: str = "16UC1",
                  frame: str = "camera_optical") -> Any:  # fmt: skip
    from sensor_msgs.msg import Image
    from std_msgs.msg import Header

    h, w = depth.shape
    if encoding == "16UC1":
        data, step = np.clip(np.rint(depth * 1000), 0, 65535).astype("<u2").tobytes(), w * 2
    else:
        data, step = depth.astype("<f4").tobytes(), w * 4
    return Image(header=Header(stamp=time_msg(t), frame_id=frame), height=h, width=w,
                 encoding=encoding, is_bigendian=0, step=step, data=data)  # fmt: skip


def info_message(k: np.ndarray, size: tuple[int, int], t: float,
                 frame: str = "camera_optical") -> Any:  # fmt: skip
    from sensor_msgs.msg import CameraInfo
    from std_msgs.msg import Header

    k = np.asarray(k, dtype=np.float64).reshape(-1)
    proj = np.zeros(12)
    proj[[0, 2, 5, 6, 10]] = k[[0, 2, 4, 5, 8]]
    return CameraInfo(header=Header(stamp=time_msg(t), frame_id=frame), height=size[0],
                      width=size[1], distortion_model="plumb_bob", d=[0.0] * 5, k=k.tolist(),
                      r=np.eye(3).reshape(-1).tolist(), p=proj.tolist())  # fmt: skip


def odometry_message(body: np.ndarray, t: float, frame: str = "odom",
                     child: str = "base_link") -> Any:  # fmt: skip
    from nav_msgs.msg import Odometry
    from std_msgs.msg import Header

    q = Rotation.from_matrix(body[:3, :3]).as_quat()
    msg = Odometry(header=Header(stamp=time_msg(t), frame_id=frame), child_frame_id=child)
    p = msg.pose.pose
    p.position.x, p.position.y, p.position.z = (float(x) for x in body[:3, 3])
    p.orientation.x, p.orientation.y, p.orientation.z, p.orientation.w = (float(x) for x in q)
    return msg


def frame_messages(rgb: np.ndarray, depth: np.ndarray, pose: np.ndarray, k: np.ndarray,
                   t: float, offset: np.ndarray, colour: str = "png", depth_encoding: str = "16UC1",
                   colour_lag: float = 0.004) -> dict[str, Any]:  # fmt: skip
    """The messages of one frame (module docstring): ``colour``, ``depth``, ``info``, ``pose``
    (the body pose ``pose @ inv(offset)`` at the depth stamp ``t``)."""
    return {
        "pose": odometry_message(pose @ np.linalg.inv(offset), t),
        "info": info_message(k, depth.shape, t),
        "depth": depth_message(depth, t, depth_encoding),
        "colour": colour_message(rgb, t + colour_lag, colour),
    }


def BagPlayer(
    topics: dict[str, str],
    colour: str = "png",
    context: Any = None,
    name: str = "bag_player",
    qos: Any = 10,
) -> Any:
    """A node with the publishers of :func:`frame_messages` (``topics``: ``colour``, ``depth``,
    ``info``, ``pose``); ``node.send(messages)`` publishes one frame's (pose, info, depth,
    colour, in that order)."""
    from nav_msgs.msg import Odometry
    from rclpy.node import Node
    from sensor_msgs.msg import CameraInfo, CompressedImage, Image

    node = Node(name, context=context)
    types = {"colour": CompressedImage if colour == "png" else Image, "depth": Image,
             "info": CameraInfo, "pose": Odometry}  # fmt: skip
    node.pubs = {k: node.create_publisher(types[k], topics[k], qos) for k in types}

    def send(messages: dict[str, Any]) -> None:
        for key in ("pose", "info", "depth", "colour"):
            if key in messages:
                node.pubs[key].publish(messages[key])

    node.send = send
    return node
