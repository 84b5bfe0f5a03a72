"""Replica (NICE-SLAM + HOV-SG ground truth; Semantic-NeRF) and TartanAir v2 as 3D benchmarks:
tiny scenes written in each download's layout (tests/helpers/posed3d_fixtures.py) read back to the
known geometry, ground-truth voxels against a numpy recomputation from the files, scores of
test encoders against values computed from that reference, and every bad input named.

One idea: the two posed 3D benchmarks' readers against the same fixture scenes
(``helpers/posed3d_fixtures.py``) and the one numpy reference of their ground truth."""

import shutil
from pathlib import Path

import numpy as np
import pytest
import torch
import torch.nn.functional as F
from PIL import Image

from helpers.paths import TESTS
from helpers.posed3d_fixtures import (
    COLOURS,
    NICE_SCALE,
    REPLICA_CLASSES,
    REPLICA_IGNORED,
    REPLICA_SCORED,
    TARTAN_CLASSES,
    TARTAN_NAME_MAP,
    TARTAN_ROW_OF_RAW,
    nice_k,
    render,
    semnerf_k,
    write_hovsg_gt,
    write_nice_replica,
    write_semnerf_replica,
    write_tartanair,
)
from resireg.method.variants import build_variants
from resireg.models.interface import DenseEncoder, DenseOutput, InputRule
from resireg_train.data.replica import NiceReplicaFrames, SemanticNerfReplicaFrames
from resireg_train.data.specs import dataset_conf
from resireg_train.data.tartanair import TartanAirFrames
from resireg_train.evaluation.mapping.engine import MappingEngine, external_labels

SIZE = (24, 32)
COMMON = {"frame_skip": 0, "image_size": SIZE, "short_side": None, "resize": "torch",
          "intrinsics": "multiply", "patch_size": 1}  # fmt: skip


# ------------------------------------------------------------------ fixtures (session-wide)
@pytest.fixture(scope="session")
def nice(tmp_path_factory):
    root = tmp_path_factory.mktemp("replica")
    scene = render(nice_k(SIZE), SIZE)
    write_nice_replica(root / "nice", scene)
    write_hovsg_gt(root / "gt" / "office0" / "external_semseg_gt.pt", scene)
    return root, scene


@pytest.fixture(scope="session")
def ninety(tmp_path_factory):
    """The Semantic-NeRF and TartanAir scenes (both 90-degree cameras: one rendering)."""
    root = tmp_path_factory.mktemp("ninety")
    scene = render(semnerf_k(SIZE), SIZE)
    write_semnerf_replica(root / "semnerf", scene)
    write_tartanair(root / "tartan", scene)
    return root, scene


def _nice(root, **kw):
    args = {**COMMON, **kw}
    return NiceReplicaFrames(root / "nice", ["office0"], None, root / "gt",
                             list(REPLICA_IGNORED), **args)  # fmt: skip


def _semnerf(root, **kw):
    return SemanticNerfReplicaFrames(root / "semnerf", ["office_0/Sequence_1"],
                                     list(REPLICA_IGNORED), **{**COMMON, **kw})  # fmt: skip


def _tartan(root, **kw):
    return TartanAirFrames(root / "tartan", ["Factory"], "Data_ground", "P0000",
                           "seg_label_clean.json", 100.0, **{**COMMON, **kw})  # fmt: skip


# ------------------------------------------------------------------ independent references
def _surface_distance(p, lo, hi):
    lo, hi = np.asarray(lo), np.asarray(hi)
    outside = np.linalg.norm(np.maximum(np.maximum(lo - p, p - hi), 0), axis=1)
    inside = np.minimum(p - lo, hi - p).min(axis=1)
    return np.where(outside > 0, outside, np.maximum(inside, 0))


