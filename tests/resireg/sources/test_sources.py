"""The map's frame sources (resireg.sources) and their table (resireg.specs.sources): every
entry against its conf file and its rules, the Nerfstudio reader on a folder written here from
the ray-cast room with known poses (and resireg-map on it against the bag of the same frames),
the ROS message decoders on rosbags' and rclpy's message forms, the config-path boundary of
resireg-map, and that the robot side imports no training stack."""

import array
import json
import subprocess
import sys
from types import SimpleNamespace

import numpy as np
import pytest
import torch
from PIL import Image

from resireg.errors import DataError, ResiregError
from resireg.sources.frames import (
    FrameCounts,
    FrameSource,
    MessageSource,
    RGBDFrame,
    windows,
)
from resireg.specs.sources import COMMON_RULES, SOURCE_SPECS, WINDOW_KEYS, source_errors
from resireg_train.data.room_bag import TOPICS, room_frames, write_bag

VOXEL = 0.2
FRAMES = 6
OPENGL = np.diag([1.0, -1.0, -1.0, 1.0])  # OpenCV camera axes <-> OpenGL's (its own inverse)


@pytest.fixture(scope="module")
def room():
    return room_frames(FRAMES)


def compose_map(*overrides):
    from hydra import compose, initialize_config_dir
    from omegaconf import OmegaConf

    from resireg_train.config.paths import CONFIG_DIR

    with initialize_config_dir(str(CONFIG_DIR), version_base="1.3"):
        cfg = compose("map", overrides=list(overrides))
    return OmegaConf.to_container(cfg.source, resolve=True)


# ---------------------------------------------------------------------------- the table
def a_block(kind):
    """The composed block of ``kind`` with a path where the kind reads a recording (a live
    source's file has ``path: null``)."""
    takes_path = "path" in SOURCE_SPECS.get(kind).common
    return compose_map(f"source={kind}", *(["source.path=somewhere"] if takes_path else []))


@pytest.mark.parametrize("kind", SOURCE_SPECS.names())
def test_every_source_entry_loads_and_its_conf_file_holds_exactly_its_keys(kind):
    """Each entry: its reader loads, its conf/source/<kind>.yaml is found by scanning and
    composes (with _common.yaml) to exactly the kind's keys, whose defaults pass its rules;
    the keys its reader takes are keywords of the reader. A kind that reads no recording
    (ros2) has path: null, and refuses a path."""
    import inspect

    spec = SOURCE_SPECS.get(kind)
    target = spec.load()
    assert callable(target) and spec.summary and "\n" not in spec.summary
    assert spec.configs == (kind,)
    block = a_block(kind)
    assert block["kind"] == kind
    assert set(block) == {"kind", *COMMON_RULES, *spec.keys}
    assert source_errors(block) == []
    params = inspect.signature(target).parameters
    assert set(spec.arguments(block)) <= set(params), (kind, list(params))
    assert not set(spec.common) & set(WINDOW_KEYS)
    assert not set(spec.keys) & set(COMMON_RULES)
    if "path" not in spec.common:
        assert block["path"] is None and "path" not in spec.arguments(block)
        (error,) = source_errors({**block, "path": "run.bag"})
        assert error.startswith("path='run.bag': expected null") and "source=rosbag" in error


@pytest.mark.parametrize("kind", SOURCE_SPECS.names())
def test_every_rule_refuses_a_bad_value_naming_its_key(kind):
    block = a_block(kind)
    for name in SOURCE_SPECS.get(kind).rules:
        errors = source_errors({**block, name: {"not": "a value"}})
        assert len(errors) == 1 and errors[0].startswith(f"{name}={{'not': "), errors
        assert ": expected " in errors[0]
    for name, bad in (("tolerance", -1), ("frame_skip", 1.5), ("limit", 0), ("max_depth", 0),
                      ("path", "???")):  # fmt: skip
        (error,) = source_errors({**block, name: bad})
        assert error.startswith(f"{name}={bad!r}: expected"), error


