"""resireg.mapping.SemanticMap: fusion against independent references (numpy voxel means of the
encoder's own features at patch_points), ReSiReg Full's window as one scene, save / load /
resume, the voxel budget, classification against a hand-built prompt average, the PLY read back
by open3d. A tiny ResiregVLM with random weights on a ray-cast box room."""

import json

import numpy as np
import pytest
import torch
import torch.nn.functional as F

from helpers.optional import open3d
from helpers.paths import ROOT
from helpers.tiny import TINY_BACKBONE, TINY_HEAD, TINY_TEXT
from resireg.mapping import MapFullError, SemanticMap, patch_points
from resireg.models import ResiregVLM
from resireg_train.data.scannet_room import NYU40_COLOURS, SyntheticRoom

VOXEL = 0.2


@pytest.fixture(scope="module")
def encoder():
    torch.manual_seed(0)
    return ResiregVLM.build(TINY_BACKBONE, TINY_HEAD, TINY_TEXT).eval()


@pytest.fixture(scope="module")
def room():
    """8 frames of 64 x 96 px: uint8 images [B, 3, H, W], depth [B, H, W], K, poses."""
    r = SyntheticRoom(image_size=(64, 96), focal=60.0, frames=8, bad_pose_frame=None)
    depth, images, poses = [], [], []
    for i in range(r.frames):
        d, raw = r.render(i)
        nyu = np.vectorize(lambda x: {1: 1, 2: 5, 3: 2, 4: 7, 5: 8, 6: 6, 7: 3, 11: 4, 35: 40,
                                      36: 22}.get(int(x), 0))(raw)  # fmt: skip
        rgb = NYU40_COLOURS[nyu].astype(np.int64)
        rgb = (rgb + np.random.default_rng(i).integers(-20, 20, rgb.shape)).clip(0, 255)
        images.append(torch.from_numpy(rgb.astype(np.uint8)).permute(2, 0, 1))
        depth.append(torch.from_numpy(d.astype(np.float32)))
        poses.append(torch.from_numpy(r.pose(i)))
    k = torch.from_numpy(r.intrinsics).float()
    return torch.stack(images), torch.stack(depth), k, torch.stack(poses)


def numpy_voxel_means(points, feats, voxel):
    """Reference: round(p / v) keys (numpy, float64), lexicographic order, float64 means, unit."""
    keys = np.round(points.astype(np.float64) / voxel).astype(np.int64)
    uniq, inv = np.unique(keys, axis=0, return_inverse=True)
    sums = np.zeros((len(uniq), feats.shape[1]))
    np.add.at(sums, inv.reshape(-1), feats.astype(np.float64))
    counts = np.bincount(inv.reshape(-1), minlength=len(uniq))
    mean = sums / counts[:, None]
    return uniq, mean / np.maximum(np.linalg.norm(mean, axis=1, keepdims=True), 1e-12)


def direct_points_and_features(encoder, images, depth, k, poses, dense=None):
    """The direct path: the encoder's language tokens normalised (``bb``) or given features,
    at the points of patch_points."""
    if dense is None:
        x = encoder.input_rule.normalize(images.float() / 255)
        with torch.no_grad():
            dense = F.normalize(encoder.encode(x).language.float(), dim=1)
    pts, valid = patch_points(depth, k, poses, tuple(dense.shape[-2:]))
    return pts[valid].numpy(), dense.permute(0, 2, 3, 1)[valid].numpy()


def test_windows_equal_numpy_voxel_means_of_the_encoder_features(encoder, room):
    images, depth, k, poses = room
    smap = SemanticMap(encoder, "bb", VOXEL)
    for s in (0, 4):
        smap.add(images[s : s + 4], depth[s : s + 4], k, poses[s : s + 4])
    pts, feats = direct_points_and_features(encoder, images, depth, k, poses)
    keys, means = numpy_voxel_means(pts, feats, VOXEL)
    assert smap.indices.tolist() == keys.tolist()
    np.testing.assert_allclose(smap.features()[1].numpy(), means, atol=1e-6)
    assert smap.frames == 8 and smap.windows == 2 and len(smap) == len(keys) > 30


