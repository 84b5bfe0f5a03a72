"""Building-scale maps (resireg.mapping.compact, SemanticMap's storage, top_k, region, merge,
the saved formats): each against an independent reference. The compact accumulation against a
float64 numpy mean over 10,000 updates (and a plain float16 running mean, which stalls); top-k
against a float64 numpy brute force with ties; merges against one map of both frame sets and
against mapping the transformed frames; old maps against the tensors of their own files read by
safetensors and the numbers the code that wrote them read back."""

import json
import warnings

import numpy as np
import pytest
import torch
from test_semantic_map import VOXEL, encoder, room  # noqa: F401  (module fixtures)

from helpers.paths import ROOT, TESTS
from resireg.errors import MapError
from resireg.integrity import IntegrityError
from resireg.mapping import SemanticMap
from resireg.mapping.compact import CompactVoxelMap
from resireg.mapping.map_file import MapFormatWarning

FIXTURES = TESTS / "fixtures" / "maps"


def frames(n, seed, dim=16, size=(48, 64), grid=(12, 16), span=2.0):
    """``n`` windows of 2 posed frames: random depth 1..4 m, random features, colours."""
    g = torch.Generator().manual_seed(seed)
    out = []
    h, w = size
    for _ in range(n):
        depth = 1.0 + 3 * torch.rand(2, h, w, generator=g)
        k = torch.tensor([[40.0, 0, (w - 1) / 2], [0, 40.0, (h - 1) / 2], [0, 0, 1]])
        pose = torch.eye(4).repeat(2, 1, 1)
        pose[:, :3, 3] = torch.rand(2, 3, generator=g) * span
        feats = torch.randn(2, dim, *grid, generator=g)
        colour = torch.rand(2, 3, h, w, generator=g)
        out.append((feats, depth, k, pose, colour))
    return out


def unit(x):
    x = np.asarray(x, dtype=np.float64)
    return x / np.maximum(np.linalg.norm(x, axis=-1, keepdims=True), 1e-300)


# ---------------------------------------------------------------- compact accumulation
@pytest.mark.slow
@pytest.mark.parametrize("dtype", [torch.float16, torch.bfloat16])
def test_compact_accumulation_keeps_the_float64_mean(dtype):
    """One voxel seen 10,000 times (1,000 calls of 10 points), its features drifting from one
    direction to another halfway: the stored direction keeps a cosine >= 0.9999 to the float64
    mean of everything it saw, and its count is exact. A plain float16 running mean of the same
    points stalls (its cosine falls below 0.999): the data would catch a stalling store."""
    g = torch.Generator().manual_seed(0)
    k = 64
    a, b = torch.randn(k, generator=g), torch.randn(k, generator=g)
    cm = CompactVoxelMap(0.1, k, dtype=dtype, hot_voxels=4)
    point = torch.full((10, 3), 0.02)
    total = np.zeros(k)
    naive = np.zeros(k, dtype=np.float16)
    seen = 0
    for call in range(1000):
        base = a if call < 500 else b
        feats = base + 0.5 * torch.randn(10, k, generator=g)
        cm.add(point, feats)
        total += feats.double().sum(0).numpy()
        for f in feats.numpy():  # a float16 running mean, updated in float32
            seen += 1
            naive = (naive + (f - naive.astype(np.float32)) / seen).astype(np.float16)
    stored = cm.features()[1][0].double().numpy()
    assert int(cm.counts[0]) == 10_000 and len(cm) == 1
    assert unit(stored) @ unit(total) >= 0.9999
    assert unit(naive) @ unit(total) < 0.999


