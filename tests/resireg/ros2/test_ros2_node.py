"""The live node (resireg.ros2) against resireg-map: real rclpy publishers play the ray-cast
room over Fast DDS restricted to shared memory (tests/fastdds_shm.xml; no UDP socket is opened,
checked per process), the node maps it with the tiny random-initialised VLM, and its map equals
resireg-map's on a bag of the same frames (voxel keys exact, features to 1e-6). Queries, save
and clear through ROS; overload; SIGINT and resume in a subprocess.

One idea: the live node against resireg-map on the same frames; every test shares the DDS
settings, the room and the node's publishers."""

import json
import os
import signal
import subprocess
import sys
import threading
import time

import numpy as np
import pytest
import torch

from helpers.ros2 import Spinner, ros_env, udp_sockets, wait_for  # sets the DDS environment first
from helpers.run import started

rclpy = pytest.importorskip("rclpy")
pytest.importorskip("rosbags")

from resireg.mapping import SemanticMap  # noqa: E402
from resireg.mapping.colours import diverging_ramp  # noqa: E402
from resireg.ros2.bag_player import BagPlayer, frame_messages, offset_parameter  # noqa: E402
from resireg.ros2.clouds import read_cloud  # noqa: E402
from resireg_train.data.room_bag import (  # noqa: E402
    BASE_TO_LINK,
    COLOUR_LAG,
    DT,
    LINK_TO_OPTICAL,
    T0,
    TOPICS,
    room_frames,
    write_bag,
)

FRAMES = 6
VOXEL = 0.2
WINDOW = 2
CONFIG = "full@n_prototypes:4"
OFFSET = BASE_TO_LINK @ LINK_TO_OPTICAL


def player_topics(prefix=""):
    """The room's topics (the bag's, the pose on /odom) under ``prefix``: each test that starts
    its own mapping node gives it topics of its own, so a node another test left subscribed
    (the module's mapped node, or one a failed test could not close) never takes its frames."""
    return {"colour": prefix + TOPICS["colour"], "depth": prefix + TOPICS["depth"],
            "info": prefix + TOPICS["info"], "pose": prefix + "/odom"}  # fmt: skip


PLAYER_TOPICS = player_topics()


def node_parameters(tmp_path, prefix="", **extra):
    """The node's parameters for the room: as resireg-map's test sets them, the pose from
    /odom with the room's camera mount, every frame a keyframe, reliable inputs; the topics
    under ``prefix`` (player_topics)."""
    from rclpy.parameter import Parameter

    topics = player_topics(prefix)
    values = {"variant": CONFIG, "window": WINDOW, "voxel_size": VOXEL, "device": "cpu",
              "source.colour_topic": topics["colour"], "source.depth_topic": topics["depth"],
              "source.camera_info_topic": topics["info"], "source.pose_topic": topics["pose"],
              "camera_offset": offset_parameter(OFFSET), "keyframe.translation": 0.0,
              "keyframe.rotation": 0.0, "qos": "reliable", "max_wait": 1.0,
              "window_timeout": 5.0, "output_dir": str(tmp_path), "publish_rate": 20.0,
              "status_rate": 10.0, **extra}  # fmt: skip
    return [Parameter(k, value=v) for k, v in values.items()]


def play(pub, room, decoys=True, start=0, stop=None, pause=0.01):
    """The room's frames as a driver publishes them (pose, info, depth, colour; the decoys of
    write_bag: a second colour image 15 ms after each depth, then a colour image far from any
    depth and a depth image far from any colour); also a pose halfway to the next frame."""
    r, frames = room
    stop = len(frames) if stop is None else stop
    for i in range(start, stop):
        rgb, d, pose = frames[i]
        t = T0 + i * DT
        pub.send(frame_messages(rgb, d, pose, r.intrinsics, t, OFFSET, colour_lag=COLOUR_LAG))
        if decoys:
            pub.send({"colour": frame_messages((255 - rgb).astype(np.uint8), d, pose,
                                               r.intrinsics, t, OFFSET, colour_lag=0.015)["colour"]})  # fmt: skip
        time.sleep(pause)
    if decoys and stop == len(frames):
        rgb, d, pose = frames[0]
        far = frame_messages(rgb, d, pose, r.intrinsics, T0 + 10.0, OFFSET, colour_lag=0.0)
        pub.send({"colour": far["colour"]})
        late = frame_messages(rgb, d, frames[-1][2], r.intrinsics, T0 + 20.0, OFFSET)
        pub.send({"pose": late["pose"], "depth": late["depth"]})


