"""The 3D protocol (docs/protocol.md section 4) against RayFronts' own evaluation, and what each
option changes.

The reference below is written from RayFronts' code as read at RayFronts/RayFronts@cfa0e6a
(``scripts/semseg_eval.py``: ``compute_semseg_gt``, ``compute_semseg_metrics``;
``scripts/eval_utils.py``: ``compute_semseg_preds``, ``eval_gt_pred``,
``align_labels_with_knn``; ``rayfronts/geometry3d.py``: ``depth_to_pointcloud``,
``pointcloud_to_sparse_voxels``; ``rayfronts/datasets/scannet.py``: ``ScanNetDataset``;
``rayfronts/datasets/base.py``: ``_init_semseg_mappings``; ``rayfronts/image_encoders/base.py``:
``encode_labels``), with numpy / torch / scikit-learn only; it imports nothing of the project
for the parts it checks (reading, ground-truth lifting, transfer, metric). Two departures, both
so that float rounding of the inputs does not enter the comparison: points are unprojected in
float64 and rounded to float32 (RayFronts computes them in float32 on the GPU; the project in
float64), and the voxel index divides in float64. The generated scenes have no lost-tracking
pose (RayFronts unprojects such frames to non-finite points; the project drops them).

One idea: the 3D protocol checked against one reference, RayFronts' evaluation re-written
here; the reference and the cases that compare with it are read together, so they stay in one
file."""

from __future__ import annotations

import csv
import json
import math
from pathlib import Path

import numpy as np
import pytest
import torch
import torch.nn.functional as F
import yaml
from PIL import Image
from sklearn.neighbors import BallTree
from test_scannet import _ClassFromColour

from helpers.paths import ROOT
from resireg.mapping import (
    VoxelMap,
    classify,
    patch_points,
    pixel_pairs,
    transfer_labels,
    transfer_labels_by_voxel,
)
from resireg.mapping import metric as metric_module
from resireg.method.variants import build_variants
from resireg.ovss import NYU40_CLASSES, SCANNET_CLASSES
from resireg_train.data.scannet import (
    CLASS_NAMES,
    INTRINSICS,
    RESIZES,
    ScanNetFrames,
    resize_nearest,
)
from resireg_train.data.scannet_room import Box, SyntheticRoom, write_scene
from resireg_train.evaluation.mapping.engine import (
    GT_RULES,
    POINTS,
    MappingEngine,
    MappingSettings,
    ground_truth_labels,
)

CONF = ROOT / "conf" / "dataset"
IMAGE = (64, 86)  # the rooms' 48 x 64 frames resized by 4/3, as ScanNet's 480 x 640 to 640 x 864


# ------------------------------------------------------------ RayFronts, re-implemented
def rf_semseg_mappings(tsv: Path, black_list):
    """``_init_semseg_mappings(cat_id_to_name, (), black_list)`` of ScanNetDataset: returns
    (raw -> nyu40 dict with 0 -> 0, cat_id_to_index table, index -> name list)."""
    with tsv.open() as f:
        rows = list(csv.DictReader(f, delimiter="\t"))
    scannet_to_nyu40 = {int(r["id"]): int(r["nyu40id"]) for r in rows}
    scannet_to_nyu40[0] = 0
    cin = {int(r["nyu40id"]): r["nyu40class"] for r in rows}
    cin[0] = ""
    index_to_id = sorted(i for i, name in cin.items() if name not in black_list)
    id_to_index = np.zeros(max(cin) + 1, dtype=np.int64)
    id_to_index[index_to_id] = np.arange(len(index_to_id))
    return scannet_to_nyu40, id_to_index, [cin[i] for i in index_to_id]


def rf_frames(root: Path, scene: str, size, frame_skip, black_list):
    """ScanNetDataset.__iter__ with rgb_resolution = depth_resolution = ``size``: depth and
    labels resized with nearest-exact, intrinsics rows scaled by the size ratios."""
    to_nyu, id_to_index, names = rf_semseg_mappings(root / "scannetv2-labels.combined.tsv",
                                                    black_list)  # fmt: skip
    folder = root / scene
    k = torch.tensor(np.loadtxt(folder / "intrinsic" / "intrinsic_depth.txt")[:3, :3])
    n = len(list((folder / "color").iterdir()))
    frames = []
    for f in range(n):
        if frame_skip > 0 and f % (frame_skip + 1) != 0:
            continue
        depth = torch.from_numpy(np.asarray(Image.open(folder / "depth" / f"{f}.png")).astype(
            np.float32))[None].float() / 1e3  # fmt: skip
        h0, w0 = depth.shape[-2:]
        kk = k.clone()
        kk[0, :] *= size[1] / w0
        kk[1, :] *= size[0] / h0
        depth = F.interpolate(depth[None], size=size, mode="nearest-exact")[0]
        img = np.asarray(Image.open(folder / "label-filt" / f"{f}.png")).astype(np.int64)
        semseg = torch.from_numpy(id_to_index[np.vectorize(to_nyu.get)(img)])[None]
        semseg = F.interpolate(semseg[None].float(), size=size, mode="nearest-exact")[0].long()
        pose = torch.tensor(np.loadtxt(folder / "pose" / f"{f}.txt"))
        frames.append((depth, semseg, pose, kk))
    return frames, names


def rf_depth_to_pointcloud(depth, pose, k):
    """depth_to_pointcloud of one frame: every valid pixel (finite, > 0) of ``depth`` [1, H,
    W] through ``pose @ [[K^-1, 0], [0, 1]]``; float64, then float32 (module docstring)."""
    _, h, w = depth.shape
    xi, yi = torch.meshgrid(torch.arange(w), torch.arange(h), indexing="xy")
    plane = torch.stack([xi.flatten(), yi.flatten(), torch.ones(h * w)], -1).double()
    plane = depth.reshape(h * w, 1).double() * plane
    unproj = pose.double() @ torch.block_diag(torch.linalg.inv(k.double()), torch.ones(1, 1))
    world = plane @ unproj[:3, :3].T + unproj[:3, 3]
    valid = torch.isfinite(depth.flatten()) & (depth.flatten() > 0)
    return world[valid].float(), valid