def _assert_on_boxes(frames, scene, tol=2e-3):
    """Every pixel with depth, unprojected with the reader's depth, K and pose, lies on the
    surface of the box the renderer hit there: the depth encoding, the camera and the pose
    convention (NED for TartanAir) are read right."""
    boxes: dict[int, list] = {}
    for b in scene.room.boxes:  # the four walls share an id
        boxes.setdefault(b.raw_id, []).append(b)
    checked = 0
    for i in range(len(frames)):
        item = frames[i]
        n = item["frame"]
        depth = item["depth"].double().numpy()
        k_inv = np.linalg.inv(item["intrinsics"].double().numpy())
        pose = item["pose"].numpy()
        v, u = np.nonzero(depth > 0)
        cam = (np.stack([u, v, np.ones_like(u)], 1) @ k_inv.T) * depth[v, u][:, None]
        world = cam @ pose[:3, :3].T + pose[:3, 3]
        raw = scene.raw[n][v, u]
        for rid in np.unique(raw):
            sel = raw == rid
            near = np.min([_surface_distance(world[sel], b.lo, b.hi) for b in boxes[int(rid)]], 0)
            assert near.max() < tol, (i, rid)
        checked += len(v)
    assert checked > 0.9 * len(frames) * SIZE[0] * SIZE[1]


def _vote(keys, columns, width):
    """{voxel index tuple: votes per column} of integer voxel indices ``[N, 3]``."""
    unique, inverse = np.unique(keys, axis=0, return_inverse=True)
    votes = np.zeros((len(unique), width), np.int64)
    np.add.at(votes, (inverse.ravel(), columns), 1)
    return unique, votes


def _reference_voxels(points, labels, voxel, k):
    """{voxel index: class or 255} of labelled points: votes per voxel (255 voting as
    "no label", column 0), argmax, ties to "no label" then the smaller class (RayFronts'
    external rule); ``labels`` int class indices or 255."""
    unique, votes = _vote(np.rint(points / voxel).astype(np.int64),
                          np.where(labels == 255, 0, labels + 1), k + 1)  # fmt: skip
    best = np.argmax(votes, axis=1)
    return {tuple(i): (int(b) - 1 if b else 255) for i, b in zip(unique.tolist(), best, strict=True)}


def _replica_index(cid):
    """Class index of a Replica id in the fixture's list (independent of the reader)."""
    name = REPLICA_CLASSES[cid]
    return REPLICA_SCORED.index(name) if name in REPLICA_SCORED else 255


def _frame_voxels(files, poses, k_matrix, voxel, k, depth_of, label_of):
    """{voxel index: class} of every frame's labelled pixels, ignored pixels casting no vote
    (``gt_unlabelled=drop``), ties to the smaller class; points cast to float32 as the engine
    holds them."""
    keys, classes = [], []
    k_inv = np.linalg.inv(k_matrix)
    for (depth_file, label_file), pose in zip(files, poses, strict=True):
        depth, label = depth_of(depth_file), label_of(label_file)
        v, u = np.nonzero((depth > 0) & (label != 255))
        cam = (np.stack([u, v, np.ones_like(u)], 1) @ k_inv.T) * depth[v, u][:, None]
        world = (cam @ pose[:3, :3].T + pose[:3, 3]).astype(np.float32)
        keys.append(np.rint(world / np.float32(voxel)).astype(np.int64))
        classes.append(label[v, u])
    unique, votes = _vote(np.concatenate(keys), np.concatenate(classes), k)
    return {tuple(i): int(c) for i, c in zip(unique.tolist(), np.argmax(votes, 1), strict=True)}


def _engine_voxels(frames, engine, external=False):
    state = engine._start_scene(0, {}, torch.device("cpu"))
    for batch in engine.loader():
        engine._map_batch(_Oracle(frames.classes), batch, {}, state, lambda s: _null())
    k = len(frames.classes)
    if external:
        labels = external_labels(state["gt"].votes, k, 255)
    else:
        labels = torch.argmax(state["gt"].votes, dim=1)
    return dict(zip(map(tuple, state["gt"].indices.tolist()), labels.tolist(), strict=True))


