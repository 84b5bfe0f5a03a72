"""The 3D semantic-mapping task on the synthetic ScanNet-format room: the reader's frame rules,
ground-truth voxels against the boxes' geometry, oracle and constant encoders through the
engine, the Hydra entry point with a tiny encoder, the 3D prototype/batch sweep and its
report, and the errors naming config keys.

One idea: the 3D task on the one synthetic ScanNet-format room, from its reader to the
report of its sweep; the tests share the room and its reference voxels."""

import json
import re
import shutil
from pathlib import Path

import numpy as np
import pytest
import torch
import torch.nn.functional as F
from PIL import Image

from helpers.paths import TESTS
from helpers.run import run
from resireg.method.variants import build_variants
from resireg.models.interface import DenseEncoder, DenseOutput, InputRule
from resireg.ovss import NYU40_CLASSES, SCANNET_CLASSES
from resireg_train.data.scannet import ScanNetFrames, evaluated_classes, label_lookup
from resireg_train.data.scannet_room import (
    NYU40_COLOURS,
    RAW_LABELS,
    SyntheticRoom,
    write_scene,
)
from resireg_train.evaluation.mapping.engine import MappingEngine

TEST_CONF = TESTS / "conf"
SCENE = "synthetic0000_00"
VOXEL = 0.1
K = len(SCANNET_CLASSES)


@pytest.fixture(scope="module")
def room():
    return SyntheticRoom()


@pytest.fixture(scope="module")
def root(tmp_path_factory, room):
    path = tmp_path_factory.mktemp("scannet")
    write_scene(path, SCENE, room)
    return path


def _frames(root, room, **kw):
    args = {"frame_skip": 0, "image_size": room.image_size, "patch_size": 1, **kw}
    return ScanNetFrames(root, [SCENE], **args)


#: The room's evaluated classes: the label map's NYU40 ids without otherprop, in id order.
ROOM_CLASSES = tuple(sorted({v[2] for v in RAW_LABELS.values()} - {"otherprop"},
                            key=NYU40_CLASSES.index))  # fmt: skip


def _class_of_raw(raw: int) -> int:
    """Evaluated class index of a raw id, from the synthetic table and the NYU40 names."""
    name = NYU40_CLASSES[RAW_LABELS[raw][1] - 1]
    return ROOM_CLASSES.index(name) if name in ROOM_CLASSES else 255


# ----------------------------------------------------------------- test encoders
class _ClassFromColour(DenseEncoder):
    """Oracle: the one-hot of the class whose colour is nearest to each pixel (patch size 1),
    and one-hot text vectors of the class named in each prompt."""

    def __init__(self, constant: int | None = None) -> None:
        super().__init__()
        self.anchor = torch.nn.Parameter(torch.zeros(1))
        self.constant = constant
        nyu_ids = [NYU40_CLASSES.index(c) + 1 for c in SCANNET_CLASSES]
        self.register_buffer("palette", torch.tensor(NYU40_COLOURS[nyu_ids], dtype=torch.float32))

    @property
    def input_rule(self) -> InputRule:
        return InputRule(1, (0.0, 0.0, 0.0), (1.0, 1.0, 1.0))

    def encode(self, images):
        b, _, h, w = images.shape
        if self.constant is not None:
            cls = torch.full((b, h, w), self.constant, dtype=torch.long)
        else:
            rgb = (images * 255).permute(0, 2, 3, 1).reshape(-1, 3)
            dist = torch.cdist(rgb, self.palette)
            cls = dist.argmin(1).reshape(b, h, w)
            far = dist.min(1).values.reshape(b, h, w) > 40  # otherprop's colour: no class
            onehot = F.one_hot(cls, K).float() * (~far)[..., None]
            return DenseOutput(onehot.permute(0, 3, 1, 2), onehot.permute(0, 3, 1, 2), None)
        onehot = F.one_hot(cls, K).float().permute(0, 3, 1, 2)
        return DenseOutput(onehot, onehot, None)

    def encode_text(self, texts):
        out = torch.zeros(len(texts), K)
        for i, text in enumerate(texts):
            hits = [c for c in SCANNET_CLASSES if c in text]
            out[i, SCANNET_CLASSES.index(max(hits, key=len))] = 1.0
        return out


