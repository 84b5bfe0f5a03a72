"""resireg-map source=ros2: the live source (resireg.ros2.source.LiveSource) fed by a bag-playing
publisher (resireg.ros2.bag_player, the ray-cast room) over Fast DDS restricted to shared memory
(tests/fastdds_shm.xml; no UDP socket is opened), resireg-map run in this process: its map
equals resireg-map's on a bag of the same frames (voxel keys exact, features to 1e-6) and
results.json counts the frames alike; a resumed live run adds the frames it receives. The stop
rules (idle, a closed or dropped iterator, Ctrl-C) end the stream and its executor thread.
Without rclpy, making the source names the robot extra."""

import importlib.util
import json
import os
import signal
import threading
import time

import pytest

from helpers.ros2 import udp_sockets, wait_for  # sets the DDS environment first
from resireg.errors import ConfigError

THREAD = "resireg-live-source"
#: This module's topics (test_ros2_node.player_topics): apart from any node another module left.
PREFIX = "/source"


@pytest.fixture(scope="module")
def live():
    """A bag-playing node in its own context, and tests/resireg/ros2/test_ros2_node.py's room, topics and
    comparisons (skipped without rclpy or rosbags)."""
    rclpy = pytest.importorskip("rclpy")
    pytest.importorskip("rosbags")
    import test_ros2_node as helpers

    from resireg.ros2.bag_player import BagPlayer

    context = rclpy.Context()
    rclpy.init(context=context)
    pub = BagPlayer(helpers.player_topics(PREFIX), context=context, name="player_source")
    yield pub, helpers
    pub.destroy_node()
    rclpy.try_shutdown(context=context)


@pytest.fixture(scope="module")
def room(live):
    from resireg_train.data.room_bag import room_frames

    return room_frames(live[1].FRAMES)


def source_keys(helpers):
    """The room's inputs as resireg-map's source keys: the pose from /odom with the room's
    camera mount, reliable subscriptions."""
    from resireg.ros2.bag_player import offset_parameter

    topics = helpers.player_topics(PREFIX)
    return {"colour_topic": topics["colour"], "depth_topic": topics["depth"],
            "camera_info_topic": topics["info"], "pose_topic": topics["pose"],
            "camera_offset": offset_parameter(helpers.OFFSET), "qos": "reliable",
            "max_wait": 1.0}  # fmt: skip


def feeding(pub, helpers, room, **play):
    """A thread that plays the room (``play``: test_ros2_node.play's keywords) once the
    source has subscribed to every input. Start it when no earlier source is subscribed."""
    wait_for(lambda: not any(p.get_subscription_count() for p in pub.pubs.values()),
             what="the earlier subscribers to leave")  # fmt: skip
    errors = []

    def feed():
        try:
            wait_for(lambda: all(p.get_subscription_count() for p in pub.pubs.values()),
                     timeout=60, what="the source's subscriptions")  # fmt: skip
            helpers.play(pub, room, **play)
        except BaseException as err:  # reported by the test
            errors.append(err)

    thread = threading.Thread(target=feed, daemon=True)
    thread.start()
    thread.errors = errors
    return thread


def map_live(helpers, out, export, *extra):
    """resireg-map source=ros2 in this process (map.yaml composed, run_map); results.json."""
    from hydra import compose, initialize_config_dir

    from resireg_train.cli.map import run_map
    from resireg_train.config.paths import CONFIG_DIR

    keys = [f"source.{k}={'[' + ','.join(map(repr, v)) + ']' if isinstance(v, list) else v}"
            for k, v in source_keys(helpers).items()]  # fmt: skip
    with initialize_config_dir(str(CONFIG_DIR), version_base="1.3"):
        cfg = compose("map", overrides=[f"model_path={export}", "device=cpu", "source=ros2",
                                        *keys, "source.idle=1.0",
                                        f"variant={helpers.CONFIG}",
                                        f"window={helpers.WINDOW}", f"voxel_size={helpers.VOXEL}",
                                        f"paths.output_dir={out}", *extra])  # fmt: skip
    run_map(cfg)
    return json.loads((out / "results.json").read_text())


@pytest.fixture(scope="module")
def encoder(tiny_export):
    from resireg.models import build_encoder

    return build_encoder("resireg_vlm", path=str(tiny_export), device="cpu")