class _null:
    def __enter__(self):
        return self

    def __exit__(self, *a):
        return False


class _Oracle(DenseEncoder):
    """Patch size 1: the one-hot of the class whose flat colour a pixel has (zero where it is
    no class of ``classes``: ignored ones), or of ``constant`` everywhere; text: the one-hot
    of the class named in the prompt."""

    def __init__(self, classes, constant=None):
        super().__init__()
        self.anchor = torch.nn.Parameter(torch.zeros(1))
        self.classes, self.constant = tuple(classes), constant
        self.register_buffer("palette", torch.tensor(np.stack([COLOURS.get(c, (1, 2, 3))
                                                                for c in self.classes]),
                                                      dtype=torch.float32))  # fmt: skip

    @property
    def input_rule(self):
        return InputRule(1, (0.0, 0.0, 0.0), (1.0, 1.0, 1.0))

    def encode(self, images):
        b, _, h, w = images.shape
        k = len(self.classes)
        if self.constant is not None:
            onehot = F.one_hot(torch.full((b, h, w), self.constant), k).float()
        else:
            rgb = (images * 255).permute(0, 2, 3, 1).reshape(-1, 3)
            dist = torch.cdist(rgb, self.palette)
            far = (dist.min(1).values > 40).reshape(b, h, w)
            onehot = F.one_hot(dist.argmin(1).reshape(b, h, w), k).float() * (~far)[..., None]
        out = onehot.permute(0, 3, 1, 2)
        return DenseOutput(out, out, None)

    def encode_text(self, texts):
        out = torch.zeros(len(texts), len(self.classes))
        for i, text in enumerate(texts):
            hits = [c for c in self.classes if c in text]
            out[i, self.classes.index(max(hits, key=len))] = 1.0
        return out


def _protocol(**kw):
    """conf/dataset/replica.yaml's task settings (RayFronts' k = 5, thresholds), ``kw`` in
    place: the engine's keywords."""
    conf = dataset_conf("replica")
    keys = ("voxel_size", "lattice", "gt_unlabelled", "points", "storage", "knn",
            "prediction_threshold", "prompt_denoising", "metric")  # fmt: skip
    return {**{k: conf[k] for k in keys}, **kw}


def _constant_scores(reference, classes, constant):
    """mIoU, f-mIoU and accuracy when every scored voxel is predicted ``constant``
    (RayFronts' metric: classes absent from the ground truth do not count)."""
    gt = np.array([c for c in reference.values() if c != 255])
    hist = np.bincount(gt, minlength=len(classes))
    iou = hist[constant] / hist.sum()
    return iou / (hist > 0).sum(), hist[constant] / hist.sum() * iou, hist[constant] / hist.sum()


# ------------------------------------------------------------------ Replica (NICE-SLAM)
def test_nice_replica_reads_the_download_layout(nice):
    """cam_params.json's camera and scale, traj.txt's rows, uint16 depth above 32767 read
    unsigned, the class list without RayFronts' structural classes, and the frames on the
    rendered surfaces."""
    root, scene = nice
    raw = np.asarray(Image.open(root / "nice" / "office0" / "results" / "depth000003.png"))
    assert raw.max() > 32767  # the far wall: a value a signed read would turn negative
    frames = _nice(root)
    assert frames.classes == REPLICA_SCORED == ("basket", "bed", "cabinet", "chair", "sofa",
                                                "table")  # fmt: skip
    assert len(frames) == 6 and not frames.dropped and frames.ground_truth == "external"
    item = frames[3]
    np.testing.assert_allclose(item["depth"].numpy(), (raw / NICE_SCALE).astype(np.float32))
    assert float(item["depth"].max()) > 5.0
    np.testing.assert_allclose(item["intrinsics"].numpy(), nice_k(SIZE), rtol=1e-6)
    np.testing.assert_array_equal(item["pose"].numpy(), scene.poses[3])
    assert "gt_label" not in item
    _assert_on_boxes(frames, scene, tol=1e-3)
    skipped = _nice(root, frame_skip=2)
    assert [f.number for f in skipped.frames] == [0, 3]


