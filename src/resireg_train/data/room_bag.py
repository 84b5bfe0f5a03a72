"""A ray-cast box room recorded as a ROS bag (rosbags' own writers): the test and benchmark
recording of ``resireg-map``, and a way to try it without a robot (docs/maps.md#robot-maps-semanticmap).

    python -m resireg_train.data.room_bag OUT [--frames 6] [--ros1] [--mcap]
    resireg-map source=rosbag source.path=OUT source.colour_topic=/cam/color \
        source.depth_topic=/cam/depth source.camera_info_topic=/cam/depth/info model_path=<export>

The room is :class:`resireg_train.data.scannet_room.SyntheticRoom` (exact depth by ray casting,
known poses), coloured with :data:`~resireg_train.data.scannet_room.NYU40_COLOURS` plus noise.
Per frame: colour (``png``: ``CompressedImage``; ``rgb8`` / ``bgr8``: ``Image``) stamped
``COLOUR_LAG`` after the depth image (``16UC1`` mm or ``32FC1`` m) and its ``CameraInfo``;
``/tf_static`` ``base_link -> camera_link -> camera_optical`` (:data:`BASE_TO_LINK`,
:data:`LINK_TO_OPTICAL`, the usual optical-frame rotation), ``/tf`` ``map -> odom`` (identity) and
``odom -> base_link`` at every depth stamp and halfway between (on the interpolated path).
``decoys``: a second colour image per frame 15 ms after the depth (farther than the right one,
inverted colours), a colour image far from any depth and a depth image far from any colour.
``corrupt``: the frame whose colour message is garbage.
"""

from __future__ import annotations

import argparse
import io
from pathlib import Path

import numpy as np
from PIL import Image
from scipy.spatial.transform import Rotation, Slerp

from resireg_train.data.scannet_room import NYU40_COLOURS, RAW_LABELS, SyntheticRoom

__all__ = ["BASE_TO_LINK", "COLOUR_LAG", "DT", "LINK_TO_OPTICAL", "T0", "TOPICS", "room_frames",
           "write_bag"]  # fmt: skip

T0 = 1700000000.0  # the first frame's stamp (seconds)
DT = 0.1  # seconds between frames
COLOUR_LAG = 0.004  # the colour image of frame i is stamped T0 + i DT + COLOUR_LAG
TOPICS = {"colour": "/cam/color", "depth": "/cam/depth", "info": "/cam/depth/info"}
#: base_link -> camera_link: the camera's mount on the robot.
BASE_TO_LINK = np.eye(4)
BASE_TO_LINK[:3, 3] = (0.2, -0.05, 0.3)
BASE_TO_LINK[:3, :3] = Rotation.from_euler("z", 10, degrees=True).as_matrix()
#: camera_link (x forward, z up) -> camera_optical (x right, y down, z forward).
LINK_TO_OPTICAL = np.eye(4)
LINK_TO_OPTICAL[:3, :3] = Rotation.from_euler("zyx", [-90, 0, -90], degrees=True).as_matrix()


def room_frames(frames: int = 6, image_size: tuple[int, int] = (96, 128), focal: float = 80.0):
    """``(room, [(uint8 RGB [H, W, 3], float32 depth [H, W] m, camera-to-world [4, 4])...])``."""
    r = SyntheticRoom(image_size=image_size, focal=focal, frames=frames, bad_pose_frame=None)
    nyu = np.zeros(max(RAW_LABELS) + 1, dtype=np.int64)
    for raw, (_, n, _) in RAW_LABELS.items():
        nyu[raw] = n
    out = []
    for i in range(frames):
        depth, raw = r.render(i)
        rgb = NYU40_COLOURS[nyu[raw]].astype(np.int64)
        rgb = (rgb + np.random.default_rng(i).integers(-25, 25, rgb.shape)).clip(0, 255)
        out.append((rgb.astype(np.uint8), depth.astype(np.float32), r.pose(i)))
    return r, out


def _time(ts, t):
    sec = int(np.floor(t))
    return ts.types["builtin_interfaces/msg/Time"](sec=sec, nanosec=int(round((t - sec) * 1e9)))


def _header(ts, t, frame, ros1):
    h = ts.types["std_msgs/msg/Header"]
    return h(seq=0, stamp=_time(ts, t), frame_id=frame) if ros1 else h(stamp=_time(ts, t),
                                                                      frame_id=frame)  # fmt: skip