def reference_map(bag, encoder, frames_window=WINDOW, extra=()):
    """resireg-map's path on the bag: its source, windows and make_map (conf/map.yaml composed
    with the same overrides and ``extra``), SemanticMap.add per window as its _map does."""
    from hydra import compose, initialize_config_dir

    from resireg.sources.frames import FrameCounts, windows
    from resireg_train.config.paths import CONFIG_DIR
    from resireg_train.jobs.map import build_source, make_map

    with initialize_config_dir(str(CONFIG_DIR), version_base="1.3"):
        cfg = compose("map", overrides=[f"variant={CONFIG}", f"window={frames_window}",
                                        f"voxel_size={VOXEL}", f"source.path={bag}",
                                        f"source.colour_topic={TOPICS['colour']}",
                                        f"source.depth_topic={TOPICS['depth']}",
                                        f"source.camera_info_topic={TOPICS['info']}",
                                        *extra])  # fmt: skip
    from omegaconf import OmegaConf

    source = build_source(OmegaConf.to_container(cfg.source, resolve=True))
    smap = make_map(cfg, encoder)
    counts = FrameCounts()
    for batch in windows(source, frames_window, counts, max_depth=cfg.source.max_depth):
        smap.add(batch["image"], batch["depth"], batch["intrinsics"], batch["pose"])
        counts.used += len(batch["name"])
    return smap, counts, source


def assert_same_map(a, b):
    assert len(a) > 20 and torch.equal(a.indices, b.indices)
    np.testing.assert_allclose(a.features()[1].numpy(), b.features()[1].numpy(), atol=1e-6)
    assert torch.equal(a.mean_colours(), b.mean_colours())
    assert a.frames == b.frames


@pytest.fixture(scope="module")
def room():
    return room_frames(FRAMES)


@pytest.fixture(scope="module")
def encoder(tiny_export):
    from resireg.models import build_encoder

    return build_encoder("resireg_vlm", path=str(tiny_export), device="cpu")


@pytest.fixture(scope="module")
def ros():
    context = rclpy.Context()
    rclpy.init(context=context)
    test_node = rclpy.create_node("resireg_test", context=context)
    spinner = Spinner(context, test_node)
    yield context, test_node, spinner
    spinner.stop()
    test_node.destroy_node()
    rclpy.try_shutdown(context=context)


class Inbox:
    """The messages of one topic a test subscriber received."""

    def __init__(self, node, msg_type, topic):
        from rclpy.qos import DurabilityPolicy, QoSProfile, ReliabilityPolicy

        self.messages = []
        qos = QoSProfile(depth=10, reliability=ReliabilityPolicy.RELIABLE,
                         durability=DurabilityPolicy.TRANSIENT_LOCAL)  # fmt: skip
        self.sub = node.create_subscription(msg_type, topic, self.messages.append, qos)


def call(node, srv_type, name):
    client = node.create_client(srv_type, name)
    assert client.wait_for_service(timeout_sec=10)
    future = client.call_async(srv_type.Request())
    wait_for(future.done, what=f"{name}'s reply")
    node.destroy_client(client)
    return future.result()