def test_replica_ground_truth_is_hovsg_points_voxelised_as_rayfronts(nice):
    """The engine's ground-truth voxels equal a numpy recomputation from
    external_semseg_gt.pt: ids to classes (structural and unlabelled ids not scored), votes
    summed per 5 cm voxel, argmax with "no label" first."""
    root, _ = nice
    frames = _nice(root)
    engine = MappingEngine(frames, batch_size=3, **_protocol())
    got = _engine_voxels(frames, engine, external=True)
    data = torch.load(root / "gt" / "office0" / "external_semseg_gt.pt", weights_only=True)
    labels = np.array([_replica_index(int(c)) for c in data["semseg_gt_label"].numpy()])
    reference = _reference_voxels(data["semseg_gt_xyz"].numpy(), labels, 0.05,
                                  len(REPLICA_SCORED))  # fmt: skip
    assert got == reference
    assert {c for c in got.values() if c != 255} == set(range(1, 6))  # no basket in the room


def test_replica_scores_of_a_constant_prediction_equal_the_reference(nice):
    """Every voxel mapped as "chair" under RayFronts' settings (k = 5, thresholds): mIoU,
    f-mIoU and accuracy are those of the numpy ground truth with one class predicted."""
    root, _ = nice
    frames = _nice(root)
    chair = frames.classes.index("chair")
    result = MappingEngine(frames, batch_size=3, **_protocol()).run(
        _Oracle(frames.classes, constant=chair), build_variants(["bb"]))
    data = torch.load(root / "gt" / "office0" / "external_semseg_gt.pt", weights_only=True)
    labels = np.array([_replica_index(int(c)) for c in data["semseg_gt_label"].numpy()])
    reference = _reference_voxels(data["semseg_gt_xyz"].numpy(), labels, 0.05, 6)
    miou, fmiou, acc = _constant_scores(reference, frames.classes, chair)
    scores = result.scores()
    assert scores["val/scannet3d/replica/miou_bb"] == pytest.approx(miou, abs=1e-9)
    assert scores["val/scannet3d/replica/fmiou_bb"] == pytest.approx(fmiou, abs=1e-9)
    assert scores["val/scannet3d/replica/acc_bb"] == pytest.approx(acc, abs=1e-9)
    assert result.voxels == {"office0": sum(c != 255 for c in reference.values())}


# ------------------------------------------------------------------ Replica (Semantic-NeRF)
def _semnerf_files(root, n):
    seq = root / "semnerf" / "office_0" / "Sequence_1"
    return [(seq / "depth" / f"depth_{i}.png", seq / "semantic_class" / f"semantic_class_{i}.png")
            for i in range(n)]  # fmt: skip


def test_semnerf_replica_reads_labels_and_lifts_them_like_numpy(ninety):
    root, scene = ninety
    frames = _semnerf(root)
    assert frames.classes == REPLICA_SCORED and len(frames) == 6
    whole = SemanticNerfReplicaFrames(root / "semnerf", ["office_0"], list(REPLICA_IGNORED),
                                      **COMMON)  # a scene without a sequence: all of them
    assert [f.color for f in whole.frames] == [f.color for f in frames.frames]
    _assert_on_boxes(frames, scene)
    engine = MappingEngine(frames, batch_size=3, **_protocol(gt_unlabelled="drop", knn=0,
                           voxel_size=0.1, prediction_threshold=None, prompt_denoising=None))  # fmt: skip
    got = _engine_voxels(frames, engine)
    lut = np.full(256, 255)
    for cid in REPLICA_CLASSES:
        lut[cid] = _replica_index(cid)
    reference = _frame_voxels(
        _semnerf_files(root, 6), scene.poses, semnerf_k(SIZE), 0.1, 6,
        lambda p: np.asarray(Image.open(p)).astype(np.float64) / 1000,
        lambda p: lut[np.asarray(Image.open(p))],
    )  # fmt: skip
    assert got == reference and len(reference) > 50
    oracle = engine.run(_Oracle(frames.classes), build_variants(["bb"])).scores()
    for name in ("miou", "fmiou", "acc"):
        assert oracle[f"val/scannet3d/replica_semnerf/{name}_bb"] == 1.0