def test_full_treats_the_window_as_one_scene(encoder, room):
    """A window of 4 frames = ReSiReg Full on the 4 frames together (encode_image, the library's
    direct path), and differs from the same frames mapped one per window."""
    images, depth, k, poses = room
    name = "full@n_prototypes:6"
    window = SemanticMap(encoder, name, VOXEL)
    window.add(images[:4], depth[:4], k, poses[:4])
    dense = encoder.encode_image(images[:4].float() / 255, "full", n_prototypes=6)
    pts, feats = direct_points_and_features(encoder, None, depth[:4], k, poses[:4], dense)
    keys, means = numpy_voxel_means(pts, feats, VOXEL)
    assert window.indices.tolist() == keys.tolist()
    np.testing.assert_allclose(window.features()[1].numpy(), means, atol=1e-6)
    single = SemanticMap(encoder, name, VOXEL)
    for i in range(4):
        single.add(images[i : i + 1], depth[i : i + 1], k, poses[i : i + 1])
    assert single.indices.tolist() == window.indices.tolist()
    assert (single.features()[1] - window.features()[1]).abs().max() > 1e-3


@pytest.mark.parametrize("sum_dtype", ["float64", "float32"])
def test_save_load_query_and_resume_equal_one_run(encoder, room, tmp_path, sum_dtype):
    images, depth, k, poses = room
    whole = SemanticMap(encoder, "lite", VOXEL, sum_dtype=sum_dtype)
    for s in (0, 3, 6):
        whole.add(images[s : s + 3], depth[s : s + 3], k, poses[s : s + 3])
    part = SemanticMap(encoder, "lite", VOXEL, sum_dtype=sum_dtype)
    part.add(images[:3], depth[:3], k, poses[:3])
    part.meta = {"kept_frames": 3}
    part.save(tmp_path / "map")
    resumed = SemanticMap.load(tmp_path / "map", encoder)
    assert resumed.meta == {"kept_frames": 3} and resumed.frames == 3
    for s in (3, 6):
        resumed.add(images[s : s + 3], depth[s : s + 3], k, poses[s : s + 3])
    assert torch.equal(resumed.indices, whole.indices)
    assert torch.equal(resumed.features()[1], whole.features()[1])  # bit for bit
    assert torch.equal(resumed.mean_colours(), whole.mean_colours())
    texts = ["a wall", "a red chair", "the floor"]
    whole.save(tmp_path / "whole")
    again = SemanticMap.load(tmp_path / "whole", encoder)
    assert torch.equal(again.query(texts), whole.query(texts))
    # the query is the cosine of the unit voxel features with the unit text embeddings
    q = F.normalize(encoder.encode_text(texts).float(), dim=-1)
    np.testing.assert_allclose(whole.query(texts).numpy(), (whole.features()[1] @ q.T).numpy(),
                               atol=1e-6)  # fmt: skip
    assert whole.query("a wall").shape == (len(whole),)
    if sum_dtype == "float32":
        exact = SemanticMap(encoder, "lite", VOXEL)
        for s in (0, 3, 6):
            exact.add(images[s : s + 3], depth[s : s + 3], k, poses[s : s + 3])
        np.testing.assert_allclose(whole.features()[1].numpy(), exact.features()[1].numpy(),
                                   atol=1e-6)  # fmt: skip
        assert whole.voxels._sums.dtype == torch.float32


def test_an_interrupted_save_leaves_the_previous_one(encoder, room, tmp_path, monkeypatch):
    images, depth, k, poses = room
    smap = SemanticMap(encoder, "bb", VOXEL)
    smap.add(images[:2], depth[:2], k, poses[:2])
    smap.save(tmp_path)
    before = smap.features()[1].clone()
    smap.add(images[2:4], depth[2:4], k, poses[2:4])
    real = json.dumps

    def crash(*args, **kwargs):  # the tensors are written, the JSON (the commit) is not
        raise OSError("disk full")

    monkeypatch.setattr(json, "dumps", crash)
    with pytest.raises(OSError, match="disk full"):
        smap.save(tmp_path)
    monkeypatch.setattr(json, "dumps", real)
    loaded = SemanticMap.load(tmp_path, encoder)
    assert loaded.frames == 2 and torch.equal(loaded.features()[1], before)
    assert not list(tmp_path.glob(".*.tmp"))
    assert len(list(tmp_path.glob("map-*.safetensors"))) == 1  # no orphan of the failed save