def test_the_kind_comes_from_the_config_group():
    """source.kind=tum on the rosbag block: one error saying to select source=tum; an unknown
    kind names the closest; the default map.yaml is the rosbag block; a missing path names it.
    The library names the block's keys (kind=, path=); resireg-map's boundary (block_errors)
    writes them as config paths (source.kind=, source.path=), and the block's own problems
    under source:."""
    from resireg_train.config.errors import block_errors

    def at_config(block):
        return block_errors(source_errors(block), "source", block)

    assert source_errors(compose_map("source.kind=ros2", "source.path=x")) == [
        "kind='ros2' is set on the block of 'rosbag': select the source with source=ros2 "
        "(not kind=ros2)"
    ]
    assert source_errors({**compose_map("source=tum", "source.path=x"), "colour": 1})[0].startswith(
        "unknown key(s) ['colour'] for kind 'tum'"
    )
    (error,) = at_config(compose_map("source.kind=tum", "source.path=x"))
    assert "source.kind='tum'" in error and "select the source with source=tum" in error
    assert "'rosbag'" in error and "colour_topic" in error
    (error,) = at_config(compose_map("source=scannet", "source.kind=nerfstudio", "source.path=x"))
    assert "source=nerfstudio" in error
    (error,) = at_config(compose_map("source.kind=ros2", "source.path=x"))  # a subset
    assert error == ("source.kind='ros2' is set on the block of 'rosbag': select the source "
                     "with source=ros2 (not source.kind=ros2)")  # fmt: skip
    (error,) = at_config({**compose_map("source.path=x"), "kind": "rosbg"})
    assert error.startswith("source.kind='rosbg': expected one of [") and "'rosbag'" in error
    assert compose_map()["kind"] == "rosbag"
    assert at_config(compose_map()) == ["source.path='???': expected a path: the recording to map"]
    (error,) = at_config({**compose_map("source=tum", "source.path=x"), "colour": 1})
    assert error.startswith("source: unknown key(s) ['colour'] for kind 'tum'"), error


def test_the_map_cli_names_the_config_path(tmp_path, room):
    """resireg-map's boundary: the library names its arguments, the CLI's ConfigError names
    source.<argument>= (each wrong topic of a bag, the path), one line, before any model."""
    from resireg.errors import ConfigError
    from resireg_train.jobs.map import build_source

    bag = write_bag(tmp_path / "room", room, decoys=False)
    block = {**compose_map("source.path=x"), "path": str(bag), "colour_topic": "/a",
             "depth_topic": "/b", "camera_info_topic": TOPICS["info"]}  # fmt: skip
    with pytest.raises(ConfigError) as info:
        build_source(block)
    text = str(info.value)
    assert "source.colour_topic='/a' is not in the bag" in text
    assert "; source.depth_topic='/b' is not in the bag" in text
    assert isinstance(info.value.__cause__, DataError)  # the library's MissingTopicError
    assert isinstance(info.value, ResiregError)
    with pytest.raises(ConfigError, match=r"^source\.path='/no/such/bag': no such bag$"):
        build_source({**block, "path": "/no/such/bag"})
    with pytest.raises(ConfigError, match=r"^source\.path=.*no such folder \(a Nerfstudio"):
        build_source({**compose_map("source=nerfstudio", "source.path=x"), "path": "/no/such"})
    source = build_source(
        {**block, "colour_topic": TOPICS["colour"], "depth_topic": TOPICS["depth"]}
    )
    assert isinstance(source, MessageSource) and len(list(source)) == FRAMES