def test_compact_voxels_equal_numpy_voxel_means():
    """Random points in calls of varying size, through add and add_pairs, a small hot buffer:
    the voxels are numpy's (round lattice, lexicographic order), their counts exact, each
    stored direction within float16 rounding of the float64 mean (cosine >= 0.99999), and the
    mean colours (uint8, rounded at each fold) within two levels of the float64 mean."""
    g = torch.Generator().manual_seed(1)
    k, voxel = 32, 0.25
    cm = CompactVoxelMap(voxel, k, hot_voxels=16)
    pts_all, feats_all, rgb_all, w_all = [], [], [], []
    for call in range(30):
        n = int(torch.randint(1, 400, (1,), generator=g))
        pts = torch.rand(n, 3, generator=g) * 2
        feats = torch.randn(n, k, generator=g) + 2.0
        rgb = torch.rand(n, 3, generator=g)
        if call % 2:
            cm.add(pts, feats, rgb)
            w = np.ones(n)
        else:  # as pairs: each point counted 1..3 times
            index = torch.round(pts.double() / voxel).long()
            counts = torch.randint(1, 4, (n,), generator=g)
            cm.add_pairs(index, counts, feats, torch.arange(n), rgb)
            w = counts.numpy().astype(np.float64)
        pts_all.append(pts.numpy())
        feats_all.append(feats.numpy())
        rgb_all.append(rgb.numpy())
        w_all.append(w)
    pts, feats = np.concatenate(pts_all), np.concatenate(feats_all).astype(np.float64)
    rgb, w = np.concatenate(rgb_all).astype(np.float64), np.concatenate(w_all)
    keys = np.round(pts.astype(np.float64) / voxel).astype(np.int64)
    uniq, inv = np.unique(keys, axis=0, return_inverse=True)
    inv = inv.reshape(-1)
    sums = np.zeros((len(uniq), k))
    np.add.at(sums, inv, feats * w[:, None])
    csum = np.zeros((len(uniq), 3))
    np.add.at(csum, inv, rgb * w[:, None])
    counts = np.bincount(inv, weights=w, minlength=len(uniq))
    assert cm.indices.tolist() == uniq.tolist()
    np.testing.assert_array_equal(cm.counts.numpy(), counts.astype(np.int64))
    cos = np.sum(unit(cm.features()[1].numpy()) * unit(sums), axis=1)
    assert cos.min() >= 0.99999
    mean_rgb = csum / counts[:, None] * 255
    assert np.abs(cm.mean_colours().numpy() - mean_rgb).max() <= 2.0
    np.testing.assert_allclose(cm.means().numpy(), sums / counts[:, None], rtol=2e-3, atol=2e-3)


# ---------------------------------------------------------------- top-k and regions
def palette_frames(seed, dim):
    """Frames whose patch features come from a palette of 6 vectors: voxels of identical
    features, so scores tie exactly."""
    out = []
    g = torch.Generator().manual_seed(seed)
    palette = torch.randn(6, dim, generator=g)
    for feats, depth, k, pose, colour in frames(3, seed, dim=dim):
        pick = torch.randint(0, 6, (2, *feats.shape[-2:]), generator=g)
        feats = palette[pick].permute(0, 3, 1, 2).contiguous()
        out.append((feats, depth, k, pose, colour))
    return out


def brute_top_k(smap, query, k):
    """The reference: float64 numpy scores of every voxel's features() row with ``query``,
    best first, ties to the lower voxel index (lexicographic order)."""
    feats = smap.features()[1].double().numpy()
    scores = feats @ query.double().numpy()
    order = np.lexsort((np.arange(len(scores)), -scores))[:k]
    return smap.indices.numpy()[order], scores[order]