def test_voxel_budget_raises_before_adding(encoder, room):
    images, depth, k, poses = room
    smap = SemanticMap(encoder, "bb", VOXEL, max_voxels=10_000)
    smap.add(images[:2], depth[:2], k, poses[:2])
    n, feats = len(smap), smap.features()[1].clone()
    smap.max_voxels = n + 1
    with pytest.raises(
        MapFullError, match=rf"max_voxels={n + 1}: .* adds \d+ voxels to the map's {n}"
    ):
        smap.add(images[2:6], depth[2:6], k, poses[2:6])
    assert len(smap) == n and smap.frames == 2 and torch.equal(smap.features()[1], feats)
    with pytest.raises(ValueError, match="max_voxels=0"):
        SemanticMap(encoder, "bb", VOXEL, max_voxels=0)
    with pytest.raises(ValueError, match="points='voxel'"):
        SemanticMap(encoder, "bb", VOXEL, points="voxel")


def test_classify_equals_the_averaged_prompts_by_hand(encoder, room):
    """The class of each voxel: the argmax of the cosine to each class's 80 OpenAI templates
    embedded, normalised, averaged and renormalised (open_clip's template list)."""
    import open_clip

    images, depth, k, poses = room
    smap = SemanticMap(encoder, "bb", VOXEL)
    smap.add(images[:4], depth[:4], k, poses[:4])
    classes = ["wall", "floor", "chair", "table"]
    protos = []
    for c in classes:
        e = encoder.encode_text([t(c) for t in open_clip.OPENAI_IMAGENET_TEMPLATES]).double()
        e = e / e.norm(dim=1, keepdim=True)
        protos.append((e.mean(0) / e.mean(0).norm()).numpy())
    feats = smap.features()[1].double().numpy()
    expect = np.argmax(feats @ np.stack(protos).T, axis=1)
    got = smap.classify(classes).numpy()
    assert (got == expect).mean() > 0.999  # float32 near-ties aside
    assert len(set(got.tolist())) > 1


def test_ply_read_back_by_open3d(encoder, room, tmp_path):
    o3d = open3d()
    images, depth, k, poses = room
    smap = SemanticMap(encoder, "bb", VOXEL)
    smap.add(images[:3], depth[:3], k, poses[:3])
    for colour_by, kwargs in (("rgb", {}), ("pca", {}), ("query", {"text": "a chair"}),
                              ("class", {"classes": ["wall", "floor"]})):  # fmt: skip
        path = smap.to_ply(tmp_path / f"{colour_by}.ply", colour_by, **kwargs)
        cloud = o3d.io.read_point_cloud(str(path))
        np.testing.assert_array_equal(np.asarray(cloud.points, dtype=np.float32),
                                      smap.centres().numpy())  # fmt: skip
        expect = smap.colours_by(colour_by, **kwargs).numpy()
        np.testing.assert_allclose(np.asarray(cloud.colors) * 255, expect, atol=1e-3)
    # the mean colour of a voxel is the mean of its patches' area-averaged colours
    wall = smap.mean_colours().float().mean(0)
    assert wall.min() > 0


def test_pca_colours_follow_sklearn_components():
    """pca_colours' first channel orders the rows as scikit-learn's first principal component
    does (up to its sign)."""
    from sklearn.decomposition import PCA

    from resireg.mapping import pca_colours

    g = torch.Generator().manual_seed(1)
    x = torch.randn(500, 16, generator=g) * torch.linspace(3, 0.1, 16)
    first = PCA(3).fit_transform(x.numpy())[:, 0]
    red = pca_colours(x)[:, 0].float().numpy()
    inner = (red > 5) & (red < 250)  # not clipped at the percentiles
    corr = np.corrcoef(red[inner], first[inner])[0, 1]
    assert abs(corr) > 0.999


def test_python_defaults_are_the_configs():
    """One source per default: SemanticMap's keyword defaults equal conf/map.yaml's keys (the
    Python API a robot calls and resireg-map agree), and its POINTS are the 3D task's."""
    import inspect

    import yaml

    from resireg.specs.mapping import POINTS
    from resireg_train.evaluation.mapping.engine import POINTS as TASK_POINTS

    conf = yaml.safe_load((ROOT / "conf" / "map.yaml").read_text())
    params = inspect.signature(SemanticMap).parameters
    for name in ("points", "lattice", "sum_dtype", "max_voxels", "short_side"):
        assert params[name].default == conf[name], name
    assert POINTS == TASK_POINTS and conf["points"] in POINTS