@pytest.fixture(scope="module")
def mapped(ros, room, encoder, tiny_export, tmp_path_factory):
    """The node, fed the room by a bag-playing node in this process; (node, folder)."""
    from resireg.ros2.node import ResiregMapNode

    context, test_node, spinner = ros
    folder = tmp_path_factory.mktemp("ros2")
    node = ResiregMapNode(parameter_overrides=node_parameters(
        folder, model_path=str(tiny_export), **{"viewer.save": str(folder / "live.rrd"),
                                                "viewer.map_every": 1}), context=context)  # fmt: skip
    pub = BagPlayer(PLAYER_TOPICS, context=context)
    spinner.add(node)
    spinner.add(pub)
    try:
        wait_for(lambda: len(node.subscribed) == 3, what="the node's subscriptions")
        wait_for(lambda: all(p.get_subscription_count() for p in pub.pubs.values()),
                 what="the player's subscribers")  # fmt: skip
        play(pub, room)
        total = FRAMES + 1
        wait_for(lambda: (lambda s: s["frames"]["used"] + sum(s["frames"]["dropped"].values())
                          == total)(node.status()), timeout=60,
                 what="every frame used or dropped")  # fmt: skip
        assert node.worker.drain()
        yield node, folder, pub
    finally:  # also when setting up failed: no node stays subscribed for the next tests
        spinner.remove(pub)
        pub.destroy_node()
        spinner.remove(node)
        node.close(save=False)
        node.destroy_node()


@pytest.mark.slow
def test_live_map_equals_resireg_map_over_shared_memory(mapped, room, encoder, tmp_path):
    """The node's map equals resireg-map's on a bag of the same frames (the decoys paired and
    left out alike: the same counts); the process holds no UDP socket."""
    node, _, _ = mapped
    bag = write_bag(tmp_path / "room", room)
    ref, counts, source = reference_map(bag, encoder)
    assert_same_map(node.worker.smap, ref)
    status = node.status()
    assert status["frames"]["received"] == counts.read == FRAMES + 1
    assert status["frames"]["used"] == counts.used == FRAMES
    assert status["frames"]["dropped"] == dict(counts.skipped) == {"unpaired": 1}
    assert status["unpaired_colour"] == source.unpaired_colour == FRAMES + 1
    assert status["map"]["voxels"] == len(ref) and status["map"]["windows"] == FRAMES // WINDOW
    assert udp_sockets(os.getpid()) == set()


def test_live_rerun_stream_logs_resireg_map_entities(mapped):
    """The node's Rerun recording (viewer.save here; viewer.serve / viewer.connect stream the same)
    holds resireg-map's entities: each frame's camera, image and depth, the path, the map."""
    from rerun.chunk import RrdReader

    node, folder, _ = mapped
    node.view.rec.flush()
    chunks = RrdReader(folder / "live.rrd").stream().to_chunks()
    entities = {str(c.entity_path) for c in chunks}
    for name in ("/world/camera", "/world/camera/image", "/world/camera/depth",
                 "/world/trajectory", "/world/map/rgb", "/world/map/pca"):  # fmt: skip
        assert name in entities, (name, entities)
    last = [c for c in chunks if str(c.entity_path) == "/world/map/pca"][-1]
    positions = last.to_record_batch().column("Points3D:positions")
    assert len(positions[len(positions) - 1]) == len(node.worker.smap)
    assert sum(c.num_rows for c in chunks if str(c.entity_path) == "/world/camera/depth") == FRAMES


