"""What RViz shows of a live map, without RViz: the live node (``resireg-ros2``'s
:class:`resireg.ros2.node.ResiregMapNode`, in this process) maps the replayed room, a text query
goes to ``~/query``, and the clouds the node publishes are received by a subscriber as RViz's
displays would receive them and drawn with matplotlib.

Setting. One process, Fast DDS restricted to shared memory (``--profile``, default
``tests/fastdds_shm.xml``; ``RMW_IMPLEMENTATION=rmw_fastrtps_cpp``, ``ROS_DOMAIN_ID``
``--domain``): a bag-playing node publishes the ray-cast room of
:mod:`resireg_train.data.room_bag` (``--frames`` frames of ``--size``; PNG colour, 16UC1 depth,
``CameraInfo``, ``Odometry`` on ``/odom`` with the room's camera mount), every frame a keyframe.
The node builds its encoder from ``--model-path`` (default: the tests' tiny ResiregVLM, random
init with seed 0, exported to a temporary folder), the map's defaults from ``conf/`` but
``--voxel``.

What is drawn, per panel, is the last message of each topic (reliable, transient local: what a
late RViz gets), decoded with :func:`resireg.ros2.clouds.read_cloud`: ``~/map/rgb`` (voxel
centres coloured by their ``rgb`` field: what RViz's PointCloud2 display with the *RGB8* colour
transformer draws), ``~/map/pca`` and, after the query, ``~/query/cloud``, with the
``~/query/top_k`` poses as markers (RViz's ``~/query/markers`` are red cubes at those centres)
and the ``/odom`` path, as 3D scatter plots (one square per voxel centre). The weights are random
unless ``--model-path`` names a trained export: with them the PCA and similarity colours show
the structure of the features, not semantics. The PNG is saved with a ``--colours`` palette
(its largest colour error against the full-colour figure is printed; ``--colours 0``: exact).

``--rrd`` also saves the node's live Rerun recording of the same run (``viewer.save``,
``viewer.map_every`` 1, ``viewer.query`` the query; open it with ``rerun <file>``). The process
is checked to hold no UDP socket.

    python benchmarks/render_live_map.py [--out docs/images/live_map.png] [--query "a chair"]
        [--frames 12] [--size 240 320] [--voxel 0.05] [--model-path EXPORT] [--rrd FILE]
        [--profile tests/fastdds_shm.xml] [--domain N] [--threads 2] [--colours 256]
"""

from __future__ import annotations

import argparse
import io
import json
import os
import sys
import tempfile
import time
from pathlib import Path

import numpy as np

ROOT = Path(__file__).resolve().parents[1]
sys.path.insert(0, str(ROOT / "tests"))
from helpers.ros2 import Spinner, udp_sockets, wait_for  # noqa: E402  (sets the shared-memory DDS env)

NODE = "resireg_map"
TOPICS = {"rgb": f"/{NODE}/map/rgb", "pca": f"/{NODE}/map/pca",
          "query": f"/{NODE}/query/cloud", "top_k": f"/{NODE}/query/top_k"}  # fmt: skip


def dds_env(profile: Path, domain: int) -> None:
    """Fast DDS with the shared-memory-only ``profile`` in ``domain``: set before rclpy makes a
    context (it reads them then)."""
    if not profile.is_file():
        raise SystemExit(f"--profile {profile}: no such file")
    os.environ["FASTRTPS_DEFAULT_PROFILES_FILE"] = str(profile.resolve())
    os.environ["RMW_IMPLEMENTATION"] = "rmw_fastrtps_cpp"
    os.environ["ROS_DOMAIN_ID"] = str(domain)
    os.environ.pop("ROS_LOCALHOST_ONLY", None)
    os.environ.pop("ROS_AUTOMATIC_DISCOVERY_RANGE", None)


def tiny_export(folder: Path) -> Path:
    """The tests' tiny ResiregVLM (``tests/conftest.py``'s ``tiny_export``: seed 0, random)."""
    import torch

    from helpers.tiny import TINY_BACKBONE, TINY_HEAD, TINY_TEXT
    from resireg.models import ResiregVLM

    torch.manual_seed(0)
    path = folder / "export"
    ResiregVLM.build(TINY_BACKBONE, TINY_HEAD, TINY_TEXT).save_pretrained(path)
    return path


def make_node(context, model_path, folder, voxel, rrd, query):
    from rclpy.parameter import Parameter

    from resireg.ros2.bag_player import offset_parameter
    from resireg.ros2.node import ResiregMapNode
    from resireg_train.data.room_bag import BASE_TO_LINK, LINK_TO_OPTICAL
    from resireg_train.data.room_bag import TOPICS as ROOM

    values = {"model_path": str(model_path), "device": "cpu", "voxel_size": voxel,
              "source.colour_topic": ROOM["colour"], "source.depth_topic": ROOM["depth"],
              "source.camera_info_topic": ROOM["info"], "source.pose_topic": "/odom",
              "camera_offset": offset_parameter(BASE_TO_LINK @ LINK_TO_OPTICAL),
              "keyframe.translation": 0.0, "keyframe.rotation": 0.0, "qos": "reliable",
              "queue_size": 64, "buffer_size": 136, "max_wait": 2.0, "window_timeout": 2.0,
              "output_dir": str(folder), "publish_rate": 5.0}  # fmt: skip
    if rrd:
        values.update({"viewer.save": str(Path(rrd).resolve()), "viewer.map_every": 1,
                       "viewer.query": query})  # fmt: skip
    return ResiregMapNode(node_name=NODE, context=context,
                          parameter_overrides=[Parameter(k, value=v) for k, v in values.items()])  # fmt: skip