def test_saved_map_files_prove_their_content(encoder, room, tmp_path):
    """map.json records its tensor file's SHA-256 (hashlib here) and its own digest: 4 KiB of
    0xFF or one flipped bit in the tensor file, a truncated tensor file or map.json, an edited
    voxel_size: each an IntegrityError naming the file, never a map with wrong numbers or a
    raw SafetensorError / JSONDecodeError. An encoder of another dimension is refused at
    load."""
    import hashlib
    import shutil

    from resireg.integrity import IntegrityError

    images, depth, k, poses = room
    smap = SemanticMap(encoder, "bb", VOXEL)
    smap.add(images[:2], depth[:2], k, poses[:2])
    good = smap.save(tmp_path / "good")
    record = json.loads((good / "map.json").read_text())
    name = record["tensors"]
    assert record["sha256"] == {name: hashlib.sha256((good / name).read_bytes()).hexdigest()}

    def damaged(label, edit):
        folder = tmp_path / label
        shutil.copytree(good, folder)
        edit(folder)
        return folder

    def overwrite(folder):
        with open(folder / name, "r+b") as f:
            f.seek((folder / name).stat().st_size // 2)
            f.write(b"\xff" * 4096)

    def flip(folder):
        data = bytearray((folder / name).read_bytes())
        data[len(data) - 100] ^= 0x01
        (folder / name).write_bytes(bytes(data))

    def truncate(folder, file):
        data = (folder / file).read_bytes()
        (folder / file).write_bytes(data[: len(data) // 2])

    def voxel_size(folder):
        text = (folder / "map.json").read_text()
        (folder / "map.json").write_text(text.replace('"voxel_size": 0.2', '"voxel_size": 0.25'))

    cases = {
        "overwritten": (overwrite, name),
        "flipped": (flip, name),
        "truncated": (lambda f: truncate(f, name), name),
        "truncated_json": (lambda f: truncate(f, "map.json"), "map.json"),
        "voxel_size": (voxel_size, "map.json"),
    }
    for label, (edit, file) in cases.items():
        folder = damaged(label, edit)
        with pytest.raises(IntegrityError) as info:
            SemanticMap.load(folder, encoder)
        assert str(folder / file) in str(info.value), (label, str(info.value))
    # another encoder dimension: a map of 7-d features
    other = SemanticMap(None, "bb", VOXEL)
    other.fuse(torch.randn(2, 7, 4, 6), depth[:2], k, poses[:2])
    other.save(tmp_path / "seven")
    with pytest.raises(ValueError, match="the map holds 7-d features, the encoder"):
        SemanticMap.load(tmp_path / "seven", encoder)
    assert SemanticMap.load(tmp_path / "seven").dim == 7


def test_fuse_refuses_non_finite_and_integer_inputs(room):
    """SemanticMap.fuse refuses NaN / inf features, intrinsics and poses, and integer
    features, naming the argument (resireg.method.checks.check_features), and adds nothing."""
    from resireg.method.checks import NonFiniteError

    _, depth, k, poses = room
    smap = SemanticMap(None, "bb", VOXEL)
    feats = torch.randn(2, 8, 4, 6)
    smap.fuse(feats, depth[:2], k, poses[:2])
    before = smap.features()[1].clone()
    bad = feats.clone()
    bad[0, 3, 1, 1] = float("nan")
    with pytest.raises(NonFiniteError, match=r"features holds 1 non-finite"):
        smap.fuse(bad, depth[:2], k, poses[:2])
    with pytest.raises(TypeError, match="features must be a floating-point tensor"):
        smap.fuse((feats * 10).to(torch.int64), depth[:2], k, poses[:2])
    k_bad = k.clone()
    k_bad[0, 0] = float("inf")
    with pytest.raises(NonFiniteError, match="intrinsics holds 1 non-finite"):
        smap.fuse(feats, depth[:2], k_bad, poses[:2])
    pose_bad = poses[:2].clone()
    pose_bad[1, 0, 3] = float("nan")
    with pytest.raises(NonFiniteError, match="cam_to_world holds 1 non-finite"):
        smap.fuse(feats, depth[:2], k, pose_bad)
    assert smap.frames == 2 and torch.equal(smap.features()[1], before)