# ------------------------------------------------------------------ TartanAir v2
def _tartan_files(root, n):
    seq = root / "tartan" / "Factory" / "Data_ground" / "P0000"
    return [(seq / "depth_lcam_front" / f"{i:06d}_lcam_front_depth.png",
             seq / "seg_lcam_front" / f"{i:06d}_lcam_front_seg.png") for i in range(n)]  # fmt: skip


def _decode_float_png(path):
    """float32 depth from the RGBA bytes (PNG R, G, B, A = bytes 2, 1, 0, 3), numpy only."""
    rgba = np.asarray(Image.open(path))
    raw = np.stack([rgba[..., 2], rgba[..., 1], rgba[..., 0], rgba[..., 3]], -1).copy()
    depth = raw.view("<f4")[..., 0].astype(np.float64)
    return np.where(depth > 100, 0.0, depth)


def test_tartanair_reads_ned_poses_float_depth_and_palette_labels(ninety):
    """The NED pose lines, the RGBA float depth (the 500 m sky pixel not mapped) and the seg
    values through seg_rgbs.txt and name_map: frames on the rendered surfaces and ground
    truth voxels equal to numpy's."""
    root, scene = ninety
    frames = _tartan(root)
    assert frames.classes == TARTAN_CLASSES and len(frames) == 6
    first = frames[0]
    assert float(first["depth"][0, 0]) == 0.0 and float(first["depth"][0, 1]) > 0
    np.testing.assert_allclose(first["pose"].numpy(), scene.poses[0], atol=1e-12)
    _assert_on_boxes(frames, scene, tol=1e-4)
    engine = MappingEngine(frames, batch_size=3, **_protocol(gt_unlabelled="drop", knn=0,
                           voxel_size=0.25, prediction_threshold=None, prompt_denoising=None))  # fmt: skip
    got = _engine_voxels(frames, engine)
    value_to_class = np.full(256, 255)
    for name, ids in TARTAN_NAME_MAP.items():
        for row in ids if isinstance(ids, list) else [ids]:
            value_to_class[7 + 19 * row] = TARTAN_CLASSES.index(name)
    reference = _frame_voxels(_tartan_files(root, 6), scene.poses, semnerf_k(SIZE), 0.25,
                              len(TARTAN_CLASSES), _decode_float_png,
                              lambda p: value_to_class[np.asarray(Image.open(p))])  # fmt: skip
    assert got == reference and len(reference) > 20
    # the plant's palette row is named by no class: its pixels are not scored
    assert TARTAN_ROW_OF_RAW[35] not in {r for ids in TARTAN_NAME_MAP.values()
                                          for r in (ids if isinstance(ids, list) else [ids])}  # fmt: skip
    oracle = engine.run(_Oracle(frames.classes), build_variants(["bb"])).scores()
    assert oracle["val/scannet3d/tartanair/miou_bb"] == 1.0