# ------------------------------------------------- independent reference (numpy)
def _reference_gt(root, room, voxel, lattice="floor", exclude=()):
    """Ground-truth voxels recomputed with numpy from the written files: every pixel of the
    kept frames unprojected with K and the pose, votes per voxel with ignored pixels as a class
    (``gt_unlabelled=vote``), argmax; returns {voxel index tuple: class or 255}. Frames
    numbered in ``exclude`` are left out."""
    folder = Path(root) / SCENE
    lookup = np.full(1 << 16, 255)
    for raw in RAW_LABELS:
        lookup[raw] = _class_of_raw(raw)
    k = len(ROOM_CLASSES)
    k_inv = np.linalg.inv(np.loadtxt(folder / "intrinsic" / "intrinsic_depth.txt")[:3, :3])
    votes: dict[tuple, np.ndarray] = {}
    for i in range(room.frames):
        pose = np.loadtxt(folder / "pose" / f"{i}.txt")
        if not np.isfinite(pose).all() or i in exclude:
            continue
        depth = np.asarray(Image.open(folder / "depth" / f"{i}.png")).astype(np.float64) / 1000
        label = lookup[np.asarray(Image.open(folder / "label-filt" / f"{i}.png")).astype(int)]
        v, u = np.nonzero(depth > 0)
        cam = (np.stack([u, v, np.ones_like(u)], 1) @ k_inv.T) * depth[v, u][:, None]
        world = cam @ pose[:3, :3].T + pose[:3, 3]
        cls = np.where(label[v, u] == 255, k, label[v, u])
        op = np.floor if lattice == "floor" else np.rint
        for idx, c in zip(map(tuple, op(world / voxel).astype(int)), cls, strict=True):
            votes.setdefault(idx, np.zeros(k + 1, int))[c] += 1
    return {idx: (int(np.argmax(n)) if np.argmax(n) < k else 255) for idx, n in votes.items()}


def _surface_distance(p, lo, hi):
    """Distance from points ``p [N, 3]`` to the surface of the box ``[lo, hi]``."""
    lo, hi = np.asarray(lo), np.asarray(hi)
    outside = np.linalg.norm(np.maximum(np.maximum(lo - p, p - hi), 0), axis=1)
    inside = np.minimum(p - lo, hi - p).min(axis=1)
    return np.where(outside > 0, outside, np.maximum(inside, 0))


