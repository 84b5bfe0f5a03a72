"""``sensor_msgs/PointCloud2`` of voxel maps, written and read with numpy (``sensor_msgs_py`` is
not on PyPI; the layout is fixed and small).

A cloud holds one point per voxel centre: ``x``, ``y``, ``z`` (float32, metres, the world
frame), ``rgb`` (a float32 whose bits are ``0x00RRGGBB``, what RViz's *RGB8* colour transformer
reads) and optional float32 fields (``similarity`` of a query). Little-endian, dense, one row.
"""

from __future__ import annotations

from typing import Any

import numpy as np

__all__ = ["FLOAT32", "cloud_fields", "cloud_message", "pack_rgb", "read_cloud", "unpack_rgb"]

#: ``sensor_msgs/PointField.FLOAT32``.
FLOAT32 = 7


def pack_rgb(colours: np.ndarray) -> np.ndarray:
    """``[M, 3]`` uint8 -> ``[M]`` float32 with the bits ``0x00RRGGBB`` (RViz's packed rgb)."""
    c = np.asarray(colours, dtype=np.uint32).reshape(-1, 3)
    return ((c[:, 0] << 16) | (c[:, 1] << 8) | c[:, 2]).astype("<u4").view("<f4")


def unpack_rgb(packed: np.ndarray) -> np.ndarray:
    """:func:`pack_rgb`'s inverse: ``[M]`` float32 -> ``[M, 3]`` uint8."""
    bits = np.ascontiguousarray(packed, dtype="<f4").view("<u4")
    return np.stack([(bits >> 16) & 255, (bits >> 8) & 255, bits & 255], 1).astype(np.uint8)


def cloud_fields(extra: tuple[str, ...] = ()) -> list[tuple[str, int]]:
    """``(name, byte offset)`` of the fields: x, y, z, rgb, then ``extra``, all float32."""
    return [(name, 4 * i) for i, name in enumerate(("x", "y", "z", "rgb", *extra))]


def cloud_message(header: Any, points: np.ndarray, colours: np.ndarray,
                  **extra: np.ndarray) -> Any:  # fmt: skip
    """A ``PointCloud2`` of ``[M, 3]`` points, ``[M, 3]`` uint8 colours and ``[M]`` float
    fields named by the keywords."""
    from sensor_msgs.msg import PointCloud2, PointField

    points = np.asarray(points, dtype=np.float32).reshape(-1, 3)
    names = tuple(extra)
    fields = cloud_fields(names)
    columns = [points[:, 0], points[:, 1], points[:, 2], pack_rgb(colours)]
    columns += [np.asarray(extra[n], dtype=np.float32).reshape(-1) for n in names]
    data = np.stack([c.astype("<f4", copy=False).view("<u4") for c in columns], 1)
    msg = PointCloud2()
    msg.header = header
    msg.height, msg.width = 1, int(points.shape[0])
    msg.fields = [PointField(name=n, offset=o, datatype=FLOAT32, count=1) for n, o in fields]
    msg.is_bigendian = False
    msg.point_step = 4 * len(fields)
    msg.row_step = msg.point_step * msg.width
    msg.data = np.ascontiguousarray(data).tobytes()
    msg.is_dense = True
    return msg


def read_cloud(msg: Any) -> dict[str, np.ndarray]:
    """The fields of a cloud :func:`cloud_message` wrote: ``points`` ``[M, 3]``, ``rgb``
    ``[M, 3]`` uint8 and each other float32 field ``[M]``."""
    names = [f.name for f in msg.fields]
    offsets = {f.name: int(f.offset) for f in msg.fields}
    for f in msg.fields:
        if int(f.datatype) != FLOAT32:
            raise ValueError(f"field {f.name!r}: datatype {f.datatype}, expected FLOAT32 (7)")
    dtype = np.dtype({"names": names, "formats": ["<f4"] * len(names),
                      "offsets": [offsets[n] for n in names], "itemsize": int(msg.point_step)})  # fmt: skip
    rows = np.frombuffer(bytes(msg.data), dtype=dtype, count=int(msg.width) * int(msg.height))
    out = {"points": np.stack([rows["x"], rows["y"], rows["z"]], 1)}
    if "rgb" in names:
        out["rgb"] = unpack_rgb(rows["rgb"])
    for n in names:
        if n not in ("x", "y", "z", "rgb"):
            out[n] = np.array(rows[n])
    return out