def test_resize_to_the_protocol_size_scales_intrinsics_and_labels(ninety):
    """RayFronts' 480 x 640 from 640 x 640 here as 18 x 32 from 24 x 32: K's rows scaled by
    the ratios, depth and labels nearest-exact."""
    root, _ = ninety
    item = _tartan(root, image_size=(18, 32))[1]
    k = semnerf_k(SIZE)
    k[1] *= 18 / 24
    np.testing.assert_allclose(item["intrinsics"].numpy(), k, rtol=1e-6)
    assert item["gt_label"].shape == (18, 32) and item["depth"].shape == (18, 32)
    rows = np.floor((np.arange(18) + 0.5) * 24 / 18).astype(int)  # nearest-exact
    full = _tartan(root)[1]
    np.testing.assert_array_equal(item["gt_label"].numpy(), full["gt_label"].numpy()[rows])


# ------------------------------------------------------------------ bad input
@pytest.fixture
def copy(tmp_path):
    def make(src):
        dst = tmp_path / Path(src).name
        shutil.copytree(src, dst)
        return dst
    return make


def test_truncated_image_and_depth_of_another_size_are_skipped_and_named(ninety, copy):
    root, _ = ninety
    work = copy(root / "tartan").parent
    seq = work / "tartan" / "Factory" / "Data_ground" / "P0000"
    colour = seq / "image_lcam_front" / "000001_lcam_front.png"
    colour.write_bytes(colour.read_bytes()[:200])
    depth = seq / "depth_lcam_front" / "000002_lcam_front_depth.png"
    Image.fromarray(np.zeros((12, 32, 4), np.uint8), "RGBA").save(depth)
    frames = _tartan(work)
    engine = MappingEngine(frames, batch_size=3, **_protocol(knn=0, voxel_size=0.25))
    result = engine.run(_Oracle(frames.classes), build_variants(["bb"]))
    reasons = {Path(s.file).name: s.reason for s in result.skipped_samples}
    assert reasons["000001_lcam_front.png"].startswith("unreadable colour")
    assert reasons["000002_lcam_front_depth.png"] == (
        "depth is 12 x 32 px, its colour image 000002_lcam_front.png is 24 x 32")
    assert result.frames == {"Factory": 4}


def test_bad_pose_lines_and_a_missing_pose_drop_the_frame_and_name_the_line(ninety, copy):
    root, _ = ninety
    work = copy(root / "semnerf").parent
    traj = work / "semnerf" / "office_0" / "Sequence_1" / "traj_w_c.txt"
    lines = traj.read_text().splitlines()
    lines[1] = lines[1].replace(lines[1].split()[5], "nan", 1)
    lines[2] = " ".join(lines[2].split()[:12])
    traj.write_text("\n".join(lines[:5]) + "\n")  # frame 5 has an image but no pose line
    frames = _semnerf(work)
    dropped = {s.file: s.reason for s in frames.dropped}
    assert dropped == {
        f"{traj}:2": "non-finite pose (NaN or inf)",
        f"{traj}:3": "pose line holds 12 numbers, expected 16",
        str(traj): "no pose for frame 5: traj_w_c.txt has 5 lines",
    }
    assert [f.number for f in frames.frames] == [0, 3, 4]
    tartan = copy(root / "tartan").parent / "tartan"
    poses = tartan / "Factory" / "Data_ground" / "P0000" / "pose_lcam_front.txt"
    lines = poses.read_text().splitlines()
    poses.write_text("\n".join([lines[0], "1 2 3", *lines[2:]]) + "\n")
    assert [(s.file, s.reason) for s in _tartan(tartan.parent).dropped] == [
        (f"{poses}:2", "pose line holds 3 numbers, expected 7")]


