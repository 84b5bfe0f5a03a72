"""Robot recordings in, maps out: bags written here with rosbags' own writers (ROS 2 sqlite3 and
MCAP, ROS 1), a TUM RGB-D folder, and resireg-map end to end with its Rerun recording read back by
the Rerun SDK. The room is ray cast (resireg_train.data.scannet_room) with known poses; the map
is compared with the direct patch_points + VoxelMap path on the known frames."""

import json

import numpy as np
import pytest
import torch
import torch.nn.functional as F
from PIL import Image
from scipy.spatial.transform import Rotation

from helpers.tiny import TINY_BACKBONE, TINY_HEAD, TINY_TEXT
from resireg.mapping import SemanticMap, VoxelMap, patch_points
from resireg.models import ResiregVLM
from resireg.sources.frames import FrameCounts, RGBDFrame, SkippedFrame, windows
from resireg.sources.pairing import pair_nearest
from resireg_train.data.scannet_room import SyntheticRoom

rosbags = pytest.importorskip("rosbags")
from resireg_train.data.room_bag import COLOUR_LAG, DT, T0, TOPICS, room_frames, write_bag  # noqa: E402

VOXEL = 0.2
FRAMES = 6


@pytest.fixture(scope="module")
def room():
    return room_frames(FRAMES)


@pytest.fixture(scope="module")
def encoder():
    torch.manual_seed(0)
    return ResiregVLM.build(TINY_BACKBONE, TINY_HEAD, TINY_TEXT).eval()


def bag_source(path, **kwargs):
    from resireg.sources.rosbag import BagSource, BagTopics

    topics = BagTopics(colour=TOPICS["colour"], depth=TOPICS["depth"],
                       camera_info=TOPICS["info"], world_frame="map", **kwargs)  # fmt: skip
    return BagSource(path, topics, tolerance=0.02)


def expected_depth(d, encoding):
    if encoding == "16UC1":
        return np.clip(np.rint(d * 1000), 0, 65535).astype(np.uint16).astype(
            np.float32
        ) * np.float32(0.001)
    return d


@pytest.mark.parametrize(("colour", "depth", "ros1", "storage"), [
    ("png", "16UC1", False, "sqlite3"), ("rgb8", "32FC1", False, "mcap"),
    ("bgr8", "16UC1", True, None)])  # fmt: skip
def test_bag_frames_are_the_written_ones(tmp_path, room, colour, depth, ros1, storage):
    """Each kept frame is its own colour image (not the decoy 11 ms farther), its depth in metres,
    the depth image's K and the camera pose through map -> odom -> base_link -> camera_link ->
    camera_optical; the decoys are counted as unpaired."""
    path = tmp_path / ("room.bag" if ros1 else "room")
    source = bag_source(write_bag(path, room, colour, depth, ros1, storage or "sqlite3"))
    records = list(source)
    frames = [r for r in records if isinstance(r, RGBDFrame)]
    skipped = [r for r in records if isinstance(r, SkippedFrame)]
    assert len(frames) == FRAMES and [s.kind for s in skipped] == ["unpaired"]
    assert skipped[0].name.startswith(f"{TOPICS['depth']}@{T0 + 20.0:.6f}"[:20])
    assert source.unpaired_colour == FRAMES + 1  # the decoys and the far image
    r, written = room
    for frame, (rgb, d, pose) in zip(frames, written, strict=True):
        np.testing.assert_array_equal(frame.image, rgb)
        np.testing.assert_array_equal(frame.depth, expected_depth(d, depth))
        np.testing.assert_allclose(frame.intrinsics, r.intrinsics)
        np.testing.assert_allclose(frame.pose, pose, atol=1e-9)


