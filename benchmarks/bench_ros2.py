"""The live node (``resireg-ros2``) on this CPU: frames per second from publication to map
update, latency from a keyframe's stamp to its voxels, query latency, and the ROS layer's share.

Setting. One process: a bag-playing node publishes the ray-cast room of
:mod:`resireg_train.data.room_bag` at ``--size`` (PNG colour as ``CompressedImage``, 16UC1
depth, ``CameraInfo``, ``Odometry``) to :class:`resireg.ros2.node.ResiregMapNode` over Fast DDS
restricted to shared memory (``tests/fastdds_shm.xml``, reliable QoS), every frame a keyframe,
``window`` frames per window, the map's and ReSiReg's defaults from ``conf/`` (``full``, voxel
0.05 m). Models: the tests' tiny VLM and the 25M architecture, random weights
(``_common.build_model``).

1. Throughput: all frames published at once (the queue holds them all); frames / seconds from
   the first publication to the last window's voxels in the map; the node's own mapping
   seconds (``SemanticMap.add``) beside it.
2. Latency: frames stamped with the wall clock at publication, published at half the measured
   throughput; seconds from each keyframe's stamp to the end of its window's ``add``
   (median, max).
3. Queries on maps of 10k and 100k voxels (random unit features of the model's dimension):
   ``SemanticMap.query`` alone, and the node's path (``~/query`` published -> the similarity
   cloud received and decoded by a subscriber), median of ``--repeats``.
4. The ROS layer against mapping, in run 1: deserialising (rclpy's ``deserialize_message`` of
   the frame's three messages, timed apart), the callbacks (pairing, PNG and depth decoding),
   publishing the clouds (``~/map/*``), against the seconds in ``SemanticMap.add``.

    python benchmarks/bench_ros2.py [--frames 16] [--size 240 320] [--window 4] [--threads 2]
        [--repeats 5] [--smoke]
"""

from __future__ import annotations

import argparse
import json
import statistics
import sys
import tempfile
import time
from pathlib import Path

from _common import build_model

ROOT = Path(__file__).resolve().parents[1]
sys.path.insert(0, str(ROOT / "tests"))
from helpers.ros2 import Spinner, wait_for  # noqa: E402  (sets the shared-memory DDS environment)


def _room(frames, size):
    from resireg_train.data.room_bag import room_frames

    return room_frames(frames, tuple(size), 0.9 * size[1])


def _offset():
    from resireg_train.data.room_bag import BASE_TO_LINK, LINK_TO_OPTICAL

    return BASE_TO_LINK @ LINK_TO_OPTICAL


def _node(context, encoder, folder, name, window, queue):
    from rclpy.parameter import Parameter

    from resireg.ros2.bag_player import offset_parameter
    from resireg.ros2.node import ResiregMapNode
    from resireg_train.data.room_bag import TOPICS

    values = {"window": window, "device": "cpu", "source.colour_topic": TOPICS["colour"],
              "source.depth_topic": TOPICS["depth"], "source.camera_info_topic": TOPICS["info"],
              "source.pose_topic": "/odom", "camera_offset": offset_parameter(_offset()),
              "keyframe.translation": 0.0, "keyframe.rotation": 0.0, "qos": "reliable",
              "queue_size": queue, "buffer_size": 2 * queue + 8, "max_wait": 2.0,
              "window_timeout": 2.0, "output_dir": str(folder), "publish_rate": 2.0}  # fmt: skip
    return ResiregMapNode(encoder, name, context=context,
                          parameter_overrides=[Parameter(k, value=v) for k, v in values.items()])  # fmt: skip


def _player(context, name):
    from resireg.ros2.bag_player import BagPlayer
    from resireg_train.data.room_bag import TOPICS

    topics = {"colour": TOPICS["colour"], "depth": TOPICS["depth"], "info": TOPICS["info"],
              "pose": "/odom"}  # fmt: skip
    return BagPlayer(topics, context=context, name=name)


def _messages(room, frames, stamps):
    from resireg.ros2.bag_player import frame_messages

    r, written = room
    return [frame_messages(*written[i % len(written)], r.intrinsics, stamps[i], _offset())
            for i in range(frames)]  # fmt: skip


def _deserialise_seconds(messages, repeats=5):
    from rclpy.serialization import deserialize_message, serialize_message

    total = 0.0
    for key in ("colour", "depth", "info", "pose"):
        msg = messages[0][key]
        data = serialize_message(msg)
        start = time.perf_counter()
        for _ in range(repeats):
            deserialize_message(data, type(msg))
        total += (time.perf_counter() - start) / repeats
    return total


