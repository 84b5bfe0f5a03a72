"""ROS message -> numpy, shared by the bag reader (:mod:`resireg.sources.rosbag`) and the live
ROS 2 node: images, depth, camera info, stamps, transforms and poses.

Every function reads only the fields of the message, so it takes both forms a message comes
in: a message ``rosbags`` deserialised (its ``uint8[]`` fields are numpy arrays) and an
``rclpy`` message (``uint8[]`` is an ``array.array('B')``, ``double[9]`` a numpy array; tests
also pass ``bytes`` and lists). Byte fields are read through :func:`byte_view` (no copy for a
buffer), and ROS 1 field names (``K``, ``secs`` / ``nsecs``) are accepted where they differ.

- colour: ``sensor_msgs/Image`` (``rgb8``, ``bgr8``, ``rgba8``, ``bgra8``, ``mono8``) or
  ``sensor_msgs/CompressedImage`` (JPEG / PNG, decoded by PIL) -> uint8 RGB ``[H, W, 3]``;
- depth: ``sensor_msgs/Image`` ``16UC1`` (``depth_scale`` metres per unit) or ``32FC1``
  (metres), or a ``CompressedImage`` of ``compressedDepth`` PNG (16UC1; its 12-byte header is
  skipped) -> float32 ``[H, W]`` metres, 0 for no depth (0 and non-finite values);
- ``sensor_msgs/CameraInfo`` -> its ``K`` ``[3, 3]`` and image size (rectified images assumed:
  the distortion is not applied);
- ``builtin_interfaces/Time`` of a header -> seconds; ``geometry_msgs/Transform`` and ``Pose``
  -> ``[4, 4]`` matrices.

A message that cannot be decoded raises ``ValueError`` saying why (a source skips that frame
and counts it as ``undecodable``).
"""

from __future__ import annotations

import io
from typing import Any

import numpy as np
from PIL import Image

from resireg.sources.pairing import pose_matrix

__all__ = [
    "byte_view",
    "camera_intrinsics",
    "camera_size",
    "decode_colour",
    "decode_depth",
    "pose_msg_matrix",
    "stamp_seconds",
    "transform_matrix",
]

_COLOUR_CHANNELS = {"rgb8": 3, "bgr8": 3, "rgba8": 4, "bgra8": 4, "mono8": 1}
_DEPTH_DTYPES = {"16UC1": np.uint16, "MONO16": np.uint16, "32FC1": np.float32}


def byte_view(data: Any) -> np.ndarray:
    """A message's ``uint8[]`` field as a flat uint8 array: a numpy array (rosbags), an
    ``array.array`` / ``bytes`` / ``memoryview`` (rclpy) viewed without a copy, a list of ints
    converted."""
    if isinstance(data, np.ndarray):
        return np.ascontiguousarray(data).reshape(-1).view(np.uint8)
    if isinstance(data, (list, tuple)):
        return np.asarray(data, dtype=np.uint8).reshape(-1)
    return np.frombuffer(memoryview(data).cast("B"), dtype=np.uint8)


def stamp_seconds(header: Any) -> float:
    """A header's stamp in seconds (ROS 2 ``sec`` / ``nanosec``; ROS 1 ``secs`` / ``nsecs``)."""
    stamp = header.stamp
    sec = getattr(stamp, "sec", None)
    if sec is None:
        return float(stamp.secs) + 1e-9 * float(stamp.nsecs)
    return float(sec) + 1e-9 * float(stamp.nanosec)


def _is_compressed(msg: Any) -> bool:
    return hasattr(msg, "format") and not hasattr(msg, "encoding")


def decode_colour(msg: Any) -> np.ndarray:
    """``sensor_msgs/Image`` or ``CompressedImage`` -> uint8 RGB ``[H, W, 3]`` (ValueError when
    it cannot be decoded)."""
    if _is_compressed(msg):
        try:
            with Image.open(io.BytesIO(byte_view(msg.data).tobytes())) as im:
                return np.asarray(im.convert("RGB"), dtype=np.uint8).copy()
        except Exception as err:  # PIL raises many types for corrupt data
            raise ValueError(f"compressed colour ({msg.format!r}) not decodable: {err}") from None
    enc = str(msg.encoding).lower()
    if enc not in _COLOUR_CHANNELS:
        raise ValueError(
            f"colour encoding {msg.encoding!r}: expected one of {sorted(_COLOUR_CHANNELS)}"
        )
    h, w, c = int(msg.height), int(msg.width), _COLOUR_CHANNELS[enc]
    data = byte_view(msg.data)
    step = int(msg.step) or w * c
    if data.size < h * step or step < w * c:
        raise ValueError(f"colour {enc} {w}x{h}: {data.size} bytes for step {step}")
    px = data[: h * step].reshape(h, step)[:, : w * c].reshape(h, w, c)
    if enc == "mono8":
        return np.repeat(px, 3, axis=2).copy()
    if enc.startswith("bgr"):
        px = px[..., [2, 1, 0]]
    return np.array(px[..., :3], dtype=np.uint8, order="C")  # a copy: the message may be reused


def decode_depth(msg: Any, depth_scale: float = 0.001) -> np.ndarray:
    """``sensor_msgs/Image`` ``16UC1`` (``depth_scale`` metres per unit) or ``32FC1`` (metres),
    or a ``compressedDepth`` PNG -> float32 ``[H, W]`` metres, 0 where there is no depth."""
    if _is_compressed(msg):  # compressedDepth: a 16UC1 PNG after a header
        raw = byte_view(msg.data).tobytes()
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
    if enc not in _DEPTH_DTYPES:
        raise ValueError(f"depth encoding {msg.encoding!r}: expected 16UC1 or 32FC1")
    h, w = int(msg.height), int(msg.width)
    dt = np.dtype(_DEPTH_DTYPES[enc]).newbyteorder(">" if msg.is_bigendian else "<")
    step = int(msg.step) or w * dt.itemsize
    data = byte_view(msg.data)
    if data.size < h * step or step < w * dt.itemsize:
        raise ValueError(f"depth {enc} {w}x{h}: {data.size} bytes for step {step}")
    rows = data[: h * step].reshape(h, step)[:, : w * dt.itemsize]
    values = np.ascontiguousarray(rows).view(dt).reshape(h, w).astype(np.float32)
    if enc == "32FC1":
        return np.where(np.isfinite(values) & (values > 0), values, 0).astype(np.float32)
    return values * np.float32(depth_scale)


def camera_intrinsics(info: Any) -> np.ndarray:
    """A ``CameraInfo``'s ``k`` (ROS 1: ``K``) as a float64 ``[3, 3]`` matrix."""
    k = getattr(info, "k", None)
    if k is None:
        k = info.K  # ROS 1 field name
    return np.asarray(k, dtype=np.float64).reshape(3, 3)


def camera_size(info: Any) -> tuple[int, int]:
    """A ``CameraInfo``'s image size ``(height, width)`` (``(0, 0)``: it does not say)."""
    return int(info.height), int(info.width)


def transform_matrix(transform: Any) -> np.ndarray:
    """``geometry_msgs/Transform`` (``translation``, ``rotation``) -> ``[4, 4]`` float64."""
    tr, q = transform.translation, transform.rotation
    return pose_matrix((tr.x, tr.y, tr.z), (q.x, q.y, q.z, q.w))


def pose_msg_matrix(pose: Any) -> np.ndarray:
    """``geometry_msgs/Pose`` (``position``, ``orientation``) -> ``[4, 4]`` float64."""
    p, q = pose.position, pose.orientation
    return pose_matrix((p.x, p.y, p.z), (q.x, q.y, q.z, q.w))