# ---------------------------------------------------------------------------- Nerfstudio
def write_nerfstudio(folder, room, per_frame=False, depth_size=None, **top):
    """The room as a Nerfstudio folder: images/*.png, depth/*.png (uint16 mm), transforms.json
    with the poses in OpenGL camera axes, listed out of order (the reader sorts by file)."""
    r, frames = room
    (folder / "images").mkdir(parents=True)
    (folder / "depth").mkdir()
    fx, fy, cx, cy = r.intrinsics[0, 0], r.intrinsics[1, 1], r.intrinsics[0, 2], r.intrinsics[1, 2]
    h, w = frames[0][0].shape[:2]
    camera = {"fl_x": fx, "fl_y": fy, "cx": cx, "cy": cy, "w": w, "h": h}
    entries = []
    for i, (rgb, d, pose) in enumerate(frames):
        Image.fromarray(rgb).save(folder / "images" / f"frame_{i:05d}.png")
        mm = np.clip(np.rint(d * 1000), 0, 65535).astype(np.uint16)
        if depth_size is not None:
            mm = mm[:: h // depth_size[0], :: w // depth_size[1]]
        Image.fromarray(mm).save(folder / "depth" / f"frame_{i:05d}.png")
        entry = {"file_path": f"images/frame_{i:05d}.png",
                 "depth_file_path": f"depth/frame_{i:05d}.png",
                 "transform_matrix": (pose @ OPENGL).tolist()}  # fmt: skip
        entries.append({**entry, **camera} if per_frame else entry)
    meta = {"camera_model": "OPENCV", **({} if per_frame else camera),
            "depth_unit_scale_factor": 0.001, **top, "frames": entries[::-1]}  # fmt: skip
    (folder / "transforms.json").write_text(json.dumps(meta))
    return folder


def expected_depth(d):
    return np.clip(np.rint(d * 1000), 0, 65535).astype(np.float32) * np.float32(0.001)


@pytest.mark.parametrize("per_frame", [False, True])
def test_nerfstudio_frames_are_the_written_ones(tmp_path, room, per_frame):
    """Each frame: its image, its depth in metres, K, and the OpenCV camera-to-world pose the
    OpenGL transform_matrix stands for (to 1e-6), in file order; intrinsics global or per frame."""
    from resireg.sources.nerfstudio import NerfstudioSource

    r, written = room
    source = NerfstudioSource(write_nerfstudio(tmp_path / "ns", room, per_frame=per_frame))
    assert isinstance(source, FrameSource) and not isinstance(source, MessageSource)
    records = list(source)
    assert len(records) == FRAMES and all(isinstance(x, RGBDFrame) for x in records)
    for i, (frame, (rgb, d, pose)) in enumerate(zip(records, written, strict=True)):
        np.testing.assert_array_equal(frame.image, rgb)
        np.testing.assert_array_equal(frame.depth, expected_depth(d))
        assert frame.depth.dtype == np.float32
        np.testing.assert_allclose(frame.intrinsics, r.intrinsics, atol=1e-9)
        np.testing.assert_allclose(frame.pose, pose, atol=1e-6)
        assert frame.stamp == float(i) and frame.name.endswith(f"frame_{i:05d}.png")
    # the path may name transforms.json itself; the argument overrides the file's depth unit
    again = NerfstudioSource(tmp_path / "ns" / "transforms.json", depth_unit_scale_factor=0.002)
    np.testing.assert_allclose(next(iter(again)).depth, 2 * records[0].depth, rtol=1e-6)


def test_nerfstudio_depth_of_another_size_gets_its_own_intrinsics(tmp_path, room):
    """A depth image at half the colour image's size: K scaled to it, pixel centres kept."""
    from resireg.sources.nerfstudio import NerfstudioSource

    r, written = room
    h, w = written[0][0].shape[:2]
    frame = next(iter(NerfstudioSource(write_nerfstudio(tmp_path / "ns", room,
                                                        depth_size=(h // 2, w // 2)))))  # fmt: skip
    assert frame.depth.shape == (h // 2, w // 2) and frame.image.shape == (h, w, 3)
    k = r.intrinsics
    np.testing.assert_allclose(frame.intrinsics[0], [k[0, 0] / 2, 0, (k[0, 2] + 0.5) / 2 - 0.5])
    np.testing.assert_allclose(frame.intrinsics[1], [0, k[1, 1] / 2, (k[1, 2] + 0.5) / 2 - 0.5])


def test_nerfstudio_bad_files_are_skipped_and_counted(tmp_path, room):
    """A missing colour file, a truncated depth PNG, a frame without depth, a malformed
    transform_matrix and an image of another size are each skipped, named and counted; the
    other frames are read. A folder without transforms.json, or a frame without intrinsics,
    is an error naming path."""
    from resireg.sources.nerfstudio import NerfstudioSource

    folder = write_nerfstudio(tmp_path / "ns", room)
    (folder / "images" / "frame_00001.png").unlink()
    depth = folder / "depth" / "frame_00002.png"
    depth.write_bytes(depth.read_bytes()[:60])
    meta = json.loads((folder / "transforms.json").read_text())
    by_file = {f["file_path"]: f for f in meta["frames"]}
    del by_file["images/frame_00003.png"]["depth_file_path"]
    by_file["images/frame_00004.png"]["transform_matrix"] = [[1, 2], [3, 4]]
    Image.fromarray(room[1][5][0][:50]).save(folder / "images" / "frame_00005.png")
    (folder / "transforms.json").write_text(json.dumps(meta))
    counts = FrameCounts()
    batches = list(windows(NerfstudioSource(folder), 4, counts))
    assert counts.read == FRAMES and sum(len(b["name"]) for b in batches) == 1
    assert dict(counts.skipped) == {"undecodable": 2, "unpaired": 1, "no_pose": 1,
                                    "size_mismatch": 1}  # fmt: skip
    reasons = {s.name.split("/")[-1]: (s.kind, s.reason) for s in counts.examples}
    assert reasons["frame_00001.png"][1] == "missing colour file"
    assert reasons["frame_00002.png"][1].startswith("unreadable depth")
    assert "colour image 128x50 but its camera is for 128x96" in reasons["frame_00005.png"][1]
    with pytest.raises(FileNotFoundError, match=r"^path='.*': no transforms.json in it"):
        NerfstudioSource(tmp_path)
    del meta["fl_x"]
    (folder / "transforms.json").write_text(json.dumps(meta))
    with pytest.raises(DataError, match=r"^path=.*frames\[0\] .* has no \['fl_x'\]"):
        NerfstudioSource(folder)
    (folder / "transforms.json").write_text("{not json")
    with pytest.raises(DataError, match="not readable JSON"):
        NerfstudioSource(folder)


def bag_map(encoder, bag):
    from resireg.mapping import SemanticMap
    from resireg.sources.rosbag import BagSource, BagTopics

    topics = BagTopics(colour=TOPICS["colour"], depth=TOPICS["depth"], camera_info=TOPICS["info"])
    smap = SemanticMap(encoder, "bb", VOXEL)
    for batch in windows(BagSource(bag, topics), 4, FrameCounts()):
        smap.add(batch["image"], batch["depth"], batch["intrinsics"], batch["pose"])
    return smap


def test_nerfstudio_maps_as_the_bag_of_the_same_frames(tmp_path, room):
    """The same room as a bag and as a Nerfstudio folder: the same map (voxel keys exact,
    features to 1e-6)."""
    from helpers.tiny import TINY_BACKBONE, TINY_HEAD, TINY_TEXT
    from resireg.mapping import SemanticMap
    from resireg.models import ResiregVLM
    from resireg.sources.nerfstudio import NerfstudioSource

    torch.manual_seed(0)
    encoder = ResiregVLM.build(TINY_BACKBONE, TINY_HEAD, TINY_TEXT).eval()
    ref = bag_map(encoder, write_bag(tmp_path / "bag", room, decoys=False))
    smap = SemanticMap(encoder, "bb", VOXEL)
    for batch in windows(NerfstudioSource(write_nerfstudio(tmp_path / "ns", room)), 4,
                         FrameCounts()):  # fmt: skip
        smap.add(batch["image"], batch["depth"], batch["intrinsics"], batch["pose"])
    assert len(ref) > 20 and torch.equal(smap.indices, ref.indices)
    np.testing.assert_allclose(smap.features()[1].numpy(), ref.features()[1].numpy(), atol=1e-6)


@pytest.mark.slow
def test_resireg_map_source_nerfstudio(tmp_path, room, tiny_export):
    """resireg-map source=nerfstudio: the map of the bag of the same frames (voxel keys exact,
    features to 1e-6); results.json records the frames."""
    from helpers.run import run
    from resireg.mapping import SemanticMap
    from resireg.models import ResiregVLM

    folder = write_nerfstudio(tmp_path / "ns", room)
    out = tmp_path / "run"
    run("resireg-map", f"model_path={tiny_export}", "device=cpu", "source=nerfstudio",
        f"source.path={folder}", "variant=bb", "window=4", f"voxel_size={VOXEL}",
        f"hydra.run.dir={out}", threads=2)  # fmt: skip
    results = json.loads((out / "results.json").read_text())
    assert (
        results["frames"]["used"] == FRAMES and results["params"]["source"]["kind"] == "nerfstudio"
    )
    encoder = ResiregVLM.from_pretrained(tiny_export).eval()
    ref = bag_map(encoder, write_bag(tmp_path / "bag", room, decoys=False))
    smap = SemanticMap.load(out / "map")
    assert torch.equal(smap.indices, ref.indices)
    np.testing.assert_allclose(smap.features()[1].numpy(), ref.features()[1].numpy(), atol=1e-6)


# ---------------------------------------------------------------------------- messages
def _rclpy_forms(msg, data):
    """The message as rclpy gives it (``uint8[]`` an array.array('B')), and as bytes / a list."""
    fields = {k: getattr(msg, k) for k in msg.__dataclass_fields__}
    raw = np.asarray(data, dtype=np.uint8).tobytes()
    return [SimpleNamespace(**{**fields, "data": array.array("B", raw)}),
            SimpleNamespace(**{**fields, "data": raw}),
            SimpleNamespace(**{**fields, "data": list(raw)})]  # fmt: skip


def test_message_decoders_take_rosbags_and_rclpy_messages():
    """Every decoder gives the same arrays for a rosbags message (numpy data) and the rclpy
    forms of it: colour rgb8 / bgr8 / mono8 (with row padding), PNG CompressedImage, depth
    16UC1 / 32FC1 (big-endian too) and compressedDepth, CameraInfo, stamps, transforms."""
    import io

    from rosbags.typesys import Stores, get_typestore

    from resireg.sources import messages as m

    ty = get_typestore(Stores.ROS2_HUMBLE).types
    header = ty["std_msgs/msg/Header"](stamp=ty["builtin_interfaces/msg/Time"](sec=12,
                                       nanosec=500_000_000), frame_id="cam")  # fmt: skip
    rng = np.random.default_rng(0)
    rgb = rng.integers(0, 255, (5, 7, 3), dtype=np.uint8)

    def image(encoding, pixels, step, big=0):
        rows = pixels.reshape(pixels.shape[0], -1).view(np.uint8)
        padded = np.zeros((rows.shape[0], step), np.uint8)
        padded[:, : rows.shape[1]] = rows
        return ty["sensor_msgs/msg/Image"](header=header, height=pixels.shape[0],
                                           width=pixels.shape[1], encoding=encoding,
                                           is_bigendian=big, step=step, data=padded.reshape(-1))  # fmt: skip

    def forms(msg):
        return [msg, *_rclpy_forms(msg, msg.data)]

    grey = rgb[..., 0]
    for msg, want in ((image("rgb8", rgb, 24), rgb), (image("bgr8", rgb[..., ::-1].copy(), 21), rgb),
                      (image("mono8", grey, 8), np.repeat(grey[..., None], 3, axis=2))):  # fmt: skip
        for form in forms(msg):
            got = m.decode_colour(form)
            np.testing.assert_array_equal(got, want)
            assert got.flags.writeable and got.flags.c_contiguous
    buf = io.BytesIO()
    Image.fromarray(rgb).save(buf, format="PNG")
    png = ty["sensor_msgs/msg/CompressedImage"](header=header, format="png",
                                                data=np.frombuffer(buf.getvalue(), np.uint8))  # fmt: skip
    for form in forms(png):
        np.testing.assert_array_equal(m.decode_colour(form), rgb)
    mm = rng.integers(0, 5000, (5, 7)).astype(np.uint16)
    metres = rng.random((5, 7)).astype(np.float32) * 3
    metres[0, 0] = np.nan
    for msg, want in ((image("16UC1", mm.astype("<u2"), 16), mm * np.float32(0.001)),
                      (image("16UC1", mm.astype(">u2"), 14, big=1), mm * np.float32(0.001)),
                      (image("32FC1", metres.astype("<f4"), 28), np.nan_to_num(metres))):  # fmt: skip
        for form in forms(msg):
            np.testing.assert_array_equal(m.decode_depth(form), want)
    buf = io.BytesIO()
    Image.fromarray(mm).save(buf, format="PNG")
    packed = ty["sensor_msgs/msg/CompressedImage"](
        header=header, format="16UC1; compressedDepth png",
        data=np.frombuffer(b"\0" * 12 + buf.getvalue(), np.uint8))  # fmt: skip
    for form in forms(packed):
        np.testing.assert_array_equal(m.decode_depth(form), mm * np.float32(0.001))
    with pytest.raises(ValueError, match="colour encoding 'yuv422'"):
        m.decode_colour(SimpleNamespace(encoding="yuv422", height=1, width=1, step=2, data=b"ab"))
    with pytest.raises(ValueError, match="not decodable"):
        m.decode_colour(SimpleNamespace(format="png", data=array.array("B", b"garbage")))
    k = np.array([80.0, 0, 63.5, 0, 80, 47.5, 0, 0, 1])
    for info in (SimpleNamespace(k=k, height=96, width=128),  # rosbags, and rclpy's double[9]
                 SimpleNamespace(k=array.array("d", k), height=96, width=128),
                 SimpleNamespace(K=list(k), height=96, width=128)):  # ROS 1 # fmt: skip
        np.testing.assert_array_equal(m.camera_intrinsics(info), k.reshape(3, 3))
        assert m.camera_size(info) == (96, 128)
    assert m.stamp_seconds(header) == 12.5
    assert (
        m.stamp_seconds(SimpleNamespace(stamp=SimpleNamespace(secs=3, nsecs=250_000_000))) == 3.25
    )
    vec = SimpleNamespace(x=1.0, y=2.0, z=3.0)
    quat = SimpleNamespace(x=0.0, y=0.0, z=np.sin(np.pi / 4), w=np.cos(np.pi / 4))
    t = m.transform_matrix(SimpleNamespace(translation=vec, rotation=quat))
    np.testing.assert_allclose(t[:3, :3], [[0, -1, 0], [1, 0, 0], [0, 0, 1]], atol=1e-12)
    np.testing.assert_array_equal(t[:3, 3], [1, 2, 3])
    np.testing.assert_array_equal(
        m.pose_msg_matrix(SimpleNamespace(position=vec, orientation=quat)), t
    )


def test_the_robot_side_imports_no_training_stack():
    """resireg.sources (every reader) and the source table load without Lightning, Hydra,
    datasets or OmegaConf; the table loads without torch."""
    code = (
        "import sys\n"
        "import resireg.specs.sources\n"
        "assert 'torch' not in sys.modules, 'the table imported torch'\n"
        "import resireg.sources, resireg.sources.frames, resireg.sources.pairing\n"
        "import resireg.sources.messages, resireg.sources.rosbag, resireg.sources.tum\n"
        "import resireg.sources.scannet, resireg.sources.nerfstudio\n"
        "bad = [m for m in ('lightning', 'hydra', 'datasets', 'omegaconf', 'resireg_train')\n"
        "       if m in sys.modules or any(k.startswith(m + '.') for k in sys.modules)]\n"
        "assert not bad, bad\n"
    )
    proc = subprocess.run([sys.executable, "-c", code], capture_output=True, text=True, timeout=120)
    assert proc.returncode == 0, proc.stderr


@pytest.mark.parametrize(("limit", "start", "sizes"), [(5, 0, [2, 2, 1]), (4, 0, [2, 2]),
                                                       (5, 2, [2, 1]), (2, 2, [])])  # fmt: skip
def test_windows_stop_at_the_limit_without_asking_for_another_frame(limit, start, sizes):
    """A stream that fails when asked for more than ``limit`` frames (as a live topic would
    block): windows(limit=...) ends after the limit-th kept frame, its last window emitted,
    the frames counted read exactly as many as were taken, in_map ones among them."""
    rng = np.random.default_rng(0)

    def stream():
        for i in range(limit):
            yield RGBDFrame(rng.integers(0, 255, (8, 8, 3), dtype=np.uint8),
                            np.ones((8, 8), np.float32), np.eye(3), np.eye(4), float(i), str(i))  # fmt: skip
        raise AssertionError("asked for a frame past the limit")

    counts = FrameCounts()
    batches = list(windows(stream(), 2, counts, limit=limit, start=start))
    assert [len(b["name"]) for b in batches] == sizes
    assert [n for b in batches for n in b["name"]] == [str(i) for i in range(start, limit)]
    assert counts.read == limit and counts.skipped["in_map"] == start