def test_query_save_and_clear_through_ros(mapped, ros, encoder):
    """A query on ~/query: the similarity cloud a subscriber decodes equals SemanticMap.query
    on the node's map (its points the voxel centres, its colours the blue..red ramp), the top-k
    PoseArray the k best centres; a map of more than max_points voxels is published as every
    n-th voxel in index order; ~/save_map writes what SemanticMap.load reads back equal;
    ~/clear_map empties the map (and the status says so) and every latched output: a
    subscriber joining after the clear gets empty clouds, no pose and the markers deleted."""
    from geometry_msgs.msg import PoseArray
    from sensor_msgs.msg import PointCloud2
    from std_msgs.msg import String
    from std_srvs.srv import Trigger
    from visualization_msgs.msg import Marker, MarkerArray

    node, folder, _ = mapped
    _, test_node, _ = ros
    clouds = Inbox(test_node, PointCloud2, "/resireg_map/query/cloud")
    top = Inbox(test_node, PoseArray, "/resireg_map/query/top_k")
    pca = Inbox(test_node, PointCloud2, "/resireg_map/map/pca")
    query = test_node.create_publisher(String, "/resireg_map/query", 10)
    wait_for(lambda: query.get_subscription_count(), what="the query subscriber")
    query.publish(String(data="a red chair"))
    wait_for(lambda: clouds.messages and top.messages, what="the query's answer")
    got = read_cloud(clouds.messages[-1])
    smap = node.worker.smap
    sim = smap.query("a red chair").numpy()
    np.testing.assert_array_equal(got["points"], smap.centres().numpy())
    np.testing.assert_allclose(got["similarity"], sim, atol=1e-6)
    np.testing.assert_array_equal(got["rgb"], diverging_ramp(torch.from_numpy(sim)).numpy())
    best = np.argsort(-sim, kind="stable")[: node.values["top_k"]]
    poses = np.array([[p.position.x, p.position.y, p.position.z] for p in top.messages[-1].poses])
    np.testing.assert_allclose(poses, smap.centres().numpy()[best], atol=1e-6)
    assert clouds.messages[-1].header.frame_id == "map"
    wait_for(lambda: pca.messages, what="the PCA cloud")
    from resireg.mapping import pca_colours

    last = read_cloud(pca.messages[-1])
    np.testing.assert_array_equal(last["rgb"], pca_colours(smap.features()[1]).numpy())
    stride = -(-len(smap) // 7)  # ceil: at most 7 points
    node.values["max_points"] = 7
    try:
        before = len(pca.messages)
        node.publish_map()
        wait_for(lambda: len(pca.messages) > before, what="the downsampled cloud")
    finally:
        node.values["max_points"] = 200_000
    small = read_cloud(pca.messages[-1])
    np.testing.assert_array_equal(small["points"], smap.centres().numpy()[::stride])
    assert len(small["points"]) <= 7

    reply = call(test_node, Trigger, "/resireg_map/save_map")
    assert reply.success, reply.message
    loaded = SemanticMap.load(folder / "map", encoder)
    assert_same_map(loaded, smap)
    assert loaded.meta["kept_frames"] == FRAMES
    reply = call(test_node, Trigger, "/resireg_map/clear_map")
    assert reply.success and reply.message == f"cleared {len(loaded)} voxels"
    assert len(node.worker.smap) == 0 and node.status()["map"]["voxels"] == 0
    late = {name: Inbox(test_node, kind, f"/resireg_map/{name}") for name, kind in (
        ("query/cloud", PointCloud2), ("query/top_k", PoseArray), ("map/rgb", PointCloud2),
        ("map/pca", PointCloud2), ("query/markers", MarkerArray))}  # fmt: skip
    wait_for(lambda: all(box.messages for box in late.values()), what="the latched outputs")
    for name in ("query/cloud", "map/rgb", "map/pca"):
        assert late[name].messages[-1].width == 0, name
    assert late["query/top_k"].messages[-1].poses == []
    assert [m.action for m in late["query/markers"].messages[-1].markers] == [Marker.DELETEALL]
    for box in late.values():
        test_node.destroy_subscription(box.sub)
    test_node.destroy_publisher(query)


@pytest.mark.slow
def test_overload_stays_bounded_and_answers_queries(ros, room, encoder, tmp_path):
    """Frames published at three times the rate the node maps them (each window made to take
    0.25 s): the keyframe queue never holds more than queue_size, the pairing buffers never
    more than buffer_size, every depth image is used or dropped with its reason (queue_full
    among them), and each query sent meanwhile is answered."""
    from sensor_msgs.msg import PointCloud2
    from std_msgs.msg import String

    from resireg.ros2.node import ResiregMapNode

    context, test_node, spinner = ros
    node = ResiregMapNode(encoder, "resireg_overload", context=context,
                          parameter_overrides=node_parameters(tmp_path, "/overload", queue_size=3,
                                                              buffer_size=8, max_wait=0.2))  # fmt: skip
    smap, real_add = node.worker.smap, node.worker.smap.add

    def slow_add(*args):
        time.sleep(0.25)
        return real_add(*args)

    smap.add = slow_add  # 2 frames per 0.25 s at most: 8 frames/s
    # a deep writer history: under a loaded machine no frame is lost before the node's reader
    pub = BagPlayer(player_topics("/overload"), context=context, name="player_overload", qos=100)
    spinner.add(node)
    spinner.add(pub)
    answers = Inbox(test_node, PointCloud2, "/resireg_overload/query/cloud")
    query = test_node.create_publisher(String, "/resireg_overload/query", 10)
    try:
        wait_for(lambda: len(node.subscribed) == 3 and query.get_subscription_count()
                 and all(p.get_subscription_count() for p in pub.pubs.values()),
                 what="the overload node's subscriptions")  # fmt: skip
        r, frames = room
        seen, sent = {"queue": 0, "pairing": 0}, 0
        total = 72
        for i in range(total):  # 24 frames/s: three times the node's rate
            rgb, d, pose = frames[i % FRAMES]
            pub.send(frame_messages(rgb, d, pose, r.intrinsics, T0 + i * DT, OFFSET))
            seen["queue"] = max(seen["queue"], len(node.worker.queue))
            seen["pairing"] = max(seen["pairing"], *node.pairer.sizes().values())
            if i % 24 == 12 and len(node.worker.smap):
                before = len(answers.messages)
                query.publish(String(data=f"query {i}"))
                sent += 1
                wait_for(lambda b=before: len(answers.messages) > b, timeout=10,
                         what="an answer under load")  # fmt: skip
            time.sleep(1 / 24)
        wait_for(lambda: (lambda s: s["frames"]["used"] + sum(s["frames"]["dropped"].values())
                          == total)(node.status()), timeout=60,
                 what="every frame accounted for")  # fmt: skip
        status = node.status()
        assert node.worker.max_queue == 3 and seen["queue"] <= 3 and seen["pairing"] <= 8
        assert status["frames"]["received"] == total
        assert status["frames"]["dropped"]["queue_full"] > 0
        assert status["frames"]["used"] == node.worker.smap.frames
        assert total == status["frames"]["used"] + sum(status["frames"]["dropped"].values())
        assert sent >= 2 and len(answers.messages) == sent
    finally:  # a failed test leaves no node subscribed for the next ones
        spinner.remove(pub)
        pub.destroy_node()
        spinner.remove(node)
        node.close(save=False)
        node.destroy_node()
        test_node.destroy_publisher(query)
        test_node.destroy_subscription(answers.sub)


def _start_node(tmp_path, export, *extra, old_names=False):
    """resireg-ros2 in a subprocess; ``old_names``: ``variant`` given by its name before 0.2.0
    (``-p configuration:=``)."""
    args = [sys.executable, "-m", "resireg.ros2.cli", "--ros-args"]
    for p in node_parameters(tmp_path, "/sigint", model_path=str(export)):
        value = p.value
        text = json.dumps(value) if isinstance(value, list) else str(value)
        name = "configuration" if old_names and p.name == "variant" else p.name
        args += ["-p", f"{name}:={text}"]
    args += [x for kv in extra for x in ("-p", kv)]
    args += ["-r", "__node:=resireg_sigint"]  # apart from the module's in-process node
    return started(args, env=ros_env(), threads=1, stderr=subprocess.PIPE)


@pytest.mark.slow
def test_sigint_saves_and_resume_continues(ros, room, encoder, tiny_export, tmp_path):
    """resireg-ros2 in a subprocess maps the first four frames and, on SIGINT, saves the map and
    then publishes it once more (the last ~/map/rgb a subscriber gets holds the saved map's
    voxels), without the "publisher's context is invalid" of a context ended first; started
    again with resume:=true it continues with the last two and stops the same way on SIGTERM
    (``kill``, a service manager): the map equals resireg-map's of all six. Neither process
    opened a UDP socket. The second is given the variant by its old name (``configuration``):
    it runs as ``variant`` (the resume would be refused for another variant), with one warning."""
    from sensor_msgs.msg import PointCloud2
    from std_msgs.msg import String

    context, test_node, spinner = ros
    pub = BagPlayer(player_topics("/sigint"), context=context, name="player_sigint")
    spinner.add(pub)
    status = []
    sub = test_node.create_subscription(String, "/resireg_sigint/status",
                                        lambda m: status.append(json.loads(m.data)), 10)  # fmt: skip
    clouds = Inbox(test_node, PointCloud2, "/resireg_sigint/map/rgb")
    try:
        for start, stop, extra in ((0, 4, ()), (4, FRAMES, ("resume:=true",))):
            with _start_node(tmp_path, tiny_export, *extra, old_names=start > 0) as proc:
                status.clear()
                wait_for(lambda: status and len(status[-1]["subscribed"]) == 3, timeout=120,
                         what="the node's subscriptions")  # fmt: skip
                wait_for(lambda: all(p.get_subscription_count() for p in pub.pubs.values()),
                         what="the player's subscribers")  # fmt: skip
                play(pub, room, decoys=False, start=start, stop=stop)
                wait_for(lambda n=stop - start: status and status[-1]["frames"]["used"] == n,
                         timeout=90, what="the frames mapped")  # fmt: skip
                assert udp_sockets(proc.pid) == set()
                sig = signal.SIGINT if start == 0 else signal.SIGTERM
                assert proc.stop(sig, timeout=60) == 0, proc.stderr[-3000:]
            out, err = proc.stdout, proc.stderr
            assert f"map saved to {tmp_path / 'map'}" in out, out + err
            assert "context is invalid" not in err and "Traceback" not in err, err[-3000:]
            renamed = [x for x in err.splitlines() if "'configuration' is now 'variant'" in x]
            assert len(renamed) == (start > 0), err[-3000:]
            assert err.index("map saved to") < err.index("published the final map"), err[-3000:]
            saved = SemanticMap.load(tmp_path / "map", encoder)
            assert saved.frames == stop
            voxels = len(saved)
            wait_for(lambda n=voxels: clouds.messages and clouds.messages[-1].width == n,
                     what="the final map's cloud")  # fmt: skip
            np.testing.assert_array_equal(read_cloud(clouds.messages[-1])["points"],
                                          saved.centres().numpy())  # fmt: skip
    finally:
        test_node.destroy_subscription(clouds.sub)
        test_node.destroy_subscription(sub)
        spinner.remove(pub)
        pub.destroy_node()
    bag = write_bag(tmp_path / "room", room, decoys=False)
    ref, _, _ = reference_map(bag, encoder)
    assert_same_map(saved, ref)


def test_a_compact_live_map_equals_resireg_map_compact(ros, room, encoder, tmp_path):
    """-p storage:=compact (a basis fitted on the first frames, a small hot buffer): the node's
    map equals resireg-map's with storage=compact on a bag of the same frames, bit for bit
    (the same code, fed the same windows), its basis the same by SHA-256."""
    from resireg.ros2.node import ResiregMapNode

    context, _, spinner = ros
    compact = {"compact.dim": 8, "compact.basis_rows": 40, "compact.hot_voxels": 16}
    node = ResiregMapNode(encoder, "resireg_compact", context=context,
                          parameter_overrides=node_parameters(tmp_path, "/compact",
                                                              storage="compact", **compact))  # fmt: skip
    pub = BagPlayer(player_topics("/compact"), context=context, name="player_compact")
    spinner.add(node)
    spinner.add(pub)
    try:
        wait_for(lambda: len(node.subscribed) == 3, what="the node's subscriptions")
        wait_for(lambda: all(p.get_subscription_count() for p in pub.pubs.values()),
                 what="the player's subscribers")  # fmt: skip
        play(pub, room, decoys=False)
        wait_for(lambda: node.status()["frames"]["used"] == FRAMES, timeout=60,
                 what="every frame used")  # fmt: skip
        assert node.worker.drain()
        live = node.worker.smap
        bag = write_bag(tmp_path / "room", room, decoys=False)
        ref, _, _ = reference_map(bag, encoder, extra=("storage=compact",
                                  *(f"{k}={v}" for k, v in compact.items())))  # fmt: skip
        assert live.storage == ref.storage == "compact" and live.basis_sha256 == ref.basis_sha256
        assert len(live) > 20 and torch.equal(live.indices, ref.indices)
        assert torch.equal(live.features()[1], ref.features()[1])
        assert torch.equal(live.mean_colours(), ref.mean_colours())
    finally:
        spinner.remove(pub)
        pub.destroy_node()
        spinner.remove(node)
        node.close(save=False)
        node.destroy_node()


@pytest.mark.slow
def test_imports_carry_no_lightning_or_hydra():
    """resireg.ros2 (node, CLI, pipeline) and resireg.sources import no Lightning, Hydra,
    datasets, nor resireg_train: checked in a fresh interpreter's sys.modules."""
    code = ("import json, sys, resireg.ros2.node, resireg.ros2.cli, resireg.ros2.pipeline, "
            "resireg.sources; print(json.dumps(sorted(sys.modules)))")  # fmt: skip
    out = subprocess.run([sys.executable, "-c", code], capture_output=True, text=True,
                         env=ros_env(), check=True, timeout=300).stdout  # fmt: skip
    roots = {m.split(".")[0] for m in json.loads(out)}
    assert "rclpy" in roots and "resireg" in roots
    assert not roots & {"lightning", "pytorch_lightning", "hydra", "omegaconf", "datasets",
                        "resireg_train"}  # fmt: skip


def test_threads_end_with_close(ros, encoder, tmp_path):
    """A node that saw no frame closes at once, leaves no thread behind and saves nothing."""
    from resireg.ros2.node import ResiregMapNode

    context, _, _ = ros
    before = {t.name for t in threading.enumerate()}
    node = ResiregMapNode(encoder, "resireg_idle", context=context,
                          parameter_overrides=node_parameters(tmp_path))  # fmt: skip
    assert node.close() is None and not (tmp_path / "map").exists()
    node.destroy_node()
    assert {t.name for t in threading.enumerate()} - before == set()


def test_a_resume_is_refused_for_other_weights_or_settings(ros, encoder, tmp_path):
    """A map one node saved: a node with resume:=true and the same encoder continues it; one
    with a weight changed (model_path unchanged), another voxel size or another window is
    refused, naming the weights' digest, voxel_size or window (resireg.mapping.opening, the
    rule of resireg-map); without resume:=true the folder's map is refused."""
    import copy

    from resireg.models.factory import weights_fingerprint
    from resireg.ros2.node import ResiregMapNode
    from resireg.ros2.settings import SettingsError

    context, _, _ = ros

    def node(enc, name, **extra):
        return ResiregMapNode(enc, name, context=context,
                              parameter_overrides=node_parameters(tmp_path, "/resume", **extra))  # fmt: skip

    def closed(n):
        n.close(save=False)
        n.destroy_node()

    first = node(encoder, "resireg_resume_a")
    first.save()
    closed(first)
    saved = SemanticMap.load(tmp_path / "map", encoder).meta["identity"]
    assert saved["weights"] == weights_fingerprint(encoder)
    closed(node(encoder, "resireg_resume_b", resume=True))
    other = copy.deepcopy(encoder)
    with torch.no_grad():
        next(other.parameters()).view(-1)[0] += 1e-3
    with pytest.raises(SettingsError, match=r"other settings \(1 differ\): weights: "):
        node(other, "resireg_resume_c", resume=True)
    with pytest.raises(SettingsError, match=r"other settings \(1 differ\): voxel_size: 0\.2 in "):
        node(encoder, "resireg_resume_d", resume=True, voxel_size=0.3)
    # the window, which resireg-map's resume compared and the node's did not: one rule now
    with pytest.raises(SettingsError, match=rf"other settings \(1 differ\): window: {WINDOW} in "
                       rf"the map, {WINDOW + 1} now\. Resume with the map's values, or set "
                       r"another -p output_dir:="):  # fmt: skip
        node(encoder, "resireg_resume_f", resume=True, window=WINDOW + 1)
    with pytest.raises(SettingsError, match=r"holds a map: -p resume:=true continues it"):
        node(encoder, "resireg_resume_e")