def _tf(ts, t, parent, child, m, ros1):
    ty = ts.types
    q = Rotation.from_matrix(m[:3, :3]).as_quat()
    tr = ty["geometry_msgs/msg/Transform"](
        translation=ty["geometry_msgs/msg/Vector3"](x=m[0, 3], y=m[1, 3], z=m[2, 3]),
        rotation=ty["geometry_msgs/msg/Quaternion"](x=q[0], y=q[1], z=q[2], w=q[3]))  # fmt: skip
    return ty["geometry_msgs/msg/TransformStamped"](header=_header(ts, t, parent, ros1),
                                                    child_frame_id=child, transform=tr)  # fmt: skip


def write_bag(path, room, colour="png", depth="16UC1", ros1=False, storage="sqlite3",
              decoys=True, corrupt=None):  # fmt: skip
    """The room as a bag: colour (``png``: CompressedImage, ``rgb8`` / ``bgr8``: Image), depth
    (16UC1 mm / 32FC1 m) and CameraInfo per frame; /tf_static base_link -> camera_link ->
    camera_optical; /tf map -> odom (identity) and odom -> base_link at each depth stamp and
    halfway between. ``decoys``: a second colour image of each frame 0.015 s after the depth
    (farther than the right one), an extra colour image far from any depth, and a depth image
    with no colour within 0.02 s. ``corrupt``: the frame whose colour message is garbage."""
    from rosbags.typesys import Stores, get_typestore

    r, frames = room
    path = Path(path)
    if ros1:
        from rosbags.rosbag1 import Writer
        from rosbags.typesys import get_types_from_msg

        ts = get_typestore(Stores.ROS1_NOETIC)  # its store lacks tf2_msgs: register it
        ts.register(get_types_from_msg("geometry_msgs/TransformStamped[] transforms",
                                       "tf2_msgs/msg/TFMessage"))  # fmt: skip
        writer, serialize = Writer(path), ts.serialize_ros1
    else:
        from rosbags.rosbag2 import StoragePlugin, Writer

        ts = get_typestore(Stores.ROS2_HUMBLE)
        plugin = StoragePlugin.MCAP if storage == "mcap" else StoragePlugin.SQLITE3
        writer, serialize = Writer(path, version=9, storage_plugin=plugin), ts.serialize_cdr
    ty = ts.types
    msgs = []  # (time, topic, msg)

    def colour_msg(rgb, t, garbage=False):
        if colour == "png":
            buf = io.BytesIO()
            Image.fromarray(rgb).save(buf, format="PNG")
            data = b"not an image" if garbage else buf.getvalue()
            return ty["sensor_msgs/msg/CompressedImage"](
                header=_header(ts, t, "camera_optical", ros1), format="png",
                data=np.frombuffer(data, dtype=np.uint8))  # fmt: skip
        px = rgb[..., ::-1] if colour == "bgr8" else rgb
        h, w = rgb.shape[:2]
        return ty["sensor_msgs/msg/Image"](header=_header(ts, t, "camera_optical", ros1),
                                           height=h, width=w, encoding=colour, is_bigendian=0,
                                           step=w * 3, data=np.ascontiguousarray(px).reshape(-1))  # fmt: skip

    def depth_msg(d, t):
        h, w = d.shape
        if depth == "16UC1":
            data = np.clip(np.rint(d * 1000), 0, 65535).astype("<u2").view(np.uint8).reshape(-1)
            step = w * 2
        else:
            data = d.astype("<f4").view(np.uint8).reshape(-1)
            step = w * 4
        return ty["sensor_msgs/msg/Image"](header=_header(ts, t, "camera_optical", ros1),
                                           height=h, width=w, encoding=depth, is_bigendian=0,
                                           step=step, data=data)  # fmt: skip

    k = r.intrinsics.reshape(-1)
    names = ("D", "K", "R", "P") if ros1 else ("d", "k", "r", "p")
    roi = ty["sensor_msgs/msg/RegionOfInterest"](x_offset=0, y_offset=0, height=0, width=0,
                                                 do_rectify=False)  # fmt: skip
    proj = np.zeros(12)
    proj[[0, 2, 5, 6, 10]] = k[[0, 2, 4, 5, 8]]
    for i, (rgb, d, pose) in enumerate(frames):
        t = T0 + i * DT
        msgs.append((t + COLOUR_LAG, TOPICS["colour"], colour_msg(rgb, t + COLOUR_LAG,
                                                                  garbage=i == corrupt)))  # fmt: skip
        if decoys:
            wrong = (255 - rgb).astype(np.uint8)
            msgs.append((t + 0.015, TOPICS["colour"], colour_msg(wrong, t + 0.015)))
        msgs.append((t, TOPICS["depth"], depth_msg(d, t)))
        info = dict(zip(names, (np.zeros(5), k, np.eye(3).reshape(-1), proj), strict=True))
        msgs.append((t, TOPICS["info"], ty["sensor_msgs/msg/CameraInfo"](
            header=_header(ts, t, "camera_optical", ros1), height=d.shape[0], width=d.shape[1],
            distortion_model="plumb_bob", binning_x=0, binning_y=0, roi=roi, **info)))  # fmt: skip
        base = pose @ np.linalg.inv(BASE_TO_LINK @ LINK_TO_OPTICAL)
        msgs.append(
            (
                t,
                "/tf",
                ty["tf2_msgs/msg/TFMessage"](
                    transforms=[
                        _tf(ts, t, "map", "odom", np.eye(4), ros1),
                        _tf(ts, t, "odom", "base_link", base, ros1),
                    ]
                ),
            )
        )
        if i + 1 < len(frames):  # a sample halfway: on the straight line between the neighbours
            nxt = frames[i + 1][2] @ np.linalg.inv(BASE_TO_LINK @ LINK_TO_OPTICAL)
            mid = np.eye(4)
            mid[:3, :3] = Slerp([0, 1], Rotation.from_matrix([base[:3, :3], nxt[:3, :3]]))(
                [0.5]).as_matrix()[0]  # fmt: skip
            mid[:3, 3] = (base[:3, 3] + nxt[:3, 3]) / 2
            msgs.append((t + DT / 2, "/tf", ty["tf2_msgs/msg/TFMessage"](
                transforms=[_tf(ts, t + DT / 2, "odom", "base_link", mid, ros1)])))  # fmt: skip
    if decoys:  # a colour image far from any depth, a depth image far from any colour
        msgs.append((T0 + 10.0, TOPICS["colour"], colour_msg(frames[0][0], T0 + 10.0)))
        msgs.append((T0 + 20.0, TOPICS["depth"], depth_msg(frames[0][1], T0 + 20.0)))
    static = ty["tf2_msgs/msg/TFMessage"](transforms=[
        _tf(ts, T0, "base_link", "camera_link", BASE_TO_LINK, ros1),
        _tf(ts, T0, "camera_link", "camera_optical", LINK_TO_OPTICAL, ros1)])  # fmt: skip
    msgs.append((T0 - 1.0, "/tf_static", static))
    with writer:
        conns = {}
        types = {TOPICS["colour"]: "sensor_msgs/msg/CompressedImage" if colour == "png"
                 else "sensor_msgs/msg/Image", TOPICS["depth"]: "sensor_msgs/msg/Image",
                 TOPICS["info"]: "sensor_msgs/msg/CameraInfo", "/tf": "tf2_msgs/msg/TFMessage",
                 "/tf_static": "tf2_msgs/msg/TFMessage"}  # fmt: skip
        for topic, msgtype in types.items():
            conns[topic] = writer.add_connection(topic, msgtype, typestore=ts)
        for t, topic, msg in sorted(msgs, key=lambda m: m[0]):
            writer.write(conns[topic], int(round(t * 1e9)), serialize(msg, types[topic]))
    return path


def main(argv: list[str] | None = None) -> None:
    parser = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    parser.add_argument("out", help="the bag to write (a folder for ROS 2, a .bag file for ROS 1)")
    parser.add_argument("--frames", type=int, default=6)
    parser.add_argument("--ros1", action="store_true")
    parser.add_argument("--mcap", action="store_true")
    args = parser.parse_args(argv)
    print(write_bag(args.out, room_frames(args.frames), ros1=args.ros1,
                    storage="mcap" if args.mcap else "sqlite3"))  # fmt: skip


if __name__ == "__main__":
    main()