def test_bag_map_equals_patch_points_and_voxel_map(tmp_path, room, encoder):
    """resireg-map's path (bag -> windows -> SemanticMap.add) against the direct path on the known
    frames (the encoder's normalised tokens at patch_points, one VoxelMap): voxel keys exact,
    features to 1e-6. The tf chain is interpolated halfway between the samples too."""
    path = write_bag(tmp_path / "room", room)
    counts = FrameCounts()
    smap = SemanticMap(encoder, "bb", VOXEL)
    for batch in windows(bag_source(path), 4, counts):
        smap.add(batch["image"], batch["depth"], batch["intrinsics"], batch["pose"])
    assert counts.read == FRAMES + 1 and dict(counts.skipped) == {"unpaired": 1}
    r, written = room
    ref = VoxelMap(VOXEL, encoder.encode(torch.zeros(1, 3, 16, 16)).language.shape[1])
    k = torch.from_numpy(r.intrinsics).float()
    for s in (0, 4):
        part = written[s : s + 4]
        images = torch.stack([torch.from_numpy(x[0]).permute(2, 0, 1) for x in part])
        depth = torch.stack([torch.from_numpy(expected_depth(x[1], "16UC1")) for x in part])
        poses = torch.stack([torch.from_numpy(x[2]) for x in part])
        with torch.no_grad():
            lang = encoder.encode(encoder.input_rule.normalize(images.float() / 255)).language
        dense = F.normalize(lang.float(), dim=1)
        pts, valid = patch_points(depth, k, poses, tuple(dense.shape[-2:]))
        ref.add(pts[valid], dense.permute(0, 2, 3, 1)[valid])
    assert torch.equal(smap.indices, ref.indices)
    np.testing.assert_allclose(smap.features()[1].numpy(), ref.features()[1].numpy(), atol=1e-6)
    # a pose halfway between two tf samples: the interpolated chain
    source = bag_source(path)
    chain = source.tf.chain("map", "camera_optical")
    mid = source.tf.lookup(chain, T0 + DT / 4)
    a, b = written[0][2], written[1][2]
    assert (
        mid is not None and np.linalg.norm(mid[:3, 3] - (0.75 * a[:3, 3] + 0.25 * b[:3, 3])) < 0.05
    )


def test_undecodable_and_unposed_frames_are_named_and_counted(tmp_path, room):
    path = write_bag(tmp_path / "room", room, decoys=False, corrupt=2)
    records = list(bag_source(path))
    bad = [r for r in records if isinstance(r, SkippedFrame)]
    assert [b.kind for b in bad] == ["undecodable"]
    assert f"{TOPICS['colour']}@{T0 + 2 * DT + COLOUR_LAG:.6f}" in bad[0].reason
    assert "not decodable" in bad[0].reason
    records = list(bag_source(path, camera_frame="no_such_frame"))
    assert [r.kind for r in records] == ["no_pose"] * 2 + ["undecodable"] + ["no_pose"] * 3
    assert "no tf chain map -> no_such_frame (frames: " in records[0].reason


def test_missing_topic_lists_the_bag_topics(tmp_path, room):
    from resireg.sources.rosbag import BagSource, BagTopics, MissingTopicError

    path = write_bag(tmp_path / "room", room, decoys=False)
    topics = BagTopics(colour="/camera/rgb", depth=TOPICS["depth"], camera_info=TOPICS["info"])
    with pytest.raises(MissingTopicError) as info:
        BagSource(path, topics)
    text = str(info.value)
    assert "colour_topic='/camera/rgb' is not in the bag" in text
    assert "source." not in text  # the library names its own arguments
    for topic, msgtype in ((TOPICS["colour"], "sensor_msgs/msg/CompressedImage"),
                           (TOPICS["depth"], "sensor_msgs/msg/Image"),
                           ("/tf_static", "tf2_msgs/msg/TFMessage")):  # fmt: skip
        assert f"{topic} ({msgtype})" in text
    topics = BagTopics(colour=TOPICS["colour"], depth=TOPICS["depth"], camera_info=TOPICS["depth"])
    with pytest.raises(MissingTopicError, match="camera_info_topic='/cam/depth' has type "
                                                 "sensor_msgs/msg/Image"):  # fmt: skip
        BagSource(path, topics)


def test_pair_nearest_by_hand():
    stamps = np.array([0.0, 0.10, 0.20, 0.30])
    anchors = np.array([0.004, 0.05, 0.149, 0.151, 0.31, 0.5, -0.01])
    # 0.05 is equally near 0.0 and 0.1: the earlier wins; 0.5 is 0.2 from the nearest
    got = pair_nearest(anchors, stamps, tolerance=0.06)
    assert got.tolist() == [0, 0, 1, 2, 3, -1, 0]
    assert pair_nearest(anchors, stamps, tolerance=0.005).tolist() == [0, -1, -1, -1, -1, -1, -1]