def test_label_ids_outside_the_class_list_are_named(ninety, nice, copy):
    """A Semantic-NeRF class id, a TartanAir segmentation value, or a HOV-SG id of no class in
    the list: the frame is skipped and named (RayFronts maps it to "no label" or crashes),
    the ground-truth file is refused in one line."""
    root, _ = ninety
    work = copy(root / "semnerf").parent
    label = work / "semnerf" / "office_0" / "Sequence_1" / "semantic_class" / "semantic_class_1.png"
    array = np.asarray(Image.open(label)).copy()
    array[0, :3] = 55
    Image.fromarray(array).save(label)
    skipped = _semnerf(work)[1]
    assert skipped.file == str(label)
    assert skipped.reason.startswith("label id(s) [55] outside the class list of ")
    tartan = copy(root / "tartan").parent / "tartan"
    seg = tartan / "Factory" / "Data_ground" / "P0000" / "seg_lcam_front" / "000004_lcam_front_seg.png"
    array = np.asarray(Image.open(seg)).copy()
    array[5, 5] = 255  # the largest uint8: no palette row holds it
    Image.fromarray(array).save(seg)
    assert _tartan(tartan.parent)[4].reason.startswith("label id(s) [255] outside the class list")
    nroot, _ = nice
    gt = copy(nroot / "gt")
    data = torch.load(gt / "office0" / "external_semseg_gt.pt", weights_only=True)
    data["semseg_gt_label"][7] = 150.0
    torch.save(data, gt / "office0" / "external_semseg_gt.pt")
    frames = NiceReplicaFrames(nroot / "nice", ["office0"], None, gt, list(REPLICA_IGNORED),
                               **COMMON)  # fmt: skip
    with pytest.raises(ValueError) as err:
        frames.scene_ground_truth(0)
    assert str(err.value) == (f"dataset.gt_path: {gt / 'office0' / 'external_semseg_gt.pt'}: "
                              "label id(s) [150] outside the class list of "
                              f"{nroot / 'nice' / 'semantic_info' / 'office_0' / 'info_semantic.json'}")  # fmt: skip


def test_empty_or_missing_folders_name_the_file_the_download_and_the_key(nice, ninety, tmp_path):
    root, _ = nice
    (tmp_path / "nice").mkdir()
    shutil.copy(root / "nice" / "cam_params.json", tmp_path / "nice")
    shutil.copytree(root / "nice" / "semantic_info", tmp_path / "nice" / "semantic_info")
    (tmp_path / "nice" / "office0").mkdir()  # an empty scene folder
    with pytest.raises(FileNotFoundError) as err:
        NiceReplicaFrames(tmp_path / "nice", ["office0"], None, root / "gt", [], **COMMON)
    message = str(err.value)
    assert "\n" not in message and message.startswith(
        f"dataset.path: no trajectory '{tmp_path / 'nice' / 'office0' / 'traj.txt'}' "
        "(download: NICE-SLAM's Replica, github.com/cvg/nice-slam")
    assert message.endswith("set dataset.path")
    with pytest.raises(FileNotFoundError, match=r"^dataset\.gt_path: no ground truth .*"
                       r"external_semseg_gt\.pt' \(download: HOV-SG's Replica ground truth"):
        NiceReplicaFrames(root / "nice", ["office0"], None, tmp_path / "nogt", [], **COMMON)
    with pytest.raises(FileNotFoundError, match=r"^dataset\.scenes: no folder .*office9'"):
        NiceReplicaFrames(root / "nice", ["office9"], None, root / "gt", [], **COMMON)
    troot, _ = ninety
    with pytest.raises(FileNotFoundError, match=r"^dataset\.data_partition / dataset\.sequence: "
                       r"no trajectory folder .*P0001' \(download: TartanGround"):
        TartanAirFrames(troot / "tartan", ["Factory"], "Data_ground", "P0001",
                        "seg_label_clean.json", 100.0, **COMMON)  # fmt: skip
    with pytest.raises(FileNotFoundError, match=r"^dataset\.label_file: no label file"):
        TartanAirFrames(troot / "tartan", ["Factory"], "Data_ground", "P0000",
                        "seg_label.json", 100.0, **COMMON)  # fmt: skip