@pytest.mark.parametrize("storage", ["exact", "compact"])
def test_top_k_equals_a_float64_brute_force_ties_included(encoder, storage):  # noqa: F811
    """top_k of texts (one string, a list) equals the float64 brute force over the map's
    features, indices and scores, on a map with many exactly tied voxels; region-restricted
    top_k equals the brute force over the voxels the region holds."""
    dim = int(encoder.encode_text(["x"]).shape[-1])
    smap = SemanticMap(encoder, "bb", 0.01, storage=storage,
                       compact={"dim": 8, "basis_rows": 100, "hot_voxels": 64})  # fmt: skip
    for f in palette_frames(3, dim):
        smap.fuse(*f)
    feats = smap.features()[1]
    scores_seen = feats.double() @ smap.project(smap.text_queries(["a chair"]))[0].double()
    assert len(smap) > 1000 and len(np.unique(scores_seen.numpy())) < len(smap) / 10  # ties
    texts = ["a chair", "the floor"]
    for text, got in zip(texts, smap.top_k(texts, k=50), strict=True):
        q = smap.project(smap.text_queries([text]))[0]
        want, scores = brute_top_k(smap, q, 50)
        np.testing.assert_array_equal(got.indices.numpy(), want)
        np.testing.assert_allclose(got.scores.numpy(), scores, rtol=1e-14)  # float64 sums' order
        centres = smap.centres().numpy()[
            [smap.indices.tolist().index(i) for i in want[:5].tolist()]
        ]
        np.testing.assert_array_equal(got.centres.numpy()[:5], centres)
    one = smap.top_k("a chair", k=7)
    assert one.indices.shape == (7, 3)
    box = [[0.5, 0.5, 1.5], [2.0, 2.0, 3.0]]
    inside = smap.region(box=box)
    c = smap.centres().double().numpy()
    mask = ((c >= np.array(box[0])) & (c <= np.array(box[1]))).all(1)
    np.testing.assert_array_equal(inside.numpy(), smap.indices.numpy()[mask])
    got = smap.top_k("a chair", k=10, box=box)
    q = smap.project(smap.text_queries(["a chair"]))[0].double().numpy()
    scores = feats.double().numpy()[mask] @ q
    order = np.lexsort((np.arange(mask.sum()), -scores))[:10]
    np.testing.assert_array_equal(got.indices.numpy(), smap.indices.numpy()[mask][order])
    ball = smap.region(centre=[1.0, 1.0, 2.5], radius=0.75)
    near = np.linalg.norm(c - np.array([1.0, 1.0, 2.5]), axis=1) <= 0.75
    np.testing.assert_array_equal(ball.numpy(), smap.indices.numpy()[near])
    assert smap.region(box=[[50, 50, 50], [51, 51, 51]]).shape == (0, 3)


def test_compact_query_and_classify_in_the_basis_space(encoder, room):  # noqa: F811
    """A compact map's query is the cosine of its stored features with the projected,
    renormalised texts (float64 numpy to 1e-6); classify is the argmax of the same with the
    projected prototypes; a map read before its basis is fitted holds no voxel."""
    images, depth, k, poses = room
    smap = SemanticMap(encoder, "bb", VOXEL, storage="compact",
                       compact={"dim": 8, "basis_rows": 40})  # fmt: skip
    smap.add(images[:1], depth[:1], k, poses[:1])
    assert len(smap) == 0 and smap.frames == 1 and smap.basis is None  # waiting for its basis
    for s in (1, 4):
        smap.add(images[s : s + 3], depth[s : s + 3], k, poses[s : s + 3])
    assert smap.basis is not None and smap.basis.shape[1] == 8 and len(smap) > 30
    basis = smap.basis.double().numpy()
    np.testing.assert_allclose(basis.T @ basis, np.eye(8), atol=1e-5)
    texts = ["a wall", "a red chair"]
    q = unit(smap.text_queries(texts).double().numpy() @ basis)
    feats = smap.features()[1].double().numpy()
    np.testing.assert_allclose(smap.query(texts).numpy(), feats @ q.T, atol=1e-6)
    classes = ["wall", "floor", "chair"]
    protos = unit(smap.prototypes(classes).double().numpy() @ basis)
    np.testing.assert_array_equal(smap.classify(classes).numpy(), np.argmax(feats @ protos.T, 1))