def write_tum(folder, room, scale=5000.0):
    """A TUM RGB-D sequence: rgb/ and depth/ PNGs with their lists (colour 3 ms after depth),
    and groundtruth.txt at 100 Hz on a trajectory whose pose at any time is known: constant
    angular velocity about z and constant velocity, so interpolation between samples is exact."""
    r, frames = room
    (folder / "rgb").mkdir(parents=True)
    (folder / "depth").mkdir()
    rgb_lines, depth_lines = ["# color images"], ["# depth maps"]
    for i, (rgb, d, _) in enumerate(frames):
        t = T0 + i * DT
        Image.fromarray(rgb).save(folder / "rgb" / f"{t + 0.003:.6f}.png")
        Image.fromarray(np.clip(np.rint(d * scale), 0, 65535).astype(np.uint16)).save(
            folder / "depth" / f"{t:.6f}.png")  # fmt: skip
        rgb_lines.append(f"{t + 0.003:.6f} rgb/{t + 0.003:.6f}.png")
        depth_lines.append(f"{t:.6f} depth/{t:.6f}.png")
    (folder / "rgb.txt").write_text("\n".join(rgb_lines) + "\n")
    (folder / "depth.txt").write_text("\n".join(depth_lines) + "\n")
    lines = ["# timestamp tx ty tz qx qy qz qw"]
    for j in range(int(FRAMES * DT * 100) + 5):
        t = T0 - 0.02 + j * 0.01 + 0.0037  # samples off the frame stamps
        lines.append(f"{t:.6f} " + " ".join(f"{v:.9f}" for v in tum_pose(t, quat=True)))
    (folder / "groundtruth.txt").write_text("\n".join(lines) + "\n")
    return folder


def tum_pose(t, quat=False):
    s = t - T0
    rot = Rotation.from_euler("z", 0.8 * s) * Rotation.from_euler("x", -100, degrees=True)
    trans = np.array([1.0 + 0.3 * s, 2.0 - 0.1 * s, 1.2])
    if quat:
        return [*trans, *rot.as_quat()]
    m = np.eye(4)
    m[:3, :3], m[:3, 3] = rot.as_matrix(), trans
    return m


def test_tum_layout(tmp_path, room):
    from resireg.sources.tum import CAMERAS, TumSource

    r, frames = room
    folder = write_tum(tmp_path / "seq", room)
    source = TumSource(folder, camera="fr1")
    records = list(source)
    assert len(records) == FRAMES and all(isinstance(x, RGBDFrame) for x in records)
    fx, fy, cx, cy = CAMERAS["fr1"]
    for i, frame in enumerate(records):
        np.testing.assert_array_equal(frame.image, frames[i][0])
        mm = np.clip(np.rint(frames[i][1] * 5000), 0, 65535).astype(np.uint16)
        np.testing.assert_allclose(frame.depth, mm / 5000.0, rtol=1e-6)
        np.testing.assert_allclose(frame.pose, tum_pose(T0 + i * DT), atol=1e-6)
        np.testing.assert_allclose(frame.intrinsics, [[fx, 0, cx], [0, fy, cy], [0, 0, 1]])
    short = TumSource(folder, tolerance=0.002, intrinsics=[80, 80, 63.5, 47.5])
    kinds = [x.kind for x in short if isinstance(x, SkippedFrame)]
    assert kinds == ["unpaired"] * FRAMES  # colour 3 ms away
    with pytest.raises(ValueError, match="^camera='fr9'"):
        TumSource(folder, camera="fr9")


@pytest.mark.slow
def test_resireg_map_cli_bag_rerun_and_resume(tmp_path, room, tiny_export):
    """resireg-map on a bag: results.json counts, the saved map and PLY, the Rerun recording read
    back with rerun.chunk.RrdReader (entities, the map's point count); a run cut by
    source.limit and resumed equals one uninterrupted run."""
    from helpers.run import run, run_side_by_side

    pytest.importorskip("rerun")
    from rerun.chunk import RrdReader

    bag = write_bag(tmp_path / "room", room)
    common = [f"model_path={tiny_export}", "device=cpu", "source=rosbag", f"source.path={bag}",
              f"source.colour_topic={TOPICS['colour']}", f"source.depth_topic={TOPICS['depth']}",
              f"source.camera_info_topic={TOPICS['info']}", "variant=full@n_prototypes:4",
              "window=2", f"voxel_size={VOXEL}", "save_every=1"]  # fmt: skip
    whole, cut = tmp_path / "whole", tmp_path / "cut"
    # The whole run, the cut one and the refused one are independent: started side by side,
    # one torch thread each (the resume below too, so whole and cut + resume compute alike).
    proc, _, refused = run_side_by_side(
        ("resireg-map", *common, f"hydra.run.dir={whole}", f"viewer.save={whole}/map.rrd",
         "viewer.query=a chair", "ply.colour_by=rgb"),
        ("resireg-map", *common, f"hydra.run.dir={cut}", "source.limit=4"),
        ("resireg-map", *common, "source.colour_topic=/nope", f"hydra.run.dir={tmp_path}/x"),
        check=(True, True, False),
    )  # fmt: skip
    assert f"frames: {FRAMES + 1} read, {FRAMES} used, skipped: 1 unpaired" in proc.stdout
    results = json.loads((whole / "results.json").read_text())
    assert results["status"] == "completed" and results["frames"]["used"] == FRAMES
    voxels = results["map"]["voxels"]
    assert voxels > 20 and (whole / "map.ply").is_file()
    chunks = RrdReader(whole / "map.rrd").stream().to_chunks()
    entities = {str(c.entity_path) for c in chunks}
    for name in ("/world/camera", "/world/camera/image", "/world/camera/depth",
                 "/world/trajectory", "/world/map/rgb", "/world/map/pca", "/world/map/query"):  # fmt: skip
        assert name in entities, (name, entities)
    last = [c for c in chunks if str(c.entity_path) == "/world/map/pca"][-1]
    positions = last.to_record_batch().column("Points3D:positions")
    assert len(positions[len(positions) - 1]) == voxels
    images = sum(c.num_rows for c in chunks if str(c.entity_path) == "/world/camera/depth")
    assert images == FRAMES
    assert json.loads((cut / "results.json").read_text())["map"]["frames"] == 4
    run("resireg-map", *common, f"hydra.run.dir={cut}", "resume=true", threads=1)
    a, b = SemanticMap.load(whole / "map"), SemanticMap.load(cut / "map")
    assert a.frames == b.frames == FRAMES
    assert torch.equal(a.indices, b.indices) and torch.equal(a.features()[1], b.features()[1])
    assert refused.returncode != 0 and "/cam/depth (sensor_msgs/msg/Image)" in refused.stderr