# ------------------------------------------------------------------ published figures, report
def test_published_rows_are_refused_without_source_out_of_range_or_unknown_benchmark(tmp_path):
    """conf/paper/rayfronts3d.yaml reads (its unconfirmed table named with the reason); a row
    without a source, with a figure outside 0-100 or a benchmark the file lacks is refused,
    naming the row."""
    from resireg_train.report.mapping3d import PUBLISHED_FILE, published_figures

    shipped = published_figures(PUBLISHED_FILE)
    assert shipped["benchmarks"] == ["replica", "scannet", "tartanair"]
    assert shipped["rows"] == {} and "could not be opened" in shipped["unconfirmed"][0]["reason"]
    good = {"source": "Doc, Table 1", "tier": "primary", "replica": {"miou": 30.1, "fmiou": 50}}
    cases = {
        "no source": ({**good, "source": ""}, "row 'm': no source"),
        "out of range": ({**good, "replica": {"miou": 130.0}},
                         "row 'm': replica.miou=130.0, expected mIoU / f-mIoU points in 0-100"),
        "unknown benchmark": ({**good, "kitti": {"miou": 3.0}},
                              "row 'm': benchmark 'kitti' is not in the table's benchmarks"),
        "tier": ({**good, "tier": "blog"}, "row 'm': tier='blog', expected one of"),
    }
    import yaml

    for name, (row, message) in cases.items():
        path = tmp_path / f"{name.replace(' ', '_')}.yaml"
        path.write_text(yaml.safe_dump({"benchmarks": ["replica"], "rows": {"m": row}}))
        with pytest.raises(ValueError) as err:
            published_figures(path)
        assert str(err.value).startswith(f"{path.name}: {message}"), name
    path = tmp_path / "ok.yaml"
    path.write_text(yaml.safe_dump({"benchmarks": ["replica"], "rows": {"m": good}}))
    assert published_figures(path)["rows"]["m"]["replica"]["miou"] == 30.1


@pytest.mark.slow
def test_replica3d_sweep_runs_through_resireg_eval_and_the_report_shows_it(nice, tiny_export,
                                                                          tmp_path):  # fmt: skip
    """`resireg-eval sweep=replica3d` (the console script, one scene of the fixture, a tiny
    export), then `resireg-report`: results.json holds the scores under val/scannet3d/replica/
    and RayFronts' protocol; table3d.md shows them x100 and names the published table it
    could not transcribe."""
    import json

    from helpers.run import run
    from resireg_train.report import report

    root, _ = nice
    logs = tmp_path / "logs"
    conf = TESTS / "conf"
    run("resireg-eval", "sweep=replica3d", "encoder=tiny_vlm", f"model_path={tiny_export}",
        f"dataset.path={root / 'nice'}", f"dataset.gt_path={root / 'gt'}",
        "dataset.scenes=[office0]", "dataset.frame_skip=1", f"dataset.image_size=[{SIZE[0]},{SIZE[1]}]",
        "batch_size=3", "full.n_prototypes=4", "num_workers=0", f"paths.log_dir={logs}",
        f"hydra.searchpath=[file://{conf}]")  # fmt: skip
    (sweep,) = (logs / "replica3d" / "multirun").iterdir()
    (results,) = [json.loads(p.read_text()) for p in sweep.glob("*/results.json")]
    assert results["status"] == "completed" and results["frames"] == {"office0": 3}
    settings = results["protocol"]["settings"]
    assert (settings["voxel_size"], settings["knn"], settings["prompt_denoising"]) == (0.05, 5, 0.5)
    miou = results["final"]["val/scannet3d/replica/miou_full"]
    files = report(sweep)
    import pandas as pd

    row = pd.read_csv(files["table3d_csv"]).iloc[0]
    assert row["model"] == "tiny_vlm + Full"
    assert row["replica mIoU"] == pytest.approx(100 * miou, abs=1e-9)
    text = files["table3d_md"].read_text()
    assert text.startswith("# 3D semantic mapping on replica ")
    assert "not transcribed: RayFronts' zero-shot 3D semantic segmentation table" in text