# ---------------------------------------------------------------- save, load, resume
def test_compact_map_saved_loaded_and_resumed_equals_one_run(encoder, room, tmp_path):  # noqa: F811
    """A compact map saved after two windows (its hot blocks with it), loaded and given the last
    equals the map that was never saved, bit for bit (features, counts, colours); map.json
    records the format, the storage and the basis by a SHA-256 hashlib recomputes from the
    tensor safetensors reads."""
    import hashlib

    from safetensors.numpy import load_file

    images, depth, k, poses = room
    settings = {"dim": 8, "basis_rows": 100, "hot_voxels": 8}
    whole = SemanticMap(encoder, "lite", VOXEL, storage="compact", compact=settings)
    for s in (0, 3, 6):
        whole.add(images[s : s + 3], depth[s : s + 3], k, poses[s : s + 3])
    part = SemanticMap(encoder, "lite", VOXEL, storage="compact", compact=settings)
    for s in (0, 3):
        part.add(images[s : s + 3], depth[s : s + 3], k, poses[s : s + 3])
    assert part.voxels.tensors()["hot_rows"][0].numel() > 0  # blocks waiting: saved too
    part.save(tmp_path / "map")
    record = json.loads((tmp_path / "map" / "map.json").read_text())
    assert (
        record["format"] == "resireg.semantic_map/2" and record["settings"]["storage"] == "compact"
    )
    tensors = load_file(str(tmp_path / "map" / record["tensors"]))
    basis = tensors["basis"]
    assert basis.shape == (whole.dim, 8)
    assert record["basis_sha256"] == hashlib.sha256(basis.astype("<f4").tobytes()).hexdigest()
    resumed = SemanticMap.load(tmp_path / "map", encoder)
    resumed.add(images[6:9], depth[6:9], k, poses[6:9])
    assert torch.equal(resumed.indices, whole.indices)
    assert torch.equal(resumed.features()[1], whole.features()[1])
    assert torch.equal(resumed.voxels.counts, whole.voxels.counts)
    assert torch.equal(resumed.mean_colours(), whole.mean_colours())
    assert resumed.basis_sha256 == whole.basis_sha256


def test_old_format_maps_load_and_resume_bit_for_bit():
    """The fixtures written by the code before the digests (a MapFormatWarning) and by the code
    of format /1 with digests (silent) load: their voxels, sums and counts equal their own
    tensor files read by safetensors; their features and colours equal what the writing code
    read back (expected.npz); fusing the fixture's frames once more equals a new map fusing
    them twice."""
    import sys

    from safetensors.numpy import load_file

    sys.path.insert(0, str(FIXTURES))
    try:
        from make_fixtures import frames as fixture_frames
    finally:
        sys.path.remove(str(FIXTURES))
    feats, depth, k, pose, colour = fixture_frames()
    for name, warns in (("v0-no-digests", True), ("v1-digests", False)):
        folder = FIXTURES / name
        record = json.loads((folder / "map.json").read_text())
        with warnings.catch_warnings(record=True) as caught:
            warnings.simplefilter("always")
            smap = SemanticMap.load(folder)
        flagged = [w for w in caught if issubclass(w.category, MapFormatWarning)]
        assert bool(flagged) == warns, name
        if warns:
            assert "before maps recorded their digests" in str(flagged[0].message)
        raw = load_file(str(folder / record["tensors"]))
        state = smap.voxels.state()
        for key in ("indices", "sums", "counts"):
            np.testing.assert_array_equal(state[key].numpy(), raw[f"features.{key}"], key)
        cstate = smap.colours.state()
        np.testing.assert_array_equal(cstate["sums"].numpy(), raw["colour.sums"])
        expected = np.load(f"{folder}.expected.npz")
        np.testing.assert_array_equal(smap.indices.numpy(), expected["indices"])
        np.testing.assert_array_equal(smap.features()[1].numpy(), expected["features"])
        np.testing.assert_array_equal(smap.mean_colours().numpy(), expected["colours"])
        assert smap.meta == {"kept_frames": 2, "note": "fixture"} and smap.lattice == "floor"
        fresh = SemanticMap(None, "bb", 0.25, lattice="floor")
        for _ in range(2):
            for i in (0, 1):
                fresh.fuse(feats[i : i + 1], depth[i : i + 1], k, pose[i : i + 1],
                           colour[i : i + 1])  # fmt: skip
        for i in (0, 1):
            smap.fuse(feats[i : i + 1], depth[i : i + 1], k, pose[i : i + 1], colour[i : i + 1])
        assert torch.equal(smap.indices, fresh.indices)
        assert torch.equal(smap.voxels.state()["sums"], fresh.voxels.state()["sums"])
        assert torch.equal(smap.mean_colours(), fresh.mean_colours())


def _rewrite(folder, edit):
    """Edit map.json and recompute its digests, as anyone editing the files would."""
    import hashlib

    from resireg.mapping.map_file import record_digest as _record_digest

    path = folder / "map.json"
    record = json.loads(path.read_text())
    edit(record)
    record["sha256"] = {n: hashlib.sha256((folder / n).resolve().read_bytes()).hexdigest()
                        for n in record["sha256"]}  # fmt: skip
    record["record_sha256"] = _record_digest(record)
    path.write_text(json.dumps(record))