def test_scannet_export_source(tmp_path):
    """A ScanNet scene export (no labels needed): frames in order, depth = uint16 mm / 1000, the
    depth intrinsics, the poses; the -inf pose ScanNet writes where tracking was lost reaches
    the windows, which drop it as no_pose."""
    from resireg.sources.scannet import scannet_rgbd
    from resireg_train.data.scannet_room import write_scene

    room = SyntheticRoom(frames=5, bad_pose_frame=2)
    folder = write_scene(tmp_path, "scene0000_00", room)
    records = list(scannet_rgbd(folder))
    assert len(records) == 5 and all(isinstance(r, RGBDFrame) for r in records)
    for i, frame in enumerate(records):
        mm = np.asarray(Image.open(folder / "depth" / f"{i}.png")).astype(np.float32)
        np.testing.assert_array_equal(frame.depth, mm / 1000.0)
        np.testing.assert_allclose(frame.intrinsics, room.intrinsics, atol=1e-9)
        assert frame.image.shape == (*room.image_size, 3)
        if i != 2:
            np.testing.assert_allclose(frame.pose, room.pose(i), atol=1e-8)
    counts = FrameCounts()
    batches = list(windows(iter(records), 2, counts))
    assert [len(b["name"]) for b in batches] == [2, 2] and dict(counts.skipped) == {"no_pose": 1}
    assert counts.read == 5 and "pose" not in str(batches[0]["name"])
    with pytest.raises(FileNotFoundError, match="^path=.*no color/ folder"):
        next(scannet_rgbd(tmp_path / "nothing"))


# ---------------------------------------------------------------- faults (issue: reliability v4)
CLI_TOPICS = [f"source.colour_topic={TOPICS['colour']}", f"source.depth_topic={TOPICS['depth']}",
              f"source.camera_info_topic={TOPICS['info']}"]  # fmt: skip


def rewrite_bag(src, dst, edit):
    """Copy a ROS 2 bag message by message with rosbags' reader and writer: ``edit(topic,
    bag_time, msg)`` returns ``[(bag_time, msg or raw bytes)]`` (``[]`` drops the message)."""
    from rosbags.highlevel import AnyReader
    from rosbags.rosbag2 import Writer

    with AnyReader([src]) as reader:
        ts = reader.typestore
        out = []
        for conn, t, raw in reader.messages():
            for t2, msg in edit(conn.topic, t, reader.deserialize(raw, conn.msgtype)):
                out.append((t2, conn.topic, conn.msgtype, msg))
        with Writer(dst, version=9) as writer:
            conns = {c.topic: writer.add_connection(c.topic, c.msgtype, typestore=ts)
                     for c in reader.connections}  # fmt: skip
            for t, topic, msgtype, msg in sorted(out, key=lambda m: m[0]):
                data = msg if isinstance(msg, bytes) else ts.serialize_cdr(msg, msgtype)
                writer.write(conns[topic], t, data)
    return dst