# ---------------------------------------------------------------------- reader
def test_frame_rules_skip_drop_and_scaled_intrinsics(root, room, tmp_path):
    """Frame skip keeps i % (s + 1) == 0 (RayFronts), the -inf pose is dropped and named,
    intrinsics follow the resize, and an unreadable frame is skipped, not fatal."""
    frames = _frames(root, room, frame_skip=1)
    assert [f.index for f in frames.frames] == [0, 4, 6, 8]  # 2 has the -inf pose
    assert len(frames.dropped) == 1 and frames.dropped[0].reason == "non-finite pose"
    assert frames.dropped[0].file.endswith("pose/2.txt")
    assert [f.index for f in _frames(root, room, frame_skip=0).frames] == [
        0,
        1,
        3,
        4,
        5,
        6,
        7,
        8,
        9,
    ]
    assert [f.index for f in _frames(root, room, frame_skip=3).frames] == [0, 4, 8]

    # image_size 96 x 128 (x2) and ground truth at 24 x 32 (x0.5): K by hand, pixel centres
    # at integers (half_pixel: c' = (c + 0.5) s - 0.5) and RayFronts' rule (multiply: c' = c s)
    big = _frames(root, room, image_size=(96, 128), gt_resolution=(24, 32),
                  intrinsics="half_pixel")  # fmt: skip
    item = big[0]
    f, (h, w) = room.focal, room.image_size
    cx, cy = (w - 1) / 2, (h - 1) / 2
    expect = np.array(
        [[2 * f, 0, (cx + 0.5) * 2 - 0.5], [0, 2 * f, (cy + 0.5) * 2 - 0.5], [0, 0, 1]]
    )
    np.testing.assert_allclose(item["intrinsics"].numpy(), expect, rtol=1e-6)
    half = np.array([[f / 2, 0, (cx + 0.5) / 2 - 0.5], [0, f / 2, (cy + 0.5) / 2 - 0.5], [0, 0, 1]])
    np.testing.assert_allclose(item["gt_intrinsics"].numpy(), half, rtol=1e-6)
    multiplied = _frames(root, room, image_size=(96, 128), gt_resolution=(24, 32))[0]
    np.testing.assert_allclose(
        multiplied["intrinsics"].numpy(),
        [[2 * f, 0, 2 * cx], [0, 2 * f, 2 * cy], [0, 0, 1]],
        rtol=1e-6,
    )
    np.testing.assert_allclose(
        multiplied["gt_intrinsics"].numpy(),
        [[f / 2, 0, cx / 2], [0, f / 2, cy / 2], [0, 0, 1]],
        rtol=1e-6,
    )
    assert item["image"].shape == (3, 96, 128) and item["depth"].shape == (96, 128)
    assert item["gt_label"].shape == (24, 32) and item["gt_depth"].shape == (24, 32)
    depth = np.asarray(Image.open(root / SCENE / "depth" / "0.png")) / 1000
    np.testing.assert_allclose(item["depth"].numpy(), np.repeat(np.repeat(depth, 2, 0), 2, 1))
    np.testing.assert_allclose(item["gt_depth"].numpy(), depth[1::2, 1::2])

    # a truncated depth, colour or label file, a deleted one: each frame is skipped naming
    # the file that failed, the others load (issue 22, item 7)
    copy = tmp_path / "copy"
    shutil.copytree(root, copy)
    for name in ("depth/3.png", "color/5.jpg", "label-filt/7.png"):
        data = (copy / SCENE / name).read_bytes()
        (copy / SCENE / name).write_bytes(data[: len(data) // 3])
    (copy / SCENE / "depth" / "8.png").unlink()
    broken = _frames(copy, room)
    bad = {x.file.split(f"{SCENE}/")[1]: x.reason for x in (broken[i] for i in range(len(broken)))
           if not isinstance(x, dict)}  # fmt: skip
    assert set(bad) == {"depth/3.png", "color/5.jpg", "label-filt/7.png", "depth/8.png"}
    assert bad["depth/3.png"].startswith("unreadable depth: ")
    assert bad["color/5.jpg"].startswith("unreadable colour: ")
    assert bad["label-filt/7.png"].startswith("unreadable label: ")
    assert bad["depth/8.png"] == "missing depth file"


def test_label_mapping_raw_to_nyu40_to_37_classes():
    """Raw id -> nyu40id (tsv) -> the evaluated classes; 0, unknown ids and otherprop -> 255.
    With every NYU40 id in the label map (ScanNet's tsv) the classes are RADSeg's 37, named by
    the tsv's nyu40class column (its spelling kept) or by NYU40; RayFronts' default ignore list
    leaves 32."""
    raw = {1: 1, 3: 2, 36: 22, 35: 40, 99: 38, 7: 3, 50: 39, **{100 + n: n for n in range(1, 41)}}
    tsv = {n: name for n, name in enumerate(NYU40_CLASSES, 1)}
    tsv[24] = "refridgerator"
    ids, names = evaluated_classes(raw, tsv)
    assert names == tuple(c if c != "refrigerator" else "refridgerator" for c in SCANNET_CLASSES)
    assert evaluated_classes(raw, tsv, "nyu40")[1] == SCANNET_CLASSES and len(ids) == 37
    table = label_lookup(raw, ids)
    assert table[1] == SCANNET_CLASSES.index("wall") == 0
    assert table[3] == 1 and table[36] == SCANNET_CLASSES.index("ceiling") == 21
    assert table[7] == 2
    assert table[35] == table[99] == table[50] == table[0] == table[1234] == 255
    assert len(SCANNET_CLASSES) == 37 and SCANNET_CLASSES[-1] == "bag"
    rayfronts = ["otherprop", "otherstructure", "otherfurniture", "wall", "floor", "ceiling",
                 "door", "window"]  # fmt: skip
    ids32, names32 = evaluated_classes(raw, tsv, "nyu40", rayfronts)
    assert len(ids32) == 32 and not {"wall", "floor", "ceiling", "door", "window"} & set(names32)
    assert label_lookup(raw, ids32)[1] == 255 and label_lookup(raw, ids32)[7] == 0  # cabinet
    with pytest.raises(ValueError, match=r"dataset\.classes_to_ignore=\['sky'\]: \['sky'\]"):
        evaluated_classes(raw, tsv, "nyu40", ["sky"])


def test_missing_root_scene_and_label_map_name_the_key(root, room, tmp_path):
    with pytest.raises(FileNotFoundError, match=r"dataset\.path='/nonexistent/scannet'"):
        ScanNetFrames("/nonexistent/scannet", [SCENE])
    with pytest.raises(FileNotFoundError, match=r"dataset\.scenes: \['scene0050_00'\] not found"):
        ScanNetFrames(root, ["scene0050_00"])
    with pytest.raises(FileNotFoundError, match=r"dataset\.label_map: no label map"):
        ScanNetFrames(root, [SCENE], label_map=tmp_path / "none.tsv")


def test_too_many_prototypes_for_a_batch_name_the_variant_and_the_batch_of_frames(root, room):
    frames = _frames(root, room)
    h, w = frames.grid_size()
    n = 4 * h * w * 4 + 1  # one more than 4 frames upsampled by s = 2 have points
    engine = MappingEngine(frames, batch_size=4, voxel_size=VOXEL)
    with pytest.raises(ValueError) as err:
        engine.check_variants(build_variants([f"full@n_prototypes:{n}"]), "variants")
    assert str(err.value).startswith(f"variants.full@n_prototypes:{n}: n_prototypes={n} exceeds")
    tail = rf"; dataset '{frames.name}' with batch_size=4 has a batch of \d frames of {h} x {w} px$"
    assert re.search(tail, str(err.value)), str(err.value)


# ---------------------------------------------------------------- ground truth
def test_ground_truth_voxels_match_numpy_and_the_box_geometry(root, room):
    """The engine's ground-truth voxels equal a numpy recomputation from the files, and every
    voxel's label is the class of a box surface within reach of its centre (the only one
    where a single class is in reach)."""
    frames = _frames(root, room)
    assert frames.classes == ROOM_CLASSES
    engine = MappingEngine(frames, batch_size=4, voxel_size=VOXEL, gt_unlabelled="vote",
                       lattice="floor")  # fmt: skip
    state = engine._start_scene(0, {}, torch.device("cpu"))
    for batch in engine.loader():
        engine._map_batch(_ClassFromColour(), batch, {}, state, lambda s: _null())
    centres, labels = state["gt"].labels()
    labels = torch.where(labels >= len(ROOM_CLASSES), 255, labels)
    got = {tuple(i): int(c) for i, c in zip(state["gt"].indices.tolist(), labels, strict=True)}
    reference = _reference_gt(root, room, VOXEL)
    assert got == reference

    scored = labels != 255
    p = centres[scored].double().numpy()
    reach = VOXEL * np.sqrt(3) / 2 + 1e-3  # half the voxel diagonal (+ mm depth rounding)
    near = np.stack([_surface_distance(p, b.lo, b.hi) <= reach for b in room.boxes], 1)
    classes = np.array([_class_of_raw(b.raw_id) for b in room.boxes])
    single = 0
    for row, label in zip(near, labels[scored].numpy(), strict=True):
        in_reach = set(classes[row].tolist())
        assert label in in_reach
        if len(in_reach) == 1:
            single += 1
            assert label == next(iter(in_reach))
    assert single > 0.5 * len(p)


class _null:
    def __enter__(self):
        return self

    def __exit__(self, *a):
        return False


# ---------------------------------------------------------------------- engine
def test_oracle_features_give_miou_one_and_constant_features_the_hand_value(root, room):
    frames = _frames(root, room)
    variants = build_variants(["bb"])
    engine = MappingEngine(frames, batch_size=3, voxel_size=VOXEL)
    oracle = engine.run(_ClassFromColour(), variants)
    scores = oracle.scores()
    prefix = "val/scannet3d/scannet"
    for name in ("miou", "fmiou", "acc", "pooled_miou", "pooled_fmiou", "pooled_acc"):
        assert scores[f"{prefix}/{name}_bb"] == 1.0
    assert oracle.frames == {SCENE: 9} and len(oracle.dropped_samples) == 1
    bf16 = engine.run(_ClassFromColour(), variants, precision="bf16").scores()
    assert bf16 == scores  # one-hot features are exact in bf16; the geometry runs in fp32/fp64

    # constant "floor" (vote ground truth, floor lattice: the numpy reference above):
    # IoU_floor = G_floor / sum G, the other present classes 0; mIoU over the present classes
    legacy = MappingEngine(frames, batch_size=3, voxel_size=VOXEL, gt_unlabelled="vote",
                         lattice="floor")  # fmt: skip
    gt = np.array([c for c in _reference_gt(root, room, VOXEL).values() if c != 255])
    hist = np.bincount(gt, minlength=len(ROOM_CLASSES))
    floor = SCANNET_CLASSES.index("floor")  # the oracle's feature index of "floor"
    iou = hist[ROOM_CLASSES.index("floor")] / hist.sum()
    constant = legacy.run(_ClassFromColour(constant=floor), variants).scores()
    assert constant[f"{prefix}/miou_bb"] == pytest.approx(iou / (hist > 0).sum())
    assert constant[f"{prefix}/fmiou_bb"] == pytest.approx(iou * iou)
    assert constant[f"{prefix}/acc_bb"] == pytest.approx(iou)


class _NaNOnCall(_ClassFromColour):
    """The oracle, whose ``call``-th ``encode`` (0-based) holds one NaN in its language."""

    def __init__(self, call: int) -> None:
        super().__init__()
        self.call, self.calls = call, 0

    def encode(self, images):
        out = super().encode(images)
        self.calls += 1
        if self.calls - 1 == self.call:
            language = out.language.clone()
            language[0, 0, 0, 0] = float("nan")
            out = out._replace(language=language)
        return out


def test_a_non_finite_encoder_batch_is_skipped_counted_and_not_fused(root, room, caplog, tmp_path):
    """The second batch's output holds a NaN: its 3 frames are neither fused nor counted in
    the ground truth, each is a skipped sample naming the reason (in the record and the log),
    and the map is that of the other 6 frames: the scored ground-truth voxels are the numpy
    reference's without those frames, and the oracle still scores 1. Before the check the
    batch was fused (a NaN voxel feature) and counted as mapped."""
    from resireg_train.evaluation.mapping.task import ScanNet3DTask

    frames = _frames(root, room)
    variants = build_variants(["bb", "full"], {"full": {"n_prototypes": 4}})
    engine = MappingEngine(frames, batch_size=3, voxel_size=VOXEL, gt_unlabelled="vote",
                       lattice="floor")  # fmt: skip
    poisoned = frames.batches(3)[1]
    result = engine.run(_NaNOnCall(1), variants)
    assert result.frames == {SCENE: 6}
    names = [frames.describe(i) for i in poisoned]
    assert [s.file for s in result.skipped_samples] == names
    assert all("encoder output language holds 1 non-finite" in s.reason
               for s in result.skipped_samples)  # fmt: skip
    numbers = {int(Path(n).stem) for n in names}
    reference = _reference_gt(root, room, VOXEL, exclude=numbers)
    assert result.voxels[SCENE] == sum(c != 255 for c in reference.values())
    assert result.voxels[SCENE] < sum(c != 255 for c in _reference_gt(root, room, VOXEL).values())
    assert result.scores()["val/scannet3d/scannet/miou_bb"] == 1.0
    task = ScanNet3DTask.__new__(ScanNet3DTask)  # results() needs out and data
    task.dataset, task.out = frames, tmp_path
    with caplog.at_level("WARNING"):
        record = task.results(result)
    assert record["skipped"] == 3 and record["frames"] == {SCENE: 6}
    assert [s["file"] for s in record["skipped_samples"]][-3:] == names
    assert f"{names[0]}: encoder output language holds" in caplog.text


# ------------------------------------------------------------ Hydra entry point
def job_of(sweep, encoder):
    """The job folder of a sweep whose results name ``encoder``."""
    for job in sweep.iterdir():
        if (job / "results.json").is_file():
            if json.loads((job / "results.json").read_text())["encoder"]["name"] == encoder:
                return job
    raise AssertionError(f"no job of {encoder} in {sweep}")


def _eval_args(root, *extra, conf=(TEST_CONF,)):
    searchpath = ",".join(f"file://{c}" for c in conf)
    return ("task=scannet3d", "dataset=scannet_synthetic", f"dataset.path={root}",
            "encoder=tiny_vlm", "num_workers=0", f"hydra.searchpath=[{searchpath}]",
            *extra)  # fmt: skip


@pytest.mark.slow
def test_prototype_batch_3d_sweep_and_report(root, tiny_export, tmp_path):
    """`sweep=prototype_batch_3d` as a real multirun (2 batch sizes x 2 prototype counts, the
    sweep's voxel 0.2 m and 228 x 308 ground truth; every frame kept so batch sizes differ),
    then the report (`resireg-report`'s function): heatmap, and a heuristic through the best
    count per batch size read from the jobs' results.json (the tiny random encoder scores
    0 everywhere here: the values are checked in the next test)."""
    logs = tmp_path / "logs"
    run("resireg-eval", *_eval_args(root, "sweep=prototype_batch_3d", "batch_size=2,4",
        "variants=[full@n_prototypes:4,full@n_prototypes:8]", "dataset.frame_skip=0",
        f"model_path={tiny_export}", f"paths.log_dir={logs}"))  # fmt: skip
    (sweep,) = (logs / "prototype_batch_3d" / "multirun").iterdir()
    from resireg_train.report import report  # the console script runs in the Table 2 test

    files = report(sweep)
    assert files["heatmap"] == sweep / "heatmap.png" and files["heatmap"].stat().st_size > 0
    scores = {}
    for job in sweep.iterdir():
        if (job / "results.json").is_file():
            r = json.loads((job / "results.json").read_text())
            assert r["status"] == "completed"
            assert r["params"]["dataset"]["voxel_size"] == 0.2
            assert r["params"]["dataset"]["gt_resolution"] == [228, 308]
            for n in (4, 8):
                key = f"val/scannet3d/scannet_synthetic/miou_full@n_prototypes:{n}"
                scores[(r["params"]["batch_size"], n)] = r["final"][key]
    assert sorted(scores) == [(2, 4), (2, 8), (4, 4), (4, 8)]
    best = {b: max((4, 8), key=lambda n, b=b: (scores[(b, n)], -n)) for b in (2, 4)}
    slope, intercept = np.polyfit(np.log([2, 4]), [best[2], best[4]], 1)
    fitted = json.loads((sweep / "prototype_heuristic.json").read_text())
    assert fitted["slope"] == pytest.approx(slope, abs=1e-9)
    assert fitted["intercept"] == pytest.approx(intercept, abs=1e-9)
    summary = (sweep / "summary.md").read_text()
    assert "val/scannet3d/scannet_synthetic/miou_full: batch size x prototypes" in summary


@pytest.mark.slow
def test_table2_sweep_end_to_end_results_and_report(root, room, tiny_export, tmp_path):
    """`resireg-eval sweep=table2` (task=scannet3d through the console script) over two tiny
    encoders (the tiny export and one of another seed, under a test encoder config), BB and
    Full. Each job's results.json holds the scores, per-scene and per-class values, frame
    counts with the dropped frame named, the parameter count and stage timings; the tiny
    export's scores equal the engine's run in-process on the same settings; the report's
    Table 2 shows model, parameters, mIoU and f-mIoU as the results hold them (x100).
    (CLIP's text tower is too slow for a test here: 37 classes x 80 prompts.)"""
    from helpers.tiny import TINY_BACKBONE, TINY_HEAD, TINY_TEXT
    from resireg.models import ResiregVLM, count_parameters

    torch.manual_seed(1)
    other = tmp_path / "export_b"
    ResiregVLM.build(TINY_BACKBONE, TINY_HEAD, TINY_TEXT).save_pretrained(other)
    conf = tmp_path / "conf" / "encoder"
    conf.mkdir(parents=True)
    (conf / "tiny_vlm_b.yaml").write_text(
        f"name: tiny_vlm_b\nkind: resireg_vlm\nthird_party: true\npath: {other}\n"
    )
    logs = tmp_path / "logs"
    run("resireg-eval", *_eval_args(root, "sweep=table2", "encoder=tiny_vlm,tiny_vlm_b",
        "batch_size=3", "variants=[bb,full]", "full.n_prototypes=8", f"model_path={tiny_export}",
        f"paths.log_dir={logs}", conf=(TEST_CONF, tmp_path / "conf")))  # fmt: skip
    (sweep,) = (logs / "table2" / "multirun").iterdir()
    results = {}
    for job in sweep.iterdir():
        if (job / "results.json").is_file():
            r = json.loads((job / "results.json").read_text())
            results[r["encoder"]["name"]] = r
    assert set(results) == {"tiny_vlm", "tiny_vlm_b"}
    r = results["tiny_vlm"]
    assert r["status"] == "completed" and r["params"]["task"] == "scannet3d"
    assert r["frames"] == {SCENE: 9} and r["images"] == 9 and r["frames_dropped"] == 1
    assert r["skipped"] == 0 and r["skipped_samples"][0]["file"].endswith(f"{SCENE}/pose/2.txt")
    prefix = "val/scannet3d/scannet_synthetic"
    assert set(r["final"]) == {
        f"{prefix}/{p}{m}_{v}" for p in ("", "pooled_") for m in ("miou", "fmiou", "acc")
        for v in ("bb", "full")
    }  # fmt: skip
    assert set(r["per_class_iou"]["full"]) == set(ROOM_CLASSES)
    assert r["protocol"]["name"] == "rayfronts_semseg_eval"
    assert r["protocol"]["settings"]["voxel_size"] == 0.1
    assert r["protocol"]["settings"]["gt_unlabelled"] == "rayfronts"
    summary = (job_of(sweep, "tiny_vlm") / r["per_scene_csv"]["full"] / "summary.csv").read_text()
    assert summary.splitlines()[0] == "scene_name,miou,fmiou,acc,gt_voxels"
    assert summary.splitlines()[1].startswith(f"{SCENE},")
    assert {"encoder", "fusion", "ground_truth", "metric", "reconstruction/full"} <= set(
        r["seconds"]
    )
    model = ResiregVLM.from_pretrained(tiny_export)
    assert r["encoder"]["parameters"] == count_parameters(model)
    frames = ScanNetFrames(root, [SCENE], frame_skip=0, image_size=room.image_size,
                           patch_size=model.input_rule.patch_size, name="scannet_synthetic")  # fmt: skip
    variants = build_variants(["bb", "full"], {"full": {"n_prototypes": 8, "n_components": None}})
    engine = MappingEngine(frames, batch_size=3, voxel_size=0.1).run(model, variants).scores()
    assert engine == pytest.approx(r["final"], abs=1e-6)
    scene = r["per_scene"][SCENE]["scores"]  # one scene: its scores are the overall ones
    assert scene["full"]["miou"] == pytest.approx(engine[f"{prefix}/miou_full"])
    assert scene["full"]["miou"] == pytest.approx(engine[f"{prefix}/pooled_miou_full"])

    proc = run("resireg-report", sweep)
    assert "table2_md" in proc.stdout
    import pandas as pd

    table = pd.read_csv(sweep / "table2.csv").set_index(["encoder", "variant"])
    assert sorted(table.index) == [
        (e, v) for e in ("tiny_vlm", "tiny_vlm_b") for v in ("bb", "full")
    ]
    for name, r in results.items():
        for variant, method in (("bb", "BB"), ("full", "Full")):
            row = table.loc[(name, variant)]
            assert row["model"] == f"{name} + {method}"
            assert row["parameters (M)"] == round(r["encoder"]["parameters"] / 1e6, 1)
            for key, column in (("miou", "mIoU"), ("fmiou", "f-mIoU"),
                                ("pooled_miou", "mIoU (pooled)"),
                                ("pooled_fmiou", "f-mIoU (pooled)")):  # fmt: skip
                value = r["final"][f"{prefix}/{key}_{variant}"]
                assert row[f"scannet_synthetic {column}"] == pytest.approx(100 * value)
    table2 = (sweep / "table2.md").read_text()
    assert "| tiny_vlm_b + Full" in table2
    assert "Protocol: rayfronts_semseg_eval: frame_skip=0, image_size=[48, 64]" in table2


# --------------------------------------------------------------------- configs
def test_3d_sweeps_are_the_papers_settings_and_bad_values_name_the_key():
    """prototype_batch_3d: RADSeg, 7 batch sizes x 10 prototype counts as configurations,
    components tied, frame skip 20, voxel 0.2 m, ground truth 228 x 308; table2: every
    encoder config x Full on ScanNet. Bad 3D values are errors naming key and value."""
    from hydra import compose, initialize_config_dir

    from resireg.errors import ConfigError
    from resireg_train.checks.eval import validate_eval
    from resireg_train.config.paths import CONFIG_DIR

    with initialize_config_dir(str(CONFIG_DIR), version_base="1.3"):
        ablation = compose("eval", ["sweep=prototype_batch_3d"], return_hydra_config=True)
        table2 = compose("eval", ["sweep=table2", "model_path=x"], return_hydra_config=True)
        bad = compose("eval", ["task=scannet3d", "dataset=scannet", "encoder=radseg",
                               "dataset.frame_skip=-1", "dataset.voxel_size=0",
                               "dataset.image_size=[640]", "dataset.gt_unlabelled=keep"])  # fmt: skip
        mismatch = compose("eval", ["task=scannet3d", "encoder=radseg"])
        plain = compose("eval", ["sweep=prototype_batch_3d"])
        ovss = compose("eval", ["dataset=scannet", "encoder=radseg"])
    assert ablation.task == "scannet3d" and ablation.encoder.kind == "radseg"
    assert ablation.dataset.kind == "scannet" and ablation.full.n_components is None
    assert [int(b) for b in ablation.hydra.sweeper.params.batch_size.split(",")] == [
        2, 4, 6, 8, 16, 24, 32,
    ]  # fmt: skip
    assert list(ablation.variants) == [f"full@n_prototypes:{n}" for n in range(24, 133, 12)]
    assert ablation.dataset.frame_skip == 20 and ablation.dataset.voxel_size == 0.2
    assert list(ablation.dataset.gt_resolution) == [228, 308]
    assert list(ablation.dataset.image_size) == [640, 864] and ablation.dataset.short_side is None
    validate_eval(plain)
    names = sorted(p.stem for p in (CONFIG_DIR / "encoder").glob("*.yaml"))
    assert sorted(table2.hydra.sweeper.params.encoder.split(",")) == names
    assert table2.task == "scannet3d" and list(table2.variants) == ["full"]
    assert table2.dataset.frame_skip == 10 and table2.dataset.voxel_size == 0.05
    assert list(table2.dataset.scenes) == [
        "scene0050_00", "scene0050_01", "scene0050_02", "scene0231_00", "scene0231_01",
        "scene0231_02", "scene0378_00", "scene0378_01", "scene0378_02", "scene0518_00",
        "scene0011_00", "scene0011_01",
    ]  # fmt: skip
    with pytest.raises(ConfigError) as info:
        validate_eval(bad)
    for text in ("dataset.frame_skip=-1", "dataset.voxel_size=0", "dataset.image_size=[640]",
                 "dataset.gt_unlabelled='keep'"):  # fmt: skip
        assert text in str(info.value)
    with pytest.raises(
        ConfigError,
        match=r"task='scannet3d': dataset\.kind='ade20k' is scored by task=ovss.*"
        r"choose a dataset of task=scannet3d \(.*dataset=scannet or",
    ):
        validate_eval(mismatch)
    with pytest.raises(ConfigError, match=r"task='ovss': dataset\.kind='scannet'"):
        validate_eval(ovss)


def test_report_of_3d_jobs_fits_the_heuristic_from_the_3d_metric(tmp_path):
    """Three 3D jobs (batch sizes 2, 4, 8) with chosen scores per prototype configuration:
    the report's grid holds them, and the heuristic is the least-squares line through the
    best count per batch size (numpy polyfit); the 2D and 3D sweeps share the code."""
    import yaml

    from resireg_train.report import report

    prefix = "val/scannet3d/scannet/miou_full"
    counts = (24, 36, 48)
    chosen = {2: (0.30, 0.20, 0.10), 4: (0.20, 0.35, 0.30), 8: (0.10, 0.20, 0.40)}
    sweep = tmp_path / "sweep"
    for n, (batch, values) in enumerate(chosen.items()):
        job = sweep / f"{n}_batch_size={batch}"
        (job / ".hydra").mkdir(parents=True)
        (job / ".hydra" / "overrides.yaml").write_text(yaml.safe_dump([f"batch_size={batch}"]))
        variants = [f"full@n_prototypes:{c}" for c in counts]
        final = {f"{prefix}@n_prototypes:{c}": v for c, v in zip(counts, values, strict=True)}
        results = {"status": "completed", "final": final,
                   "params": {"task": "scannet3d", "variants": variants},
                   "protocol": {"name": "rayfronts_semseg_eval",
                                "settings": {"voxel_size": 0.2, "knn": 1}}}  # fmt: skip
        (job / "results.json").write_text(json.dumps(results))
    files = report(sweep)
    assert files["heatmap"].stat().st_size > 0
    best = {b: counts[int(np.argmax(v))] for b, v in chosen.items()}
    assert best == {2: 24, 4: 36, 8: 48}
    slope, intercept = np.polyfit(np.log(list(best)), list(best.values()), 1)
    fitted = json.loads(files["heuristic"].read_text())
    assert fitted["slope"] == pytest.approx(slope) and fitted["intercept"] == pytest.approx(
        intercept
    )
    assert (fitted["min_prototypes"], fitted["max_prototypes"]) == (24, 48)
    summary = files["md"].read_text()
    assert f"## {prefix}: batch size x prototypes" in summary
    assert "|            4 | 0.2000 | 0.3500 | 0.3000 |" in summary
    assert "Protocol: rayfronts_semseg_eval: voxel_size=0.2, knn=1" in summary


# ------------------------------------------------------- a newcomer's 3D run (issue 22, 16)
@pytest.mark.slow
def test_a_smoke_trained_model_scores_above_chance_on_the_smoke_room(tmp_path):
    """`resireg-train experiment=smoke` (3 epochs, no validation callback), then the README's
    3D commands: the synthetic room as the command line writes it by default (the smoke world:
    the classes and textures the smoke model learned) scored with the export. Accuracy is
    over twice chance (8 classes: 1/8), and every class the model learned is in the vocabulary
    the room's label map gives."""
    import sys

    from resireg_train.data.synthetic import SYNTHETIC_CLASSES

    logs = tmp_path / "logs"
    run("resireg-train", "experiment=smoke", "trainer.max_epochs=3", "~callbacks.resireg_eval",
        f"paths.log_dir={logs}")  # fmt: skip
    (export,) = logs.glob("smoke/*/export")
    room = tmp_path / "scannet_synthetic"
    run(sys.executable, "-m", "resireg_train.data.scannet_room", room)
    run("resireg-eval", f"model_path={export}", "task=scannet3d", "dataset=scannet_synthetic",
        f"dataset.path={room}", "variants=[bb,full]", "batch_size=4", "num_workers=0",
        f"paths.log_dir={logs}")  # fmt: skip
    (record,) = logs.glob("eval/*/results.json")
    r = json.loads(record.read_text())
    assert set(r["per_class_iou"]["full"]) <= set(SYNTHETIC_CLASSES)
    assert len(r["per_class_iou"]["full"]) == 8
    prefix = "val/scannet3d/scannet_synthetic"
    for variant in ("bb", "full"):
        assert r["final"][f"{prefix}/acc_{variant}"] > 2 / 8
        assert r["final"][f"{prefix}/miou_{variant}"] > 0.1