def rf_voxelize(xyz, vox, feat, aggregation):
    """pointcloud_to_sparse_voxels: index round(xyz / vox) (float64 division here), unique
    rows, scatter ``aggregation`` of the features; centres float32(index) * vox."""
    idx = torch.round(xyz.double() / vox).long()
    uniq, inverse, counts = torch.unique(idx, return_inverse=True, return_counts=True, dim=0)
    out = torch.zeros(len(uniq), feat.shape[1], dtype=feat.dtype).index_add_(0, inverse, feat)
    if aggregation == "mean":
        out = out / counts[:, None].to(feat.dtype)
    return uniq.float() * vox, out, uniq


def rf_compute_semseg_preds(map_feats, text_embeds, prompt_denoising_thresh,
                            prediction_thresh, chunk_size):  # fmt: skip
    """compute_semseg_preds with utils.compute_cos_sim(softmax=True): returns 0 for "no
    prediction", else the class index + 1."""
    preds = []
    for c in range(int(np.ceil(map_feats.shape[0] / chunk_size))):
        vec2 = map_feats[c * chunk_size : (c + 1) * chunk_size]
        n, cdim = text_embeds.shape
        m = vec2.shape[0]
        v1 = (text_embeds / text_embeds.norm(dim=-1, keepdim=True)).reshape(1, n, 1, cdim)
        v2 = (vec2 / vec2.norm(dim=-1, keepdim=True)).reshape(m, 1, cdim, 1)
        sim_vx = torch.softmax(100 * (v1 @ v2).reshape(m, n), dim=-1)
        max_sim = torch.max(sim_vx, dim=0).values
        low_conf_classes = torch.argwhere(max_sim < prompt_denoising_thresh)
        sim_vx[:, low_conf_classes] = -torch.inf
        sim_value, pred = torch.max(sim_vx, dim=-1)
        pred += 1
        pred[sim_value < prediction_thresh] = 0
        preds.append(pred)
    return torch.cat(preds)


def rf_ground_truth(frames, num_classes, vox):
    """compute_semseg_gt: one-hot label images (index 0 = ignore) lifted with every valid
    pixel, averaged per voxel (all frames), labelled by compute_semseg_preds(feats, GTEncoder
    prompts, 0, 0.1). Returns (centres, index, labels with 0 = ignore)."""
    xyz, feats = [], []
    for depth, semseg, pose, k in frames:
        pts, valid = rf_depth_to_pointcloud(depth, pose, k)
        onehot = F.one_hot(semseg, num_classes).squeeze(0).permute(2, 0, 1).float()
        xyz.append(pts)
        feats.append(onehot.permute(1, 2, 0).reshape(-1, num_classes)[valid])
    centres, mean, index = rf_voxelize(torch.cat(xyz), vox, torch.cat(feats), "mean")
    prompts = torch.full((num_classes - 1, num_classes), 1e-10)  # encode_labels, eps 1e-10
    prompts[torch.arange(num_classes - 1), torch.arange(1, num_classes)] = 1.0
    return centres, index, rf_compute_semseg_preds(mean, prompts, 0, 0.1, 10000)


def rf_metrics(gt_xyz, gt, pred_xyz, pred, k, num_classes):
    """compute_semseg_metrics with align_labels_with_knn (k >= 1): miou, fmiou, acc, iou."""
    index = BallTree(pred_xyz.numpy()).query(gt_xyz.numpy(), k=k)[1]
    aligned = torch.mode(pred[torch.from_numpy(index)], dim=-1).values
    gt_bin = F.one_hot(gt, num_classes).bool()
    pred_bin = F.one_hot(aligned, num_classes).bool()
    valid = (gt != 0).unsqueeze(-1)
    tp = torch.sum(gt_bin & pred_bin & valid, dim=0)[1:]
    fp = torch.sum(~gt_bin & pred_bin & valid, dim=0)[1:]
    fn = torch.sum(gt_bin & ~pred_bin & valid, dim=0)[1:]
    # float64 here (RayFronts divides in float32, ~6e-8 relative: too coarse for 1e-9)
    iou = tp.double() / (tp + fp + fn).double()
    freq = (tp + fn).double()
    iou[freq == 0] = torch.nan
    fiou = freq / torch.sum(freq) * iou
    acc = torch.mean((aligned[gt != 0] == gt[gt != 0]).double())
    return {"miou": float(torch.nanmean(iou)), "fmiou": float(torch.nansum(fiou)),
            "acc": float(acc), "tp": tp, "fp": fp, "fn": fn}  # fmt: skip


# ------------------------------------------------------------------- generated scenes
SCENES = ("synthetic0000_00", "synthetic0001_00")


@pytest.fixture(scope="module")
def rooms(tmp_path_factory):
    """Two ScanNet-format rooms (no lost-tracking pose), different sizes and furniture, with a
    label map holding every NYU40 id (as ScanNet's does: 37 evaluated classes)."""
    root = tmp_path_factory.mktemp("rooms")
    write_scene(root, SCENES[0], SyntheticRoom(frames=8, bad_pose_frame=None))
    other = SyntheticRoom(size=(3.6, 3.4, 2.6), frames=6, bad_pose_frame=None, objects=[
        Box((0.4, 2.0, 0.0), (1.8, 3.2, 0.5), 11), Box((2.2, 0.3, 0.0), (3.0, 0.9, 0.8), 4),
        Box((0.1, 0.2, 0.0), (0.6, 1.0, 1.8), 7), Box((2.7, 2.2, 0.0), (3.3, 2.8, 1.0), 35),
    ])  # fmt: skip
    write_scene(root, SCENES[1], other)
    tsv = root / "scannetv2-labels.combined.tsv"
    used = {int(r.split("\t")[4]) for r in tsv.read_text().splitlines()[1:]}
    extra = [f"{1000 + n}\t{c}\t{c}\t1\t{n}\t{c}" for n, c in enumerate(NYU40_CLASSES, 1)
             if n not in used]  # fmt: skip
    tsv.write_text(tsv.read_text() + "\n".join(extra) + "\n")
    return root