class Latest:
    """The messages a subscriber received on one topic, with RViz's QoS for latched clouds."""

    def __init__(self, node, msg_type, topic):
        from rclpy.qos import DurabilityPolicy, QoSProfile, ReliabilityPolicy

        self.messages = []
        qos = QoSProfile(depth=5, reliability=ReliabilityPolicy.RELIABLE,
                         durability=DurabilityPolicy.TRANSIENT_LOCAL)  # fmt: skip
        node.create_subscription(msg_type, topic, self.messages.append, qos)


def run(args, model_path, folder):
    import rclpy
    from geometry_msgs.msg import PoseArray
    from sensor_msgs.msg import PointCloud2
    from std_msgs.msg import String

    from resireg.ros2.bag_player import BagPlayer, frame_messages
    from resireg.ros2.clouds import read_cloud
    from resireg_train.data.room_bag import BASE_TO_LINK, DT, LINK_TO_OPTICAL, T0, room_frames
    from resireg_train.data.room_bag import TOPICS as ROOM

    room, frames = room_frames(args.frames, tuple(args.size), 0.9 * args.size[1])
    offset = BASE_TO_LINK @ LINK_TO_OPTICAL
    context = rclpy.Context()
    rclpy.init(context=context)
    viewer = rclpy.create_node("live_map_viewer", context=context)
    spinner = Spinner(context, viewer)
    inbox = {k: Latest(viewer, PointCloud2, TOPICS[k]) for k in ("rgb", "pca", "query")}
    inbox["top_k"] = Latest(viewer, PoseArray, TOPICS["top_k"])
    query = viewer.create_publisher(String, f"/{NODE}/query", 10)
    node = make_node(context, model_path, folder, args.voxel, args.rrd, args.query)
    pub = BagPlayer({"colour": ROOM["colour"], "depth": ROOM["depth"], "info": ROOM["info"],
                    "pose": "/odom"}, context=context, name="room_player")  # fmt: skip
    try:
        spinner.add(node)
        spinner.add(pub)
        wait_for(lambda: len(node.subscribed) == 3, what="the node's subscriptions")
        wait_for(lambda: all(p.get_subscription_count() for p in pub.pubs.values()),
                 what="the player's subscribers")  # fmt: skip
        path = []
        start = time.perf_counter()
        for i, (rgb, depth, pose) in enumerate(frames):
            msgs = frame_messages(rgb, depth, pose, room.intrinsics, T0 + i * DT, offset)
            p = msgs["pose"].pose.pose.position
            path.append((p.x, p.y, p.z))
            pub.send(msgs)
            time.sleep(0.02)
        wait_for(lambda: node.status()["frames"]["used"] == len(frames), timeout=600,
                 what="every frame mapped")  # fmt: skip
        node.worker.drain(600)
        voxels = node.status()["map"]["voxels"]
        wait_for(lambda: all(inbox[k].messages and inbox[k].messages[-1].width == voxels
                             for k in ("rgb", "pca")), timeout=60,
                 what="the map clouds of the whole map")  # fmt: skip
        wait_for(lambda: query.get_subscription_count(), what="the query subscriber")
        query.publish(String(data=args.query))
        wait_for(lambda: inbox["query"].messages and inbox["top_k"].messages, timeout=60,
                 what="the query's answer")  # fmt: skip
        seconds = time.perf_counter() - start
        clouds = {k: read_cloud(inbox[k].messages[-1]) for k in ("rgb", "pca", "query")}
        top = np.array([[q.position.x, q.position.y, q.position.z]
                        for q in inbox["top_k"].messages[-1].poses])  # fmt: skip
        frame_id = inbox["rgb"].messages[-1].header.frame_id
        status = node.status()
        udp = udp_sockets(os.getpid())
        if node.view is not None:
            node.view.rec.flush()
    finally:
        for n in (pub, node):
            spinner.remove(n)
        node.close(save=False)
        node.destroy_node()
        pub.destroy_node()
        spinner.stop()
        viewer.destroy_node()
        rclpy.try_shutdown(context=context)
    if udp:
        raise SystemExit(f"the process opened UDP sockets {sorted(udp)}: check --profile")
    return {"clouds": clouds, "top": top, "path": np.array(path), "frame_id": frame_id,
            "status": status, "seconds": seconds}  # fmt: skip