def _window_seconds(node):
    """Wrap the map's ``add`` to sum its seconds; returns the list it appends to."""
    spent = []
    smap = node.worker.smap
    real = smap.add

    def timed(*args):
        start = time.perf_counter()
        out = real(*args)
        spent.append(time.perf_counter() - start)
        return out

    smap.add = timed
    return spent


def throughput(context, spinner, encoder, room, frames, window, folder, name):
    node = _node(context, encoder, folder, name, window, frames)
    pub = _player(context, f"{name}_player")
    spent = _window_seconds(node)
    spinner.add(node)
    spinner.add(pub)
    wait_for(lambda: len(node.subscribed) == 3, what="subscriptions")
    wait_for(lambda: all(p.get_subscription_count() for p in pub.pubs.values()), what="matching")
    from resireg_train.data.room_bag import DT, T0

    msgs = _messages(room, frames, [T0 + i * DT for i in range(frames)])
    start = time.perf_counter()
    for m in msgs:
        pub.send(m)
    wait_for(
        lambda: node.status()["frames"]["used"] == frames, timeout=3600, what="every frame mapped"
    )
    node.worker.drain(3600)
    seconds = time.perf_counter() - start
    wait_for(lambda: node.timing["cloud_seconds"] > 0, timeout=60, what="a map cloud")
    mapping = sum(spent)
    deser = _deserialise_seconds(msgs) * frames
    ros = node.timing["ros_seconds"]
    clouds = node.timing["cloud_seconds"]
    out = {"frames": frames, "seconds": seconds, "fps": frames / seconds,
           "mapping_seconds": mapping, "mapping_fps": frames / mapping,
           "voxels": len(node.worker.smap),
           "ros_layer": {"deserialise": deser, "callbacks": ros, "clouds": clouds,
                         "share_of_mapping": (deser + ros + clouds) / mapping}}  # fmt: skip
    for n in (pub, node):
        spinner.remove(n)
    node.close(save=False)
    node.destroy_node()
    pub.destroy_node()
    return out


def latency(context, spinner, encoder, room, frames, window, rate, folder, name):
    node = _node(context, encoder, folder, name, window, frames)
    pub = _player(context, f"{name}_player")
    delays = []
    real = node._on_window

    def record(batch, rec):
        now = time.time()
        delays.extend(now - s for s in batch["stamp"])
        real(batch, rec)

    node.worker.on_window = record
    spinner.add(node)
    spinner.add(pub)
    wait_for(lambda: len(node.subscribed) == 3, what="subscriptions")
    wait_for(lambda: all(p.get_subscription_count() for p in pub.pubs.values()), what="matching")
    from resireg.ros2.bag_player import frame_messages

    r, written = room
    for i in range(frames):
        t = time.time()
        pub.send(frame_messages(*written[i % len(written)], r.intrinsics, t, _offset()))
        time.sleep(max(0.0, 1 / rate - (time.time() - t)))
    wait_for(lambda: len(delays) == frames, timeout=3600, what="every frame mapped")
    for n in (pub, node):
        spinner.remove(n)
    node.close(save=False)
    node.destroy_node()
    pub.destroy_node()
    return {"rate_hz": rate, "median_s": statistics.median(delays), "max_s": max(delays)}


def _big_map(encoder, voxels, seed=0):
    import torch

    from resireg.mapping import SemanticMap, VoxelMap

    dim = int(encoder.dense_text(encoder.text_features(["a"])).shape[-1])
    g = torch.Generator().manual_seed(seed)
    side = int(round(voxels ** (1 / 3))) + 1
    grid = torch.stack(torch.meshgrid(*[torch.arange(side)] * 3, indexing="ij"), -1)
    points = (grid.reshape(-1, 3)[:voxels].float() + 0.5) * 0.05
    smap = SemanticMap(encoder, "bb", 0.05, colour=False)
    smap.store.voxels = VoxelMap(0.05, dim)  # the storage's feature map, filled directly
    feats = torch.nn.functional.normalize(torch.randn(voxels, dim, generator=g), dim=1)
    smap.voxels.add(points, feats)
    return smap