def test_a_map_json_naming_a_file_outside_its_folder_is_refused(tmp_path):
    """map.json's tensor entries must name files of the map's own folder: a '../' path, an
    absolute path and a digest entry naming another folder's file are refused naming the field
    and the path, though every digest matches (recomputed)."""
    import shutil

    smap = SemanticMap(None, "bb", 0.25)
    smap.fuse(*frames(1, 0)[0])
    good = smap.save(tmp_path / "good")
    name = json.loads((good / "map.json").read_text())["tensors"]
    outside = tmp_path / "outside"
    outside.mkdir()
    shutil.copy(good / name, outside / name)
    cases = {
        "parent": lambda r: r.update(
            tensors=f"../outside/{name}", sha256={f"../outside/{name}": ""}
        ),  # fmt: skip
        "absolute": lambda r: r.update(
            tensors=str(outside / name), sha256={str(outside / name): ""}
        ),  # fmt: skip
        "digest": lambda r: r["sha256"].update({f"../outside/{name}": ""}),
    }
    for label, edit in cases.items():
        folder = tmp_path / label
        shutil.copytree(good, folder)
        _rewrite(folder, edit)
        with pytest.raises(IntegrityError) as info:
            SemanticMap.load(folder)
        text = str(info.value)
        field = "sha256=" if label == "digest" else "tensors="
        assert field in text and "outside the map folder" in text, (label, text)
        assert str(folder / "map.json") in text


# ---------------------------------------------------------------- merging
@pytest.mark.parametrize("storage", ["exact", "compact"])
def test_merge_with_identity_equals_one_map_of_both_frame_sets(storage):
    """Two runs' maps merged equal one map of both runs' frames: the same voxels and counts
    exactly; exact means to 1e-12 relative (float64 sums in another order), compact features
    within float16 rounding (cosine >= 0.9999) and colours within one level."""
    settings = {"dim": 8, "basis_rows": 300}
    a_frames, b_frames = frames(3, 1), frames(3, 2)
    one = SemanticMap(None, "bb", 0.1, storage=storage, compact=settings)
    a = SemanticMap(None, "bb", 0.1, storage=storage, compact=settings)
    b = SemanticMap(None, "bb", 0.1, storage=storage, compact=settings)
    for f in a_frames + b_frames:
        one.fuse(*f)
    for f in a_frames:
        a.fuse(*f)
    if storage == "compact":
        b.set_basis(a.basis)  # the second run mapped with the first map's basis
    for f in b_frames:
        b.fuse(*f)
    a.merge(b)
    assert torch.equal(a.indices, one.indices) and torch.equal(a.voxels.counts, one.voxels.counts)
    assert a.frames == one.frames
    if storage == "exact":
        np.testing.assert_allclose(a.voxels.means().numpy(), one.voxels.means().numpy(),
                                   rtol=1e-12, atol=0)  # fmt: skip
        assert torch.equal(a.colours.counts, one.colours.counts)
    else:
        cos = np.sum(unit(a.features()[1].numpy()) * unit(one.features()[1].numpy()), 1)
        assert cos.min() >= 0.9999
    diff = a.mean_colours().int() - one.mean_colours().int()
    assert int(diff.abs().max()) <= 1


def rotation_z(quarter_turns, shift):
    c, s = [(1, 0), (0, 1), (-1, 0), (0, -1)][quarter_turns % 4]
    t = np.eye(4)
    t[:3, :3] = [[c, -s, 0], [s, c, 0], [0, 0, 1]]
    t[:3, 3] = shift
    return t


@pytest.mark.parametrize(("storage", "lattice"), [("exact", "round"), ("exact", "floor"),
                                                   ("compact", "round")])  # fmt: skip