def render(out, got, args):
    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    clouds, top, path = got["clouds"], got["top"], got["path"]
    pts = clouds["rgb"]["points"]
    lo, hi = pts.min(0), pts.max(0)
    panels = [("rgb", "~/map/rgb: mean colour"), ("pca", "~/map/pca: PCA of the features"),
              ("query", f'~/query/cloud: "{args.query}" (blue..red)')]  # fmt: skip
    fig = plt.figure(figsize=(13.5, 4.8), dpi=args.dpi)
    for j, (key, title) in enumerate(panels):
        ax = fig.add_subplot(1, 3, j + 1, projection="3d")
        c = clouds[key]
        ax.scatter(*c["points"].T, c=c["rgb"] / 255.0, s=args.point_size, marker="s",
                   linewidths=0, depthshade=False)  # fmt: skip
        ax.plot(*path.T, color="0.25", lw=1.2, label="/odom path (base_link)")
        if key == "query":
            ax.scatter(*top.T, s=60, marker="s", facecolor=(1, 0, 0, 0.8), edgecolor="k",
                       linewidths=0.8, depthshade=False, label=f"~/query/top_k ({len(top)})")  # fmt: skip
            ax.legend(loc="lower left", fontsize=7, frameon=False)
        ax.set_title(title, fontsize=9)
        ax.set_xlim(lo[0], hi[0])
        ax.set_ylim(lo[1], hi[1])
        ax.set_zlim(lo[2], hi[2])
        ax.set_box_aspect(tuple(hi - lo))
        ax.view_init(elev=args.elev, azim=args.azim)
        ax.set_zticks(np.arange(0.0, hi[2] + 1e-6, 0.5))
        ax.tick_params(labelsize=6, pad=0)
        for axis in "xyz":
            getattr(ax, f"set_{axis}label")(f"{axis} (m)", fontsize=7, labelpad=-8)
    s = got["status"]
    weights = f"model {Path(args.model_path).name}" if args.model_path else "random weights"
    fig.suptitle(f"resireg-ros2's live map of the replayed room ({s['frames']['used']} frames, "
                 f"{s['map']['voxels']} voxels of {args.voxel} m, frame '{got['frame_id']}'): "
                 f"the PointCloud2 messages it published; {weights}", fontsize=9)  # fmt: skip
    fig.subplots_adjust(left=0.0, right=1.0, bottom=0.02, top=0.88, wspace=0.02)
    buf = io.BytesIO()
    fig.savefig(buf, format="png", dpi=args.dpi)
    plt.close(fig)
    from PIL import Image

    image = Image.open(buf).convert("RGB")
    error = 0
    if args.colours:  # a palette PNG: a quarter of the bytes; the largest colour error returned
        full = np.asarray(image, dtype=np.int16)
        image = image.quantize(args.colours, method=Image.Quantize.MAXCOVERAGE,
                               dither=Image.Dither.NONE)  # fmt: skip
        error = int(np.abs(np.asarray(image.convert("RGB"), dtype=np.int16) - full).max())
    out.parent.mkdir(parents=True, exist_ok=True)
    image.save(out, optimize=True)
    return {"size": list(image.size), "palette_max_error": error}


def main(argv: list[str] | None = None) -> None:
    parser = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    parser.add_argument("--out", type=Path, default=ROOT / "docs" / "images" / "live_map.png")
    parser.add_argument("--query", default="a chair")
    parser.add_argument("--frames", type=int, default=12)
    parser.add_argument("--size", type=int, nargs=2, default=[240, 320], help="H W")
    parser.add_argument("--voxel", type=float, default=0.05)
    parser.add_argument("--model-path", default=None, help="an export (default: the tiny one)")
    parser.add_argument("--rrd", default=None, help="also save the node's Rerun recording here")
    parser.add_argument("--profile", type=Path, default=ROOT / "tests" / "fastdds_shm.xml",
                        help="a Fast DDS profile restricted to shared memory")  # fmt: skip
    parser.add_argument("--domain", type=int, default=os.getpid() % 100, help="ROS_DOMAIN_ID")
    parser.add_argument("--threads", type=int, default=2)
    parser.add_argument("--dpi", type=int, default=100)
    parser.add_argument("--colours", type=int, default=256,
                        help="palette size of the PNG (0: full RGB)")  # fmt: skip
    parser.add_argument("--point-size", type=float, default=3.0)
    parser.add_argument("--elev", type=float, default=62.0)
    parser.add_argument("--azim", type=float, default=-62.0)
    args = parser.parse_args(argv)
    dds_env(args.profile, args.domain)
    import torch

    torch.set_num_threads(args.threads)
    with tempfile.TemporaryDirectory() as tmp:
        model = Path(args.model_path) if args.model_path else tiny_export(Path(tmp))
        got = run(args, model, Path(tmp) / "node")
    png = render(args.out, got, args)
    s = got["status"]
    print(json.dumps({"out": str(args.out), "bytes": args.out.stat().st_size, **png,
                      "frames_used": s["frames"]["used"], "voxels": s["map"]["voxels"],
                      "top_k": len(got["top"]), "seconds": round(got["seconds"], 1),
                      "rrd": args.rrd}))  # fmt: skip


if __name__ == "__main__":
    main()