def queries(context, spinner, test_node, encoder, folder, name, repeats):
    from sensor_msgs.msg import PointCloud2
    from std_msgs.msg import String

    from resireg.ros2.clouds import read_cloud

    node = _node(context, encoder, folder, name, 2, 4)
    spinner.add(node)
    got = []
    sub = test_node.create_subscription(PointCloud2, f"/{name}/query/cloud", got.append, 10)
    query = test_node.create_publisher(String, f"/{name}/query", 10)
    wait_for(lambda: query.get_subscription_count(), what="the query subscriber")
    out = {}
    for voxels in (10_000, 100_000):
        smap = _big_map(encoder, voxels)
        node.worker.smap = smap
        alone, path = [], []
        smap.query("warm up")
        for i in range(repeats):
            start = time.perf_counter()
            smap.query(f"a chair {i}")
            alone.append(time.perf_counter() - start)
            before = len(got)
            start = time.perf_counter()
            query.publish(String(data=f"a table {i}"))
            wait_for(lambda b=before: len(got) > b, timeout=120, what="the answer")
            read_cloud(got[-1])
            path.append(time.perf_counter() - start)
        out[voxels] = {"query_s": statistics.median(alone), "node_s": statistics.median(path)}
    test_node.destroy_subscription(sub)
    test_node.destroy_publisher(query)
    spinner.remove(node)
    node.close(save=False)
    node.destroy_node()
    return out


def main(argv: list[str] | None = None) -> None:
    parser = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    parser.add_argument("--frames", type=int, default=16)
    parser.add_argument("--size", type=int, nargs=2, default=[240, 320])
    parser.add_argument("--window", type=int, default=4)
    parser.add_argument("--threads", type=int, default=2)
    parser.add_argument("--repeats", type=int, default=5)
    parser.add_argument("--smoke", action="store_true", help="tiny sizes: seconds")
    args = parser.parse_args(argv)
    import rclpy
    import torch

    torch.set_num_threads(args.threads)
    if args.smoke:
        args.frames, args.size, args.repeats = 4, [96, 128], 1
    room = _room(args.frames, args.size)
    context = rclpy.Context()
    rclpy.init(context=context)
    test_node = rclpy.create_node("bench", context=context)
    spinner = Spinner(context, test_node)
    out = {"setting": {"frames": args.frames, "size": args.size, "window": args.window,
                       "threads": args.threads}}  # fmt: skip
    try:
        with tempfile.TemporaryDirectory() as tmp:
            for label, tiny in (("tiny", True), ("25M", False)):
                torch.manual_seed(0)
                encoder = build_model(tiny)
                name = f"bench_{label.lower()}"
                run = throughput(context, spinner, encoder, room, args.frames, args.window,
                                 Path(tmp) / f"{name}_a", name)  # fmt: skip
                rate = run["fps"] / 2
                lat = latency(context, spinner, encoder, room, args.frames, args.window, rate,
                              Path(tmp) / f"{name}_b", f"{name}_lat")  # fmt: skip
                q = queries(context, spinner, test_node, encoder, Path(tmp) / f"{name}_c",
                            f"{name}_q", args.repeats)  # fmt: skip
                out[label] = {"throughput": run, "latency": lat, "queries": q}
                print(json.dumps({label: out[label]}), flush=True)
    finally:
        spinner.stop()
        test_node.destroy_node()
        rclpy.try_shutdown(context=context)
    print(json.dumps(out, indent=2))
    print(table(out))


def table(out: dict) -> str:
    rows = ["| model | fps (publish -> map) | fps (mapping alone) | stamp -> voxels median / max "
            "(s, at half the fps) | query 10k: alone / node (ms) | query 100k: alone / node (ms)"
            " | ROS layer / mapping |", "| --- | --- | --- | --- | --- | --- | --- |"]  # fmt: skip
    for label in ("tiny", "25M"):
        if label not in out:
            continue
        r = out[label]
        t, lat, q = r["throughput"], r["latency"], r["queries"]
        rows.append(
            f"| {label} | {t['fps']:.2f} | {t['mapping_fps']:.2f} | {lat['median_s']:.2f} / "
            f"{lat['max_s']:.2f} | {1e3 * q[10_000]['query_s']:.1f} / "
            f"{1e3 * q[10_000]['node_s']:.1f} | {1e3 * q[100_000]['query_s']:.1f} / "
            f"{1e3 * q[100_000]['node_s']:.1f} | {100 * t['ros_layer']['share_of_mapping']:.1f}% |"
        )
    return "\n".join(rows)


if __name__ == "__main__":
    main()