def test_merge_with_a_lattice_transform_equals_mapping_the_transformed_frames(storage, lattice):
    """A second run in its own frame, merged through a quarter turn about the vertical and a
    translation of whole voxels, equals mapping its frames with the transformed poses: the same
    voxels and counts exactly, the features to the storage's rounding. A transform off the
    lattice (10 degrees, a third of a voxel) merges approximately: every point is kept (the
    counts add up) and most voxels land where re-mapping puts them."""
    voxel = 0.25
    settings = {"dim": 8, "basis_rows": 300}
    a_frames, b_frames = frames(2, 3, span=1.0), frames(2, 4, span=1.0)
    t = rotation_z(1, [2 * voxel, -3 * voxel, voxel])
    moved = [(f, d, k, torch.from_numpy(t).float() @ p, c) for f, d, k, p, c in b_frames]

    def mapped(windows, basis=None):
        m = SemanticMap(None, "bb", voxel, lattice=lattice, storage=storage, compact=settings)
        if basis is not None:
            m.set_basis(basis)
        for f in windows:
            m.fuse(*f)
        return m

    a = mapped(a_frames)
    truth = mapped(a_frames + moved, a.basis)
    b = mapped(b_frames, a.basis)
    a.merge(b, t)
    assert torch.equal(a.indices, truth.indices)
    assert torch.equal(a.voxels.counts, truth.voxels.counts)
    cos = np.sum(unit(a.features()[1].numpy()) * unit(truth.features()[1].numpy()), 1)
    assert cos.min() >= (1 - 1e-12 if storage == "exact" else 0.9999)
    angle = np.radians(10)
    off = np.eye(4)
    off[:2, :2] = [[np.cos(angle), -np.sin(angle)], [np.sin(angle), np.cos(angle)]]
    off[:3, 3] = [voxel / 3, 0, 0]
    a2 = mapped(a_frames)
    truth2 = mapped(a_frames + [(f, d, k, torch.from_numpy(off).float() @ p, c)
                                for f, d, k, p, c in b_frames], a2.basis)  # fmt: skip
    a2.merge(mapped(b_frames, a2.basis), off)
    assert int(a2.voxels.counts.sum()) == int(truth2.voxels.counts.sum())
    same = set(map(tuple, a2.indices.tolist())) & set(map(tuple, truth2.indices.tolist()))
    assert len(same) >= 0.5 * len(truth2)


def test_incompatible_maps_are_refused_naming_what_differs():
    """merge refuses, naming each difference: the voxel size, the storage, the basis (by
    SHA-256), the encoder's weights (the digest resireg-map records), the feature dimension."""
    f = frames(1, 5)[0]

    def made(dim=16, **kw):
        meta = kw.pop("meta", None)
        m = SemanticMap(None, "bb", kw.pop("voxel", 0.1), **kw)
        m.fuse(f[0][:, :dim], *f[1:])
        if meta:
            m.meta = meta
        return m

    base = made()
    cases = [
        (made(voxel=0.2), r"voxel_size: 0\.1 here, 0\.2 in the other map"),
        (made(storage="compact", compact={"dim": 4, "basis_rows": 10}), r"storage: 'exact' here"),
        (made(dim=8), r"dim: 16 here, 8 in the other map"),
        (made(meta={"identity": {"weights": "abc"}}), None),
    ]
    for other, pattern in cases:
        if pattern is None:  # only one side records a digest: nothing to compare
            base.meta = {}
            continue
        with pytest.raises(MapError, match=pattern):
            base.merge(other)
    base.meta = {"identity": {"weights": "def"}}
    with pytest.raises(MapError, match=r"encoder weights: def here, abc in the other map"):
        base.merge(made(meta={"identity": {"weights": "abc"}}))
    c1 = made(storage="compact", compact={"dim": 4, "basis_rows": 10})
    c2 = made(storage="compact", compact={"dim": 4, "basis_rows": 10})
    c2b = SemanticMap(None, "bb", 0.1, storage="compact", compact={"dim": 4, "basis_rows": 10})
    c2b.set_basis(torch.linalg.qr(torch.randn(16, 4))[0])
    c2b.fuse(*f)
    with pytest.raises(
        MapError, match=rf"basis_sha256: {c1.basis_sha256} here, {c2b.basis_sha256}"
    ):
        c1.merge(c2b)
    assert c1.merge(c2) is c1 and c1.frames == 4