class _Confused(_ClassFromColour):
    """The colour oracle, wrong on the left third of every image (class + 1): a map that is
    neither perfect nor empty."""

    def encode(self, images):
        out = super().encode(images)
        w = images.shape[-1]
        shifted = out.language.roll(1, dims=1)
        lang = torch.cat([shifted[..., : w // 3], out.language[..., w // 3 :]], dim=-1)
        return type(out)(lang, lang, None)


class _Recording(MappingEngine):
    """The task, keeping each scene's predicted voxels (centres and labels: the map side,
    which the reference takes as given) and ground-truth voxels and labels."""

    def _finish_scene(self, state, protos, result, timed):
        centres, feats = state["maps"]["bb"].features()
        p = self.protocol
        pred = classify(feats, protos, p.prediction_threshold, p.prompt_denoising,
                        none=len(self.dataset.classes))  # fmt: skip
        gt = ground_truth_labels(state["gt"], p.gt_unlabelled, len(self.dataset.classes), 255)
        self.record[state["name"]] = (centres, pred, state["gt"].indices, gt)
        super()._finish_scene(state, protos, result, timed)


@pytest.mark.parametrize(("knn", "threshold"), [(1, None), (5, 0.1)])
def test_defaults_equal_rayfronts_semseg_eval(rooms, knn, threshold):
    """The project's default protocol on two generated scenes against the reference: ground
    truth voxels and labels equal, per-scene mIoU / f-mIoU / accuracy to 1e-9, the table's
    figure (mean over scenes) and the pooled figure (the reference's counts summed)."""
    frames = ScanNetFrames(rooms, SCENES, frame_skip=1, image_size=IMAGE, patch_size=1)
    task = _Recording(frames, batch_size=3, voxel_size=0.1, knn=knn,
                      prediction_threshold=threshold)  # fmt: skip
    task.record = {}
    result = task.run(_Confused(), build_variants(["bb"]))
    scores, per_scene = result.scores(), result.per_scene()
    ref_scores = []
    totals = {name: 0 for name in ("tp", "fp", "fn")}
    for scene in SCENES:
        rf, names = rf_frames(rooms, scene, IMAGE, 1, ("otherstructure", "otherfurniture",
                                                       "otherprop"))  # fmt: skip
        assert tuple(names[1:]) == frames.classes == SCANNET_CLASSES
        n = len(names)
        gt_xyz, gt_index, gt = rf_ground_truth(rf, n, 0.1)
        centres, pred, our_index, our_gt = task.record[scene]
        ours = dict(zip(map(tuple, our_index.tolist()), our_gt.tolist(), strict=True))
        theirs = dict(zip(map(tuple, gt_index.tolist()), (gt - 1).tolist(), strict=True))
        theirs = {i: (255 if c < 0 else c) for i, c in theirs.items()}
        assert ours == theirs and 0 < sum(c == 255 for c in ours.values()) < len(ours)
        rf_pred = torch.where(pred == n - 1, 0, pred + 1)  # none -> 0, class c -> c + 1
        ref = rf_metrics(gt_xyz, gt, centres, rf_pred, knn, n)
        got = per_scene[scene]["scores"]["bb"]
        for name in ("miou", "fmiou", "acc"):
            assert got[name] == pytest.approx(ref[name], abs=1e-9)
        assert 0.2 < ref["miou"] < 0.95
        ref_scores.append(ref)
        for name in totals:
            totals[name] = totals[name] + ref[name]
    prefix = "val/scannet3d/scannet"
    for name in ("miou", "fmiou", "acc"):
        mean = sum(r[name] for r in ref_scores) / len(ref_scores)
        assert scores[f"{prefix}/{name}_bb"] == pytest.approx(mean, abs=1e-9)
    tp, fp, fn = (totals[k].double() for k in ("tp", "fp", "fn"))
    freq = tp + fn
    iou = torch.where(freq > 0, tp / (tp + fp + fn), torch.nan)
    assert scores[f"{prefix}/pooled_miou_bb"] == pytest.approx(float(torch.nanmean(iou)), abs=1e-9)
    assert scores[f"{prefix}/pooled_fmiou_bb"] == pytest.approx(
        float(torch.nansum(freq / freq.sum() * iou)), abs=1e-9
    )


def test_rayfronts_ground_truth_rule_is_not_the_vote_rule(rooms):
    """On the same scene the two rules label some voxels differently (ignored pixels outvote
    labelled ones under ``vote`` only), the voxel set is the same, and ``drop`` scores every
    voxel that has a labelled pixel."""
    frames = ScanNetFrames(rooms, SCENES[1:], frame_skip=0, image_size=IMAGE, patch_size=1)
    labels = {}
    for rule in GT_RULES:
        task = _Recording(frames, batch_size=4, voxel_size=0.25, gt_unlabelled=rule)
        task.record = {}
        task.run(_ClassFromColour(), build_variants(["bb"]))
        _, _, index, gt = task.record[SCENES[1]]
        labels[rule] = dict(zip(map(tuple, index.tolist()), gt.tolist(), strict=True))
    assert set(labels["rayfronts"]) == set(labels["vote"]) and set(labels["drop"]) < set(
        labels["vote"])  # fmt: skip
    differ = [i for i in labels["vote"] if labels["vote"][i] != labels["rayfronts"][i]]
    assert differ and all(labels["vote"][i] == 255 for i in differ)
    assert 255 not in labels["drop"].values()


def test_ground_truth_rules_by_hand():
    """Votes of four voxels (K = 37 classes + the ignore column): the hand values of
    RayFronts' rule, softmax(100 cos) of the vote fractions against the one-hot prompts.
    1 chair + 3 ignored: cos(chair) = 1 / sqrt(10) = 0.316, p = e^31.6 / (e^31.6 + 36) ~ 1:
    chair (vote: ignored wins). 1 chair + 1000 ignored: cos = 0.001, p = e^0.1 / (e^0.1 + 36)
    = 0.030 < 0.1: ignored. 2 chair + 2 table: a tie, the lower class. 5 ignored: every class
    at p = 1/37: ignored. With 9 classes the last voxel's 1/9 passes 0.1 and RayFronts'
    reference labels it class 0; the project leaves it unscored (docs/protocol.md section 5)."""
    from resireg.mapping import LabelVoxelMap

    k, chair, table = 37, 4, 6
    gt = LabelVoxelMap(1.0, k + 1, ignore_index=-1)
    add = [((0, 0, 0), chair, 1), ((0, 0, 0), k, 3), ((5, 0, 0), chair, 1), ((5, 0, 0), k, 1000),
           ((9, 0, 0), table, 2), ((9, 0, 0), chair, 2), ((12, 0, 0), k, 5)]  # fmt: skip
    for at, cls, n in add:
        gt.add(torch.tensor([at], dtype=torch.float32).repeat(n, 1), torch.full((n,), cls))
    assert ground_truth_labels(gt, "rayfronts", k, 255).tolist() == [chair, 255, chair, 255]
    assert ground_truth_labels(gt, "vote", k, 255).tolist() == [255, 255, chair, 255]
    small = LabelVoxelMap(1.0, 10, ignore_index=-1)
    small.add(torch.zeros(5, 3), torch.full((5,), 9))  # 5 ignored pixels, 9 classes
    votes = torch.cat([small.votes[:, 9:], small.votes[:, :9]], 1).float()
    prompts = torch.full((9, 10), 1e-10)
    prompts[torch.arange(9), torch.arange(1, 10)] = 1.0
    assert rf_compute_semseg_preds(votes / 5, prompts, 0, 0.1, 10).tolist() == [1]  # class 0 + 1
    assert ground_truth_labels(small, "rayfronts", 9, 255).tolist() == [255]


# ------------------------------------------------------------------- the options
def test_patch_and_pixel_lifting_voxel_counts_by_hand():
    """``points``: an 8 x 8 depth image of a wall 2 m ahead (fx = fy = 4, principal point at
    the centre, so pixel u sits at x = (u - 3.5) / 2 m), a 2 x 2 feature grid (4 x 4-pixel
    patches), 1 m voxels, round lattice; frame 2 is moved by (0.125, 0.6, 0) m.
    patch: the patch centres (grid K: f = 1, c = 0.5) are at x, y = +-1 m: frame 1 fills voxels
    (+-1, +-1, 2), frame 2 (+-1, {0, 2}, 2): 8 voxels of one point each.
    pixel: per axis the 8 pixels of frame 1 fall in voxels -2, -1, 0, 1, 2 as 1, 2, 2, 2, 1
    (patch 0: 1, 2, 1 in -2, -1, 0; patch 1: 1, 2, 1 in 0, 1, 2); frame 2's x alike, its y: 2
    pixels in each of -1, 0, 1, 2 (patch 0 in -1, 0; patch 1 in 1, 2). A voxel's count is the
    product of its axes' counts, its mean the count-weighted mean of its patches' features."""
    k = torch.tensor([[4.0, 0.0, 3.5], [0.0, 4.0, 3.5], [0.0, 0.0, 1.0]])
    poses = torch.eye(4).repeat(2, 1, 1)
    poses[1, :3, 3] = torch.tensor([0.125, 0.6, 0.0])
    depth = torch.full((2, 8, 8), 2.0)
    feats = torch.arange(8 * 3, dtype=torch.float32).reshape(2 * 2 * 2, 3)  # [frame, i, j]
    points, valid = patch_points(depth, k, poses, (2, 2))
    patch_map = VoxelMap(1.0, 3)
    patch_map.add(points[valid], feats[valid.reshape(-1)])
    assert dict(zip(map(tuple, patch_map.indices.tolist()), patch_map.counts.tolist(),
                    strict=True)) == {(x, y, 2): 1 for x in (-1, 1) for y in (-1, 1, 0, 2)}  # fmt: skip

    x_of_patch = {0: {-2: 1, -1: 2, 0: 1}, 1: {0: 1, 1: 2, 2: 1}}  # frame 1 x, frame 1 y, frame 2 x
    y2_of_patch = {0: {-1: 2, 0: 2}, 1: {1: 2, 2: 2}}  # frame 2 y
    expect_counts: dict = {}
    expect_sums: dict = {}
    for frame in (0, 1):
        for i in (0, 1):
            for j in (0, 1):
                ys = x_of_patch[i] if frame == 0 else y2_of_patch[i]
                for vx, cx in x_of_patch[j].items():
                    for vy, cy in ys.items():
                        key = (vx, vy, 2)
                        expect_counts[key] = expect_counts.get(key, 0) + cx * cy
                        f = feats[frame * 4 + i * 2 + j].double() * cx * cy
                        expect_sums[key] = expect_sums.get(key, 0) + f
    index, patch, count = pixel_pairs(depth, k, poses, (2, 2), 1.0)
    assert int(count.sum()) == 2 * 64
    pixel_map = VoxelMap(1.0, 3)
    pixel_map.add_pairs(index, count, feats, patch)
    got = dict(zip(map(tuple, pixel_map.indices.tolist()), pixel_map.counts.tolist(), strict=True))
    assert got == expect_counts and len(got) == 25  # frame 2's voxels are among frame 1's 5 x 5
    for key, mean in zip(map(tuple, pixel_map.indices.tolist()), pixel_map.means(), strict=True):
        assert torch.equal(mean, expect_sums[key] / expect_counts[key])


def _dyadic(n, d, seed):
    """Features that are multiples of 2^-10: their float64 sums are exact in any order."""
    g = torch.Generator().manual_seed(seed)
    return torch.round(torch.randn(n, d, generator=g) * 1024) / 1024


@pytest.mark.parametrize(("lattice", "grid"), [("round", (15, 20)), ("floor", (13, 17))])
def test_pixel_pairs_equal_the_per_pixel_reference_exactly(lattice, grid):
    """Issue 26 item 4: a generated 120 x 160 frame pair (the benchmark's room, noisy depth with
    holes, a random pose), the literal reading fused as (patch, voxel, count) pairs: voxel
    indices, counts and means equal a numpy per-pixel fusion (every pixel its own point at its
    patch's depth, float64 numpy geometry) exactly; also for a grid that does not divide the
    image (13 x 17: patches of unequal size)."""
    from bench_mapping import room_frames

    depth, k, poses = next(room_frames(2, (120, 160), batch=2, seed=7))
    h, w = grid
    feats = _dyadic(2 * h * w, 6, 0)
    index, patch, count = pixel_pairs(depth, k, poses, grid, 0.05, lattice)
    vmap = VoxelMap(0.05, 6, lattice=lattice)
    vmap.add_pairs(index, count, feats, patch)
    # numpy reference: nearest-exact patch of each pixel, ((2 x + 1) n) // (2 N), per pixel
    rows = ((2 * np.arange(120) + 1) * h) // (2 * 120)
    cols = ((2 * np.arange(160) + 1) * w) // (2 * 160)
    d = depth.numpy().astype(np.float64)
    z = d[:, ((2 * np.arange(h) + 1) * 120) // (2 * h)][
        :, :, ((2 * np.arange(w) + 1) * 160) // (2 * w)
    ]
    kk = k.numpy().astype(np.float64)
    keys, feat_rows = [], []
    for b in range(2):
        zp = z[b][rows][:, cols]  # [120, 160] the patch depth of every pixel
        v, u = np.mgrid[0:120, 0:160]
        cam = np.stack([(u - kk[0, 2]) / kk[0, 0], (v - kk[1, 2]) / kk[1, 1], np.ones_like(zp)],
                       -1) * zp[..., None]  # fmt: skip
        pose = poses[b].numpy().astype(np.float64)
        world = cam @ pose[:3, :3].T + pose[:3, 3]
        ok = zp > 0
        op = np.rint if lattice == "round" else np.floor
        keys.append(op(world[ok] / 0.05).astype(np.int64))
        feat_rows.append(b * h * w + (rows[:, None] * w + cols[None, :])[ok])
    keys, feat_rows = np.concatenate(keys), np.concatenate(feat_rows)
    uniq, inv = np.unique(keys, axis=0, return_inverse=True)
    sums = np.zeros((len(uniq), 6))
    np.add.at(sums, inv.reshape(-1), feats.numpy().astype(np.float64)[feat_rows])
    counts = np.bincount(inv.reshape(-1))
    assert len(keys) > 30_000 and len(patch) < len(keys) / 5  # the pairs are far fewer
    np.testing.assert_array_equal(vmap.indices.numpy(), uniq)
    np.testing.assert_array_equal(vmap.counts.numpy(), counts)
    assert np.array_equal(vmap.means().numpy(), sums / counts[:, None])


def _numpy_pixel_fusion(depth, k, poses, grid, voxel, lattice, feats):
    """Independent per-pixel reference of the literal reading: every pixel its own point at its
    patch's depth (nearest-exact, ``((2 x + 1) n) // (2 N)``), float64 numpy geometry, numpy
    voxelisation and sums. Returns sorted voxel indices, counts and mean features."""
    b, hh, ww = depth.shape
    h, w = grid
    rows = ((2 * np.arange(hh) + 1) * h) // (2 * hh)
    cols = ((2 * np.arange(ww) + 1) * w) // (2 * ww)
    d = depth.numpy().astype(np.float64)
    z = d[:, ((2 * np.arange(h) + 1) * hh) // (2 * h)][
        :, :, ((2 * np.arange(w) + 1) * ww) // (2 * w)
    ]
    kk = k.numpy().astype(np.float64)
    keys, feat_rows, faces = [], [], 0
    for f in range(b):
        pose = poses[f].numpy().astype(np.float64)
        zp = z[f][rows][:, cols]
        if not np.isfinite(pose).all():
            continue
        v, u = np.mgrid[0:hh, 0:ww]
        with np.errstate(invalid="ignore"):  # holes: inf * 0 (dropped below)
            cam = np.stack([(u - kk[0, 2]) / kk[0, 0], (v - kk[1, 2]) / kk[1, 1],
                            np.ones_like(zp)], -1) * zp[..., None]  # fmt: skip
            world = cam @ pose[:3, :3].T + pose[:3, 3]
        ok = np.isfinite(zp) & (zp > 0)
        op = np.rint if lattice == "round" else np.floor
        scaled = world[ok] / voxel
        faces += int((np.mod(scaled, 1) == (0.5 if lattice == "round" else 0.0)).sum())
        keys.append(op(scaled).astype(np.int64))
        feat_rows.append(f * h * w + (rows[:, None] * w + cols[None, :])[ok])
    keys, feat_rows = np.concatenate(keys), np.concatenate(feat_rows)
    uniq, inv = np.unique(keys, axis=0, return_inverse=True)
    sums = np.zeros((len(uniq), feats.shape[1]))
    np.add.at(sums, inv.reshape(-1), feats.numpy().astype(np.float64)[feat_rows])
    counts = np.bincount(inv.reshape(-1))
    return uniq, counts, sums / counts[:, None], faces


@pytest.mark.parametrize("lattice", ["round", "floor"])
@pytest.mark.parametrize("grid", [(6, 8), (5, 7)])
@pytest.mark.parametrize("path", ["bincount", "sorting"])
def test_pixel_pairs_at_voxel_faces_and_invalid_depth_equal_numpy(lattice, grid, path, monkeypatch):
    """Issue 26 item 4, the exact corner cases: a 48 x 64 frame pair with axis-aligned poses and
    dyadic depths, intrinsics, translations and voxel (0.25 m), so every coordinate is exact in
    float64 and many pixels lie exactly on voxel faces (``round``: ties ``k + 0.5``, half to
    even; ``floor``: integers); holes (0, NaN, inf, negative depth) and a frame with an infinite
    pose drop their patches. Voxel indices, counts and means equal the numpy per-pixel fusion
    exactly, for a grid that divides the image (6 x 8) and one that does not (5 x 7: padded
    patches), by ``bincount`` over the patches' boxes and by the sorting fallback (forced)."""
    import resireg.mapping.lifting as lifting

    if path == "sorting":
        monkeypatch.setattr(lifting, "_MAX_BINS", 0)
    g = torch.Generator().manual_seed(11)
    choices = torch.tensor([0.5, 0.75, 1.0, 1.25, 1.5, 2.0, 3.0])
    depth = choices[torch.randint(0, len(choices), (3, 48, 64), generator=g)]
    holes = torch.tensor([0.0, math.nan, math.inf, -1.0])
    mask = torch.rand(3, 48, 64, generator=g) < 0.15
    depth[mask] = holes[torch.randint(0, 4, (int(mask.sum()),), generator=g)]
    k = torch.tensor([[8.0, 0.0, 32.0], [0.0, 8.0, 23.5], [0.0, 0.0, 1.0]])
    poses = torch.eye(4).repeat(3, 1, 1)
    poses[1, :3, :3] = torch.tensor([[0.0, 0.0, 1.0], [1.0, 0.0, 0.0], [0.0, 1.0, 0.0]])
    poses[1, :3, 3] = torch.tensor([0.125, -0.375, 2.5])
    poses[2, 0, 3] = -math.inf  # lost tracking: no patch of frame 2 is lifted
    h, w = grid
    feats = _dyadic(3 * h * w, 5, 1)
    index, patch, count = pixel_pairs(depth, k, poses, grid, 0.25, lattice)
    vmap = VoxelMap(0.25, 5, lattice=lattice)
    vmap.add_pairs(index, count, feats, patch)
    uniq, counts, means, faces = _numpy_pixel_fusion(depth, k, poses, grid, 0.25, lattice, feats)
    assert faces > 2000  # many coordinates exactly on a face: where a rounding slip would flip
    assert int(patch.max()) < 2 * h * w  # frame 2 contributes nothing
    np.testing.assert_array_equal(vmap.indices.numpy(), uniq)
    np.testing.assert_array_equal(vmap.counts.numpy(), counts)
    assert np.array_equal(vmap.means().numpy(), means)
    # pairs: by patch, then voxel (lexicographic), each pair once
    order = np.lexsort((*index.numpy().T[::-1], patch.numpy()))
    np.testing.assert_array_equal(order, np.arange(len(patch)))
    key = np.concatenate([patch.numpy()[:, None], index.numpy()], 1)
    assert len(np.unique(key, axis=0)) == len(key)


def test_pixel_pairs_out_of_range_indices_raise():
    """A depth whose voxel indices exceed VoxelMap's packable range (|index| > 2^20 - 1) is a
    ValueError naming the index and the voxel size, raised before any integer conversion."""
    k = torch.tensor([[4.0, 0.0, 3.5], [0.0, 4.0, 3.5], [0.0, 0.0, 1.0]])
    depth = torch.full((1, 8, 8), 1e6)
    with pytest.raises(ValueError, match=r"voxel indices up to .* voxel_size=0.05"):
        pixel_pairs(depth, k, torch.eye(4)[None], (2, 2), 0.05)


def test_transfer_k_and_same_voxel_by_hand():
    """``knn``: targets among labelled lattice points: k = 1 the nearest label, k = 5 the mode of
    the five nearest (ties to the smaller label, torch.mode), k = 0 the same voxel or none."""
    src = torch.tensor([[0, 0, 0], [1, 0, 0], [2, 0, 0], [3, 0, 0], [4, 0, 0], [10, 0, 0]],
                       dtype=torch.float32)  # fmt: skip
    labels = torch.tensor([7, 3, 3, 5, 5, 9])
    tgt = torch.tensor([[0.1, 0, 0], [3.9, 0, 0], [10, 0, 0]])
    assert transfer_labels(src, labels, tgt, 1).tolist() == [7, 5, 9]
    # 5 nearest of x=0.1: labels 7 3 3 5 5 -> 3 (2 votes) vs 5 (2): smaller 3; of x=3.9:
    # 5 5 3 3 7 -> 3; of x=10: 9 5 5 3 3 -> 3
    assert transfer_labels(src, labels, tgt, 5).tolist() == [3, 3, 3]
    by_voxel = transfer_labels_by_voxel(
        src.long(), labels, torch.tensor([[3, 0, 0], [5, 0, 0]]), 99
    )
    assert by_voxel.tolist() == [5, 99]


def test_prediction_threshold_and_denoising_equal_compute_semseg_preds():
    """``prediction_threshold`` / ``prompt_denoising``: classify with RayFronts' rule equals the
    reference compute_semseg_preds (chunks of 10,000, the none label 0 there), on features where
    both take effect; without them it is the cosine argmax."""
    g = torch.Generator().manual_seed(3)
    protos = torch.linalg.qr(torch.randn(16, 12, generator=g))[0].T  # 12 orthonormal classes
    near = protos[torch.randint(0, 4, (20_000,), generator=g)]  # confident: classes 0..3 only
    near = near + 0.3 * torch.randn(20_000, 16, generator=g) / 4
    even = protos.mean(0) + 1e-4 * torch.randn(4_000, 16, generator=g)  # ~1/12 each: no class
    weak = protos.mean(0) + 0.0045 * protos[5] + 1e-5 * torch.randn(1_000, 16, generator=g)
    feats = torch.cat([near, even, weak])[torch.randperm(25_000, generator=g)]  # weak: p5 ~ 0.3
    ref = rf_compute_semseg_preds(feats, protos, 0.5, 0.1, 10_000)
    got = classify(feats, protos, threshold=0.1, denoise=0.5, none=-1)
    assert torch.equal(torch.where(got < 0, 0, got + 1), ref)
    assert int((ref == 0).sum()) == 5_000 and set(ref.tolist()) == {0, 1, 2, 3, 4}
    kept = rf_compute_semseg_preds(feats, protos, 0, 0.1, 10_000)  # no denoising: class 5 stays
    assert int((kept == 0).sum()) == 4_000 and int((kept == 6).sum()) == 1_000
    assert torch.equal(
        torch.where(
            classify(feats, protos, threshold=0.1) < 0,
            0,
            classify(feats, protos, threshold=0.1) + 1,
        ),
        kept,
    )
    plain = classify(feats, protos)
    assert not torch.equal(plain, got)
    assert torch.equal(plain, torch.argmax(F.normalize(feats) @ F.normalize(protos).T, dim=1))


def test_resize_and_intrinsics_rules():
    """``resize``: torch's nearest-exact and the integer rule differ where a sample's centre is
    on a pixel edge (640 -> 54 columns, column 40: centre 480.0, torch 479, exact 480).
    ``intrinsics``: multiply scales c by s, half_pixel maps c + 1/2."""
    row = torch.arange(640, dtype=torch.float32).reshape(1, 640)
    torch_cols = resize_nearest(row, (1, 54), "torch")[0]
    exact_cols = resize_nearest(row, (1, 54), "exact")[0]
    assert torch_cols[40] == 479 and exact_cols[40] == 480
    assert int((torch_cols != exact_cols).sum()) >= 1
    labels = torch.arange(12).reshape(3, 4)
    assert resize_nearest(labels, (6, 8), "torch").dtype == torch.int64
    from resireg_train.data.scannet import scale_camera

    k = torch.tensor([[577.6, 0.0, 318.9], [0.0, 578.7, 242.7], [0.0, 0.0, 1.0]])
    mul = scale_camera(k, (480, 640), (640, 864), "multiply")
    half = scale_camera(k, (480, 640), (640, 864), "half_pixel")
    assert mul[0, 2] == pytest.approx(318.9 * 1.35) and mul[1, 2] == pytest.approx(242.7 * 4 / 3)
    assert half[0, 2] == pytest.approx(319.4 * 1.35 - 0.5)
    assert half[1, 2] == pytest.approx(243.2 * 4 / 3 - 0.5)


def test_metric_definitions_by_hand():
    """``metric``: a class predicted but absent from the ground truth is NaN (left out) under
    rayfronts and 0 under union; f-mIoU and accuracy agree; "no prediction" is a miss.
    Ground truth: class 0 x 3, class 1 x 1; predictions 0, 0, none, 2 (class 2 absent)."""
    cm = metric_module.confusion(torch.tensor([0, 0, 3, 2]), torch.tensor([0, 0, 0, 1]), 3, 255)
    assert cm.tolist() == [[2, 0, 0, 1], [0, 0, 1, 0], [0, 0, 0, 0]]
    rf, union = metric_module.scores(cm, "rayfronts"), metric_module.scores(cm, "union")
    assert rf["iou"][:2] == [2 / 3, 0.0] and math.isnan(rf["iou"][2])
    assert union["iou"] == [2 / 3, 0.0, 0.0]
    assert rf["miou"] == pytest.approx(1 / 3) and union["miou"] == pytest.approx(2 / 9)
    assert rf["fmiou"] == union["fmiou"] == pytest.approx(3 / 4 * 2 / 3)
    assert rf["acc"] == union["acc"] == 0.5


def test_gt_resolution_and_the_option_checks(rooms):
    """``gt_resolution``: image = image_size, label = the label files' size, or [H, W]; a bad
    value of any 3D option names its key."""
    item = ScanNetFrames(rooms, SCENES[:1], frame_skip=0, image_size=IMAGE, patch_size=1)[0]
    assert item["gt_label"].shape == IMAGE == item["gt_depth"].shape
    label = ScanNetFrames(rooms, SCENES[:1], frame_skip=0, image_size=IMAGE, patch_size=1,
                          gt_resolution="label")[0]  # fmt: skip
    assert label["gt_label"].shape == (48, 64)
    with pytest.raises(ValueError, match=r"dataset\.resize='bilinear'"):
        ScanNetFrames(rooms, SCENES[:1], resize="bilinear")
    with pytest.raises(ValueError, match=r"points='voxel'"):
        MappingSettings.from_conf(points="voxel")

    from hydra import compose, initialize_config_dir

    from resireg.errors import ConfigError
    from resireg_train.checks.eval import validate_eval
    from resireg_train.config.paths import CONFIG_DIR

    bad = ["dataset.resize=area", "dataset.intrinsics=shift", "dataset.lattice=ceil",
           "dataset.points=voxel", "dataset.knn=-1", "dataset.prediction_threshold=2",
           "dataset.prompt_denoising=0", "dataset.metric=mean", "dataset.class_names=x",
           "dataset.classes_to_ignore=wall", "dataset.gt_resolution=null",
           "dataset.gt_unlabelled=keep"]  # fmt: skip
    with initialize_config_dir(str(CONFIG_DIR), version_base="1.3"):
        cfg = compose("eval", ["task=scannet3d", "dataset=scannet", "encoder=radseg", *bad])
        legacy = compose("eval", ["task=scannet3d", "dataset=scannet_legacy", "encoder=radseg"])
    with pytest.raises(ConfigError) as info:
        validate_eval(cfg)
    for override in bad:
        key, value = override.split("=")
        assert f"{key}=" in str(info.value), key
    validate_eval(legacy)
    assert legacy.dataset.lattice == "floor" and legacy.dataset.metric == "union"


def test_defaults_and_allowed_values_are_the_configs():
    """One source per value: the task's and the reader's defaults equal conf/dataset/
    scannet.yaml, and the values validation accepts are the engine's."""
    import dataclasses
    import inspect

    from hydra import compose, initialize_config_dir

    from resireg_train.config.paths import CONFIG_DIR
    from resireg_train.data.specs import DATASET_SPECS

    spec = yaml.safe_load((CONF / "scannet.yaml").read_text())
    # The task's settings have no Python default (conf/ is their one source): the Python API's
    # are read from the yaml, and an entry missing one is an error naming it.
    for f in dataclasses.fields(MappingSettings):
        assert f.default is dataclasses.MISSING, f.name
    for name, value in dataclasses.asdict(MappingSettings.from_conf()).items():
        assert spec[name] == value, name
    assert MappingSettings.from_conf(voxel_size=0.2).voxel_size == 0.2
    # A config that composes another (scannet_legacy: defaults [scannet, _self_]) holds its
    # parent's settings too, as Hydra composes it for dataset=scannet_legacy.
    with initialize_config_dir(str(CONFIG_DIR), version_base="1.3"):
        legacy = compose("eval", overrides=["dataset=scannet_legacy"]).dataset
    for name, value in dataclasses.asdict(MappingSettings.from_conf("scannet_legacy")).items():
        assert legacy[name] == value, name
    with pytest.raises(ValueError, match=r"dataset\.knn"):
        MappingSettings.from_spec({k: v for k, v in spec.items() if k != "knn"})
    params = inspect.signature(ScanNetFrames).parameters
    for name in ("frame_skip", "image_size", "gt_resolution", "resize", "intrinsics",
                 "class_names", "classes_to_ignore", "short_side", "limit"):  # fmt: skip
        default = params[name].default
        assert spec[name] == (list(default) if isinstance(default, tuple) else default), name
    rules = DATASET_SPECS["scannet"].rules  # the dataset table's, checked by validate_eval
    for key, allowed in (("resize", RESIZES), ("intrinsics", INTRINSICS), ("points", POINTS),
                         ("gt_unlabelled", GT_RULES), ("class_names", CLASS_NAMES),
                         ("metric", metric_module.METRICS), ("lattice", ("round", "floor"))):  # fmt: skip
        check = rules[key][0]
        assert all(check(v) for v in allowed) and not check("other"), key


def test_the_classes_check_values_by_the_dataset_table(rooms, monkeypatch):
    """One rule per ScanNet option: MappingSettings and ScanNetFrames check their values with
    the dataset table's rules (the config check's), so a rule changed there changes what they
    accept, and they report a bad value in the config check's words."""
    from resireg.specs.rules import one_of
    from resireg_train.data.specs import DATASET_SPECS

    rules = DATASET_SPECS["scannet"].rules
    with pytest.raises(
        ValueError, match=r"dataset\.lattice='ceil': expected one of \['round', 'floor'\]"
    ):
        MappingSettings.from_conf(lattice="ceil")
    monkeypatch.setitem(rules, "lattice", one_of(("round", "floor", "ceil")))
    monkeypatch.setitem(rules, "resize", one_of(("exact",)))
    assert MappingSettings.from_conf(lattice="ceil").lattice == "ceil"  # accepted: the table's rule
    with pytest.raises(ValueError, match=r"dataset\.resize='torch': expected one of \['exact'\]"):
        ScanNetFrames(rooms, SCENES[:1], resize="torch")
    # every field of MappingSettings, the two RayFronts probabilities and the voxel size included
    # (before, a threshold of 2 passed the class silently: every voxel became "no prediction")
    for name, value, words in (
        ("prediction_threshold", 2.0, r"null or a number in \(0, 1\)"),
        ("prompt_denoising", 0.0, r"null or a number in \(0, 1\)"),
        ("voxel_size", 0.0, r"a number > 0 \(finite\)"),
        ("voxel_size", float("inf"), r"a number > 0 \(finite\)"),
    ):
        with pytest.raises(ValueError, match=rf"dataset\.{name}={value!r}: expected {words}"):
            MappingSettings.from_conf(**{name: value})
    # the config check reads the same rules (no copy of its own), for each kind that has the key
    from hydra import compose, initialize_config_dir

    from resireg.errors import ConfigError
    from resireg_train.checks.eval import validate_eval
    from resireg_train.config.paths import CONFIG_DIR

    for task, config, key, value, words in (
        ("ovss", "synthetic", "image_size", "[0,8]", r"\[height, width\]"),
        ("scannet3d", "scannet", "frame_skip", "-1", "an integer >= 0"),
        ("scannet3d", "scannet", "voxel_size", "inf", r"a number > 0 \(finite\)"),
        ("scannet3d", "scannet", "scenes", "[]", "a non-empty list of scene names"),
    ):
        with initialize_config_dir(str(CONFIG_DIR), version_base="1.3"):
            cfg = compose("eval", [f"task={task}", f"dataset={config}", "encoder=radseg",
                                   f"dataset.{key}={value}"])  # fmt: skip
        with pytest.raises(ConfigError, match=rf"dataset\.{key}=.+: expected {words}"):
            validate_eval(cfg)


# ------------------------------------------------------------------ the protocol record
def test_protocol_record_of_both_tasks_and_its_line_under_table_1(tmp_path):
    """resireg_train.evaluation.protocol: the 3D record is the dataset entry's protocol keys (only those);
    the 2D record the entry's keys, the temperature, the built set's reduce_zero_label, class
    list and templates, and the encoder's dense_path where its config has one. Table 1 prints
    the protocol the jobs share; jobs with two protocols get one line each."""
    from types import SimpleNamespace

    from resireg_train.evaluation.protocol import protocol_record, protocol_text
    from resireg_train.report import collect, write_encoder_table

    spec = yaml.safe_load((CONF / "scannet.yaml").read_text())
    record = protocol_record({"task": "scannet3d", "dataset": spec, "encoder": {"kind": "radseg"}})
    assert record["name"] == "rayfronts_semseg_eval"
    # docs/protocol.md section 4's settings (the task table's protocol_keys of scannet3d)
    mapping_keys = {
        "frame_skip", "image_size", "short_side", "resize", "intrinsics", "gt_resolution",
        "gt_unlabelled", "points", "lattice", "voxel_size", "storage", "knn",
        "prediction_threshold", "prompt_denoising", "metric", "class_names", "classes_to_ignore",
    }  # fmt: skip
    assert set(record["settings"]) == mapping_keys and record["settings"]["knn"] == 1
    ade = {"name": "ade20k", "kind": "ade20k", "short_side": 576, "path": "x"}
    dataset = SimpleNamespace(reduce_zero_label=True, classes=("wall",) * 150,
                              templates="openai_imagenet")  # fmt: skip
    clip = {"kind": "clip", "dense_path": "maskclip"}
    two_d = protocol_record({"task": "ovss", "dataset": ade, "encoder": clip, "temperature": 100.0},
                            dataset)  # fmt: skip
    assert two_d == {"name": "ovss/ade20k", "settings": {
        "short_side": 576, "temperature": 100.0, "reduce_zero_label": True,
        "classes": "ade20k (150)", "templates": "open_clip OPENAI_IMAGENET_TEMPLATES (80)",
        "encoder.dense_path": "maskclip"}}  # fmt: skip
    assert protocol_text(two_d).startswith("ovss/ade20k: short_side=576, temperature=100.0, ")

    sweep = tmp_path / "sweep"
    for n, (encoder, short) in enumerate((("clip", 576), ("radio", 576), ("tips", 448))):
        job = sweep / f"{n}_encoder={encoder}"
        (job / ".hydra").mkdir(parents=True)
        (job / ".hydra" / "overrides.yaml").write_text(yaml.safe_dump([f"encoder={encoder}"]))
        rec = {"name": "ovss/ade20k", "settings": {"short_side": short}}
        results = {"status": "completed", "final": {"val/ovss/ade20k/miou_bb": 0.1},
                   "params": {"dataset": {"name": "ade20k"}, "encoder": {"name": encoder}},
                   "protocol": rec}  # fmt: skip
        (job / "results.json").write_text(json.dumps(results))
    text = write_encoder_table(collect(sweep), tmp_path)["table1_md"].read_text()
    assert "Protocol (jobs 0, 1): ovss/ade20k: short_side=576" in text
    assert "Protocol (jobs 2): ovss/ade20k: short_side=448" in text