def restamped(msg, seconds):
    """``msg`` with its header stamp moved by ``seconds``."""
    from dataclasses import replace

    ns = msg.header.stamp.sec * 10**9 + msg.header.stamp.nanosec + round(seconds * 1e9)
    stamp = replace(msg.header.stamp, sec=ns // 10**9, nanosec=ns % 10**9)
    return replace(msg, header=replace(msg.header, stamp=stamp))


def frame_of(msg):
    """The room frame a message belongs to (its stamp's place on the DT grid)."""
    s = msg.header.stamp.sec + 1e-9 * msg.header.stamp.nanosec
    return int(np.floor((s - T0) / DT + 1e-6))


def test_colliding_bag_times_and_stamps_going_back(tmp_path, room):
    """Depth and colour messages that share bag receive times (every message of frame 2k + 1
    received at frame 2k's time, as a coarse recording clock gives) but have their own
    stamps: every frame is read, its own (no false "message missing on the second read"). Then stamps that go back while the bag
    times still increase: those frames are skipped as bad_stamp naming the topic and times,
    and their colour images are never paired with another frame's depth."""
    clean = write_bag(tmp_path / "clean", room, decoys=False)

    def collide(topic, t, msg):
        i = frame_of(msg) if topic in (TOPICS["colour"], TOPICS["depth"]) else 0
        if i % 2:  # frame i - 1's bag time, as write_bag computed it
            lag = COLOUR_LAG if topic == TOPICS["colour"] else 0.0
            return [(int(round((T0 + (i - 1) * DT + lag) * 1e9)), msg)]
        return [(t, msg)]

    records = list(bag_source(rewrite_bag(clean, tmp_path / "collide", collide)))
    assert [type(r).__name__ for r in records] == ["RGBDFrame"] * FRAMES, records
    _, written = room
    for frame, (rgb, _, pose) in zip(records, written, strict=True):
        np.testing.assert_array_equal(frame.image, rgb)
        np.testing.assert_allclose(frame.pose, pose, atol=1e-9)

    def back(topic, t, msg):  # frames 3..5 stamped 0.3 s back: onto frames 0..2's stamps
        if topic in (TOPICS["colour"], TOPICS["depth"], TOPICS["info"]) and frame_of(msg) >= 3:
            return [(t, restamped(msg, -3 * DT))]
        return [(t, msg)]

    source = bag_source(rewrite_bag(clean, tmp_path / "back", back))
    records = list(source)
    kinds = [getattr(r, "kind", "frame") for r in records]
    assert sorted(kinds) == ["bad_stamp"] * 3 + ["frame"] * 3, records
    for r in records:
        if isinstance(r, RGBDFrame):  # frames 0..2: their own colour image and pose
            i = int(round((r.stamp - T0) / DT))
            np.testing.assert_array_equal(r.image, written[i][0])
        else:
            assert f"on {TOPICS['depth']} is not after" in r.reason and "bag time" in r.reason
    assert len(source.colour_stamp_faults) == 3


def test_every_missing_topic_and_the_tf_static_reason(tmp_path, room):
    """All wrong topics in one message with the bag's topics listed once; a bag without
    /tf_static gives no_pose frames whose reason says so."""
    from resireg.sources.rosbag import BagSource, BagTopics, MissingTopicError

    path = write_bag(tmp_path / "room", room, decoys=False)
    topics = BagTopics(colour="/a", depth="/b", camera_info="/c", tf="/d", tf_static="/e")
    with pytest.raises(MissingTopicError) as info:
        BagSource(path, topics)
    text = str(info.value)
    for key, topic in (("colour_topic", "/a"), ("depth_topic", "/b"), ("camera_info_topic", "/c"),
                       ("tf_topic", "/d")):  # fmt: skip
        assert f"{key}='{topic}' is not in the bag" in text, text
    assert text.count(f"{TOPICS['depth']} (sensor_msgs/msg/Image)") == 1
    no_static = rewrite_bag(path, tmp_path / "no_static",
                            lambda topic, t, msg: [] if topic == "/tf_static" else [(t, msg)])  # fmt: skip
    records = list(bag_source(no_static))
    assert {r.kind for r in records} == {"no_pose"}
    assert "no tf chain map -> camera_optical: /tf_static has no message" in records[0].reason


@pytest.fixture(scope="module")
def room12():
    return room_frames(12)


@pytest.mark.slow
def test_resireg_map_bad_stamps_sizes_depth_corrupt_tf(tmp_path, room12, tiny_export):
    """One resireg-map run on a 12-frame 32FC1 bag with, at once: frames 8..11 (depth, colour,
    camera info) restamped 0.8 s back with increasing bag times, frame 2's depth at half size
    under a full-size CameraInfo, 1e20 m in an 8 x 8 corner of every depth image, one /tf and
    one CameraInfo message of garbage. The map must equal the one computed here from the
    known frames 0, 1, 3..7 (their own colour, their corner without depth): voxel keys exact,
    bb features to 1e-6; the skips counted by kind with both sizes named; the corrupt messages
    counted by topic; viewer.save=map.rrd under the run folder, recorded absolute; the map's
    files with the umask's mode."""
    import os

    from helpers.run import run

    pytest.importorskip("rerun")
    r, written = room12
    clean = write_bag(tmp_path / "clean", room12, depth="32FC1")

    def damage(topic, t, msg):
        from dataclasses import replace

        if topic == "/tf" and abs(t * 1e-9 - (T0 + 5.5 * DT)) < 1e-3:
            return [(t, b"\x00\x01\x00\x00garbage")]
        if topic in (TOPICS["colour"], TOPICS["depth"], TOPICS["info"]):
            i = frame_of(msg)
            if topic == TOPICS["info"] and i == 7:
                return [(t, b"\x00\x01\x00\x00garbage")]
            if topic == TOPICS["depth"] and i < 12:
                d = np.frombuffer(bytes(msg.data), "<f4").reshape(msg.height, msg.width).copy()
                d[:8, :8] = 1e20
                if i == 2:
                    d = np.ascontiguousarray(d[::2, ::2])
                msg = replace(msg, height=d.shape[0], width=d.shape[1], step=d.shape[1] * 4,
                              data=d.astype("<f4").view(np.uint8).reshape(-1))  # fmt: skip
            if 8 <= i < 12:
                msg = restamped(msg, -8 * DT)
        return [(t, msg)]

    bag = rewrite_bag(clean, tmp_path / "faulty", damage)
    out = tmp_path / "run"
    proc = run("resireg-map", f"model_path={tiny_export}", "device=cpu", f"source.path={bag}",
               *CLI_TOPICS, "variant=bb", "window=4", f"voxel_size={VOXEL}",
               f"hydra.run.dir={out}", "viewer.save=map.rrd", threads=2)  # fmt: skip
    results = json.loads((out / "results.json").read_text())
    frames = results["frames"]
    assert frames["used"] == 7, proc.stdout
    assert frames["skipped"] == {"bad_stamp": 4, "size_mismatch": 1, "unpaired": 1}
    assert "depth image 64x48 but /cam/depth/info" in frames["reasons"]["size_mismatch"]
    assert "is for 128x96" in frames["reasons"]["size_mismatch"]
    assert f"header stamp {T0:.6f} on /cam/depth is not after" in frames["reasons"]["bad_stamp"]
    assert results["depth_out_of_range"] == {"pixels": 7 * 64, "frames": 7}
    assert results["corrupt_messages"]["by_topic"] == {"/tf": 1, TOPICS["info"]: 1}
    assert results["colour_stamp_faults"]["count"] == 8  # each frame's image and its decoy
    log = (out / "map.log").read_text()
    assert "1 corrupt message(s) on /tf" in log and "bad_stamp" in log
    # the reference: the kept frames' bb features at their patch points
    from resireg.models import ResiregVLM

    encoder = ResiregVLM.from_pretrained(tiny_export).eval()
    keep = [0, 1, 3, 4, 5, 6, 7]
    images = torch.stack([torch.from_numpy(written[i][0]).permute(2, 0, 1) for i in keep])
    depth = torch.stack([torch.from_numpy(written[i][1]) for i in keep]).clone()
    depth[:, :8, :8] = 0
    poses = torch.stack([torch.from_numpy(written[i][2]) for i in keep])
    with torch.no_grad():
        lang = encoder.encode(encoder.input_rule.normalize(images.float() / 255)).language
    dense = F.normalize(lang.float(), dim=1)
    ref = VoxelMap(VOXEL, dense.shape[1])
    pts, valid = patch_points(depth, torch.from_numpy(r.intrinsics).float(), poses,
                              tuple(dense.shape[-2:]))  # fmt: skip
    ref.add(pts[valid], dense.permute(0, 2, 3, 1)[valid])
    smap = SemanticMap.load(out / "map")
    assert torch.equal(smap.indices, ref.indices)
    np.testing.assert_allclose(smap.features()[1].numpy(), ref.features()[1].numpy(), atol=1e-6)
    assert results["map"]["rerun"] == str((out / "map.rrd").resolve())
    assert (out / "map.rrd").is_file()
    umask = os.umask(0)
    os.umask(umask)
    for f in (out / "map").iterdir():
        assert f.stat().st_mode & 0o777 == 0o666 & ~umask, f


@pytest.mark.slow
def test_resireg_map_resume_inside_a_window_and_another_model(tmp_path, room12, tiny_export):
    """source.limit=6 window=4, then resume=true without the limit: all 12 frames (the frames
    6 and 7 of the cut window too), equal to an uninterrupted map under bb (per-frame features,
    so the shifted windows do not matter). Resuming with another model's export, the same bag
    given by another path: refused, naming only what differs (encoder.path, weights)."""
    import shutil

    from helpers.run import run, run_side_by_side
    from helpers.tiny import TINY_BACKBONE, TINY_HEAD, TINY_TEXT
    from resireg.models import ResiregVLM

    bag = write_bag(tmp_path / "bag", room12, decoys=False)
    other = tmp_path / "other_export"
    torch.manual_seed(1)
    ResiregVLM.build(TINY_BACKBONE, TINY_HEAD, TINY_TEXT).save_pretrained(other)
    common = [f"model_path={tiny_export}", "device=cpu", *CLI_TOPICS, "variant=bb",
              "window=4", f"voxel_size={VOXEL}"]  # fmt: skip
    whole, cut = tmp_path / "whole", tmp_path / "cut"
    run_side_by_side(("resireg-map", *common, f"source.path={bag}", f"hydra.run.dir={whole}"),
                     ("resireg-map", *common, f"source.path={bag}", f"hydra.run.dir={cut}",
                      "source.limit=6"))  # fmt: skip
    run("resireg-map", *common, f"source.path={bag}", f"hydra.run.dir={cut}", "resume=true",
        threads=2)  # fmt: skip
    a, b = SemanticMap.load(whole / "map"), SemanticMap.load(cut / "map")
    assert a.frames == b.frames == 12
    assert torch.equal(a.indices, b.indices)
    np.testing.assert_allclose(a.features()[1].numpy(), b.features()[1].numpy(), atol=1e-6)
    results = json.loads((cut / "results.json").read_text())
    assert results["frames"]["skipped"] == {"in_map": 6} and results["frames"]["used"] == 6
    shutil.copytree(cut / "map", tmp_path / "kept")
    via = tmp_path / "bag" / ".." / "bag"
    refused = run("resireg-map", *common, f"model_path={other}", f"source.path={via}",
                  f"hydra.run.dir={cut}", "resume=true", check=False, threads=2)  # fmt: skip
    assert refused.returncode != 0
    line = next(x for x in refused.stderr.splitlines() if "ConfigError: resume=true" in x)
    # the shallowest key first (resireg.specs.tree.differences): the weights, then encoder.path
    assert "(2 differ): weights: " in line and "; encoder.path: " in line, line
    assert "source" not in line.split("differ")[1] and len(line) < 600, line
    # the refused run left the map as it was
    assert (tmp_path / "kept" / "map.json").read_text() == (cut / "map" / "map.json").read_text()


@pytest.mark.slow
def test_resireg_map_damaged_bags_and_a_non_finite_encoder(tmp_path, room12, tiny_export):
    """Damaged bags through resireg-map (side by side): a ROS 1 bag with 4 KiB overwritten in
    its middle maps the frames before the damage and counts the rest as damaged, naming
    source.path; a truncated ROS 2 sqlite3 bag and a truncated MCAP one fail in one line
    naming source.path and what is wrong, no traceback. An export whose weights make NaN
    features: every window skipped as non_finite, and the run's "no frame was mapped" says
    why per kind, in results.json and on stderr."""
    import os

    from helpers.run import run_side_by_side
    from helpers.tiny import TINY_BACKBONE, TINY_HEAD, TINY_TEXT
    from resireg.models import ResiregVLM

    ros1 = write_bag(tmp_path / "room.bag", room12, ros1=True)
    with open(ros1, "r+b") as f:
        f.seek(os.path.getsize(ros1) // 2)
        f.write(b"\xff" * 4096)
    truncated = {}
    for storage in ("sqlite3", "mcap"):
        bag = write_bag(tmp_path / storage, room12, storage=storage)
        (data,) = [p for p in bag.iterdir() if p.suffix in (".db3", ".mcap")]
        os.truncate(data, int(os.path.getsize(data) * 0.6))
        truncated[storage] = bag
    nan_export = tmp_path / "nan_export"
    torch.manual_seed(0)
    model = ResiregVLM.build(TINY_BACKBONE, TINY_HEAD, TINY_TEXT)
    with torch.no_grad():
        model.backbone.model.patch_embed.proj.bias.fill_(float("nan"))
    model.save_pretrained(nan_export)
    clean = write_bag(tmp_path / "clean", room12)
    common = ["device=cpu", *CLI_TOPICS, "variant=bb", "window=4", f"voxel_size={VOXEL}"]
    outs = [tmp_path / f"run{i}" for i in range(4)]
    procs = run_side_by_side(
        ("resireg-map", *common, f"model_path={tiny_export}", f"source.path={ros1}",
         f"hydra.run.dir={outs[0]}"),
        ("resireg-map", *common, f"model_path={tiny_export}",
         f"source.path={truncated['sqlite3']}", f"hydra.run.dir={outs[1]}"),
        ("resireg-map", *common, f"model_path={tiny_export}",
         f"source.path={truncated['mcap']}", f"hydra.run.dir={outs[2]}"),
        ("resireg-map", *common, f"model_path={nan_export}", f"source.path={clean}",
         f"hydra.run.dir={outs[3]}"),
        check=(True, False, False, False),
    )  # fmt: skip
    results = json.loads((outs[0] / "results.json").read_text())
    frames = results["frames"]
    assert results["status"] == "completed" and frames["used"] >= 4, frames
    assert frames["skipped"].get("damaged", 0) >= 1, frames
    assert frames["read"] == 13  # 12 frames and the far depth image: every one counted
    assert f"source.path={str(ros1)!r} is damaged after" in results["damage"]
    for proc, storage in zip(procs[1:3], ("sqlite3", "mcap"), strict=True):
        assert proc.returncode != 0
        error = [x for x in proc.stderr.splitlines() if "ConfigError" in x]
        assert len(error) == 1, proc.stderr
        assert f"source.path={str(truncated[storage])!r}: the bag cannot be opened" in error[0]
        assert "Traceback" not in proc.stderr
    nan = procs[3]
    assert nan.returncode != 0 and "no frame was mapped" in nan.stderr
    assert "why, per kind: non_finite: /cam/depth@" in nan.stderr, nan.stderr[-2000:]
    results = json.loads((outs[3] / "results.json").read_text())
    assert results["status"] == "failed"
    assert results["frames"]["skipped"] == {"non_finite": 12, "unpaired": 1}
    assert "encoder output holds" in results["frames"]["reasons"]["non_finite"]


def test_full_disk_during_a_map_save(tmp_path, room, tiny_export, monkeypatch):
    """resireg-map in this process (map.yaml composed, run_map) with the second tensor-file
    write failing as a full disk does (ENOSPC, a partial file): the error and results.json's
    failed status name the file; no temporary or orphan file is left; the first save loads."""
    import errno

    from hydra import compose, initialize_config_dir

    from resireg.mapping import map_file
    from resireg_train.cli.map import run_map
    from resireg_train.config.paths import CONFIG_DIR

    bag = write_bag(tmp_path / "room", room, decoys=False)
    real = map_file.write_tensors  # the map's tensor-file writer (resireg.mapping.tensor_file)
    calls = []

    def full_disk(filename, tensors):
        calls.append(filename)
        if len(calls) < 2:
            return real(filename, tensors)
        with open(filename, "wb") as f:
            f.write(b"\0" * 100)
        raise OSError(errno.ENOSPC, "No space left on device")

    monkeypatch.setattr(map_file, "write_tensors", full_disk)
    out = tmp_path / "run"
    with initialize_config_dir(str(CONFIG_DIR), version_base="1.3"):
        cfg = compose("map", overrides=[f"model_path={tiny_export}", "device=cpu",
                                        f"source.path={bag}", *CLI_TOPICS, "variant=bb",
                                        "window=4", "save_every=1", f"voxel_size={VOXEL}",
                                        f"paths.output_dir={out}"])  # fmt: skip
    with pytest.raises(OSError) as info:
        run_map(cfg)
    assert info.value.errno == errno.ENOSPC and "map-" in str(info.value)
    assert str(out / "map") in str(info.value)
    results = json.loads((out / "results.json").read_text())
    assert results["status"] == "failed" and str(out / "map") in results["error"]
    left = sorted(p.name for p in (out / "map").iterdir())
    assert len(left) == 2 and "map.json" in left and not any(n.endswith(".tmp") for n in left)
    assert SemanticMap.load(out / "map").frames == 4


def test_a_corrupt_depth_message_does_not_make_later_stamps_bad(tmp_path, room):
    """A bag recorded on another clock than its header stamps (bag times 1000 s later, as a
    robot on simulated time gives) with one depth message of garbage: that frame is
    undecodable, and every other frame is read (the garbage message has no stamp to compare)."""
    clean = write_bag(tmp_path / "clean", room, decoys=False)

    def later(topic, t, msg):
        if topic == TOPICS["depth"] and frame_of(msg) == 2:
            return [(t + 10**12, b"\x00\x01\x00\x00garbage")]
        return [(t + 10**12, msg)]

    records = list(bag_source(rewrite_bag(clean, tmp_path / "later", later)))
    kinds = [getattr(r, "kind", "frame") for r in records]
    assert sorted(kinds) == ["frame"] * (FRAMES - 1) + ["undecodable"], records