# ---------------------------------------------------------------- one source per rule
def test_map_settings_are_one_table_and_conf_holds_the_defaults():
    """The node's map rules are the objects of resireg.specs.mapping.MAP_RULES, resireg-map's
    check refuses a value by the same rule, the 3D task's dataset rules take theirs; the
    compact defaults of CompactSettings and SemanticMap's storage default are conf/map.yaml's."""
    import inspect
    from dataclasses import asdict

    import yaml
    from omegaconf import OmegaConf

    from resireg.errors import ConfigError
    from resireg.mapping.compact import CompactSettings
    from resireg.ros2.settings import _MAP_RULES, parameters
    from resireg.specs.mapping import MAP_RULES, compact_defaults
    from resireg_train.checks.map import check_map_config
    from resireg_train.data.specs import DATASET_SPECS

    for key, rule in MAP_RULES.items():
        assert _MAP_RULES[key] is rule, key
    table = parameters()
    assert table["storage"].rule is MAP_RULES["storage"]
    assert table["compact.dim"].rule is MAP_RULES["compact.dim"]
    scannet = DATASET_SPECS["scannet"].rules
    for key in ("voxel_size", "lattice", "points", "storage"):
        assert scannet[key] is MAP_RULES[key], key
    conf = yaml.safe_load((ROOT / "conf" / "map.yaml").read_text())
    assert asdict(CompactSettings()) == conf["compact"] == compact_defaults()
    assert inspect.signature(SemanticMap).parameters["storage"].default == conf["storage"]
    bad = OmegaConf.create({**{k: v for k, v in conf.items() if k != "defaults"},
                            "window": 0, "compact": {**conf["compact"], "dim": 0, "oops": 1}})  # fmt: skip
    with pytest.raises(ConfigError) as info:
        check_map_config(bad)
    text = str(info.value)
    assert "window=0: expected an integer >= 1" in text
    assert "compact.dim=0: expected null or an integer >= 1" in text
    assert "compact.oops: no such setting" in text


def test_resireg_map_merge_writes_a_run_record_and_refuses_other_maps(tmp_path):
    """resireg-map-merge A B --out C (A a map folder, B a resireg-map run folder): C/map equals
    SemanticMap.merge of the two, C/results.json is the run's record (completed, the inputs,
    the result); maps of another voxel size: exit 1, one line naming voxel_size, the record
    failed, no map written."""
    from helpers.run import run

    windows = frames(2, 7)
    for name, part in (("a", windows[:1]), ("b/map", windows[1:])):
        m = SemanticMap(None, "bb", 0.1)
        for f in part:
            m.fuse(*f)
        m.save(tmp_path / name)
    odd = SemanticMap(None, "bb", 0.2)
    odd.fuse(*windows[0])
    odd.save(tmp_path / "odd")
    run("resireg-map-merge", tmp_path / "a", tmp_path / "b", "--out", tmp_path / "c")
    record = json.loads((tmp_path / "c" / "results.json").read_text())
    merged = SemanticMap.load(tmp_path / "c" / "map")
    want = SemanticMap.load(tmp_path / "a").merge(SemanticMap.load(tmp_path / "b" / "map"))
    assert torch.equal(merged.indices, want.indices)
    assert torch.equal(merged.voxels.state()["sums"], want.voxels.state()["sums"])
    assert record["status"] == "completed" and record["map"]["voxels"] == len(want)
    assert [i["folder"] for i in record["inputs"]] == [
        str(tmp_path / "a"),
        str(tmp_path / "b" / "map"),
    ]
    assert record["provenance"]  # the job wrapper's record
    proc = run("resireg-map-merge", tmp_path / "a", tmp_path / "odd", "--out", tmp_path / "d",
               check=False)  # fmt: skip
    assert proc.returncode == 1 and "Traceback" not in proc.stderr
    lines = [x for x in proc.stderr.splitlines() if "voxel_size: 0.1 here, 0.2" in x]
    assert len(lines) == 1, proc.stderr[-2000:]
    failed = json.loads((tmp_path / "d" / "results.json").read_text())
    assert failed["status"] == "failed" and "voxel_size" in failed["error"]
    assert not (tmp_path / "d" / "map").exists()
