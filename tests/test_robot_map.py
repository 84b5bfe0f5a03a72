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

from _tiny import TINY_BACKBONE, TINY_HEAD, TINY_TEXT
from resireg.mapping import SemanticMap, VoxelMap, patch_points
from resireg.models import ResiregVLM
from resireg_train.data.rgbd import FrameCounts, RGBDFrame, SkippedFrame, pair_nearest, windows
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
    from resireg_train.data.rosbag import BagSource, BagTopics

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
    assert "no tf chain map -> 'no_such_frame'" in records[0].reason


def test_missing_topic_lists_the_bag_topics(tmp_path, room):
    from resireg_train.data.rosbag import BagSource, BagTopics, MissingTopicError

    path = write_bag(tmp_path / "room", room, decoys=False)
    topics = BagTopics(colour="/camera/rgb", depth=TOPICS["depth"], camera_info=TOPICS["info"])
    with pytest.raises(MissingTopicError) as info:
        BagSource(path, topics)
    text = str(info.value)
    assert "source.colour_topic='/camera/rgb' is not in the bag" in text
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
    from resireg_train.data.tum import CAMERAS, TumSource

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
    with pytest.raises(ValueError, match="source.camera='fr9'"):
        TumSource(folder, camera="fr9")


@pytest.mark.slow
def test_resireg_map_cli_bag_rerun_and_resume(tmp_path, room, tiny_export):
    """resireg-map on a bag: results.json counts, the saved map and PLY, the Rerun recording read
    back with rerun.chunk.RrdReader (entities, the map's point count); a run cut by
    source.limit and resumed equals one uninterrupted run."""
    from _run import run, run_side_by_side

    pytest.importorskip("rerun")
    from rerun.chunk import RrdReader

    bag = write_bag(tmp_path / "room", room)
    common = [f"model_path={tiny_export}", "device=cpu", "source.kind=rosbag", f"source.path={bag}",
              f"source.colour_topic={TOPICS['colour']}", f"source.depth_topic={TOPICS['depth']}",
              f"source.camera_info_topic={TOPICS['info']}", "configuration=full@n_prototypes:4",
              "window=2", f"voxel_size={VOXEL}", "save_every=1"]  # fmt: skip
    whole, cut = tmp_path / "whole", tmp_path / "cut"
    # The whole run, the cut one and the refused one are independent: started side by side,
    # one torch thread each (the resume below too, so whole and cut + resume compute alike).
    proc, _, refused = run_side_by_side(
        ("resireg-map", *common, f"hydra.run.dir={whole}", f"rerun.save={whole}/map.rrd",
         "rerun.query=a chair", "ply.colour_by=rgb"),
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
    from resireg_train.data.scannet import scannet_rgbd
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
    with pytest.raises(FileNotFoundError, match="source.path=.*no color/ folder"):
        next(scannet_rgbd(tmp_path / "nothing"))