@pytest.mark.slow
def test_resireg_map_source_ros2_equals_the_bag(live, room, encoder, tiny_export, tmp_path):
    """resireg-map source=ros2 while the room is published (with write_bag's decoys: a second
    colour image per frame, a colour image far from any depth, a depth image far from any
    colour): the map of resireg-map on the bag of the same messages, the same frame counts in
    results.json; the run ended source.idle after the last depth image, its executor thread
    is gone, and this process holds no UDP socket."""
    from resireg.mapping import SemanticMap
    from resireg_train.data.room_bag import write_bag

    pub, h = live
    feed = feeding(pub, h, room)
    results = map_live(h, tmp_path / "run", tiny_export)
    feed.join(10)
    assert not feed.errors, feed.errors
    ref, counts, bag_source = h.reference_map(write_bag(tmp_path / "room", room), encoder)
    h.assert_same_map(SemanticMap.load(tmp_path / "run" / "map"), ref)
    assert results["status"] == "completed" and results["params"]["source"]["kind"] == "ros2"
    frames = results["frames"]
    assert frames["read"] == counts.read == h.FRAMES + 1
    assert frames["used"] == counts.used == h.FRAMES
    assert frames["skipped"] == dict(counts.skipped) == {"unpaired": 1}
    assert results["unpaired_colour"] == bag_source.unpaired_colour == h.FRAMES + 1
    assert results["colour_stamp_faults"] == {"count": 0, "examples": []}
    assert results["corrupt_messages"] == {"by_topic": {}, "examples": []}
    assert results["damage"] is None
    assert results["map"]["voxels"] == len(ref) and results["map"]["windows"] == h.FRAMES // 2
    assert THREAD not in {t.name for t in threading.enumerate()}
    assert udp_sockets(os.getpid()) == set()


@pytest.mark.slow
def test_a_resumed_live_run_adds_the_frames_it_receives(live, room, encoder, tiny_export,
                                                         tmp_path):  # fmt: skip
    """A live run of the first four frames, then resume=true (source.idle may differ: a stop
    rule) while the last two are published: they are added (none skipped as in_map, as a
    recording's first frames would be), and the map equals resireg-map's of all six."""
    from resireg.mapping import SemanticMap
    from resireg_train.data.room_bag import write_bag

    pub, h = live
    out = tmp_path / "run"
    for start, stop, extra in ((0, 4, ()), (4, h.FRAMES, ("resume=true", "source.idle=0.8"))):
        feed = feeding(pub, h, room, decoys=False, start=start, stop=stop)
        results = map_live(h, out, tiny_export, *extra)
        feed.join(10)
        assert not feed.errors, feed.errors
        assert results["frames"]["used"] == stop - start and results["frames"]["skipped"] == {}
    smap = SemanticMap.load(out / "map")
    assert smap.meta["kept_frames"] == smap.frames == h.FRAMES
    ref, _, _ = h.reference_map(write_bag(tmp_path / "room", room, decoys=False), encoder)
    h.assert_same_map(smap, ref)


@pytest.mark.slow
def test_the_stream_ends_when_dropped_or_interrupted(live, room):
    """Iterated directly: an iterator dropped after its first frame (as resireg-map's windows
    drop it at source.limit) stops the executor thread and the context at once; with idle=None,
    Ctrl-C (SIGINT) ends the stream with every frame received, and the SIGINT handler is the
    one before again."""
    from resireg.ros2.source import LiveSource
    from resireg.sources.frames import RGBDFrame

    pub, h = live
    source = LiveSource(**source_keys(h), idle=None)
    feed = feeding(pub, h, room, decoys=False, stop=3)
    it = iter(source)
    assert isinstance(next(it), RGBDFrame)
    assert THREAD in {t.name for t in threading.enumerate()}
    del it  # the generator is finalised: its finally stops the executor
    assert THREAD not in {t.name for t in threading.enumerate()}
    assert source.ended == "the consumer stopped"
    feed.join(10)
    assert not feed.errors, feed.errors

    if threading.current_thread() is not threading.main_thread():
        pytest.skip("the Ctrl-C rule is the main thread's (signal handlers run there)")
    before = signal.getsignal(signal.SIGINT)
    feed = feeding(pub, h, room, decoys=False, stop=3)

    def ctrl_c():
        feed.join(30)
        time.sleep(1.0)  # the messages delivered (shared memory: milliseconds)
        os.kill(os.getpid(), signal.SIGINT)

    threading.Thread(target=ctrl_c, daemon=True).start()
    records = list(source)
    assert source.ended == "Ctrl-C" and signal.getsignal(signal.SIGINT) is before
    assert [type(r) for r in records] == [RGBDFrame] * 3
    assert THREAD not in {t.name for t in threading.enumerate()}


def test_without_rclpy_the_source_names_the_robot_extra(monkeypatch):
    """No rclpy: making the source is a ConfigError naming the extra (no rclpy needed here)."""
    from resireg.ros2.source import LiveSource

    real = importlib.util.find_spec
    monkeypatch.setattr(importlib.util, "find_spec",
                        lambda name, *a: None if name == "rclpy" else real(name, *a))  # fmt: skip
    with pytest.raises(ConfigError, match=r"needs the 'robot' extra \(rclpy not installed\)"):
        LiveSource(colour_topic="/c", depth_topic="/d", camera_info_topic="/i", pose_topic="/o")
    with pytest.raises(ConfigError, match=r"^idle=0: expected null or seconds > 0"):
        LiveSource(colour_topic="/c", depth_topic="/d", camera_info_topic="/i", idle=0)
