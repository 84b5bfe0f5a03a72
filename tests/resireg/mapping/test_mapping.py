"""resireg.mapping against independent references (numpy, scipy, hand computations).

One idea: the geometry under every map (unprojection, voxel means, label votes, nearest
neighbours, classify), each step against an independent numpy / scipy / open3d reference."""

from __future__ import annotations

import numpy as np
import pytest
import torch
import torch.nn.functional as F
from scipy.spatial.transform import Rotation

from helpers.optional import open3d
from helpers.paths import ROOT
from resireg.mapping import (
    LabelVoxelMap,
    VoxelMap,
    classify,
    nearest,
    nearest_downsample,
    patch_points,
    scale_intrinsics,
    transfer_labels,
    unproject,
    voxel_indices,
)
from resireg.mapping import voxels as voxels_module

# ScanNet-like depth camera (480 x 640) and a rotated, translated pose.
K_DEPTH = np.array([[577.6, 0.0, 318.9], [0.0, 578.7, 242.7], [0.0, 0.0, 1.0]])


def pose(seed: int) -> np.ndarray:
    """A random rigid camera-to-world transform (scipy rotation, translation in a room)."""
    rng = np.random.default_rng(seed)
    t = np.eye(4)
    t[:3, :3] = Rotation.random(random_state=seed).as_matrix()
    t[:3, 3] = rng.uniform(-4, 4, 3)
    return t


def project(world: np.ndarray, k: np.ndarray, cam_to_world: np.ndarray) -> np.ndarray:
    """Forward pinhole projection of ``[..., 3]`` world points -> ``[..., 2]`` pixel (u, v)."""
    r, t = cam_to_world[:3, :3], cam_to_world[:3, 3]
    cam = (world - t) @ r  # R^T (p - t), row vectors
    uvw = cam @ k.T
    return uvw[..., :2] / uvw[..., 2:]


def numpy_index(points: np.ndarray, v: float, lattice: str) -> np.ndarray:
    """Voxel indices: np.rint (half to even, RayFronts' torch.round) or np.floor of p / v."""
    op = np.rint if lattice == "round" else np.floor
    return op(points.astype(np.float64) / v).astype(np.int64)


def numpy_voxel_means(points: np.ndarray, feats: np.ndarray, v: float, lattice: str = "round"):
    """Reference: np.rint / np.floor indices, np.unique(axis=0), np.add.at sums, bincount."""
    idx = numpy_index(points, v, lattice)
    uniq, inv = np.unique(idx, axis=0, return_inverse=True)
    inv = inv.reshape(-1)
    sums = np.zeros((len(uniq), feats.shape[1]))
    np.add.at(sums, inv, feats.astype(np.float64))
    counts = np.bincount(inv, minlength=len(uniq))
    return uniq, counts, sums / counts[:, None]


def random_cloud(n: int, d: int, seed: int) -> tuple[torch.Tensor, torch.Tensor]:
    g = torch.Generator().manual_seed(seed)
    points = torch.rand(n, 3, generator=g) * 2.0 - 1.0  # negative coordinates included
    return points, torch.randn(n, d, generator=g)


# ----------------------------------------------------------------------------- geometry


def test_fronto_parallel_plane_unprojects_to_world_plane():
    z0, cam_to_world = 2.5, pose(1)
    depth = torch.full((1, 480, 640), z0, dtype=torch.float32)
    points, valid = unproject(
        depth, torch.tensor(K_DEPTH), torch.tensor(cam_to_world)[None].float()
    )
    assert valid.all() and points.dtype == torch.float32 and points.shape == (1, 480, 640, 3)
    p = points[0].double().numpy()
    # On the plane n . p = n . t + z0, n = the camera's optical axis in world coordinates.
    n, t = cam_to_world[:3, 2], cam_to_world[:3, 3]
    np.testing.assert_allclose(p @ n, n @ t + z0, atol=2e-6)
    # And each point projects back onto its own pixel (forward model in numpy).
    v, u = np.mgrid[0:480, 0:640]
    np.testing.assert_allclose(project(p, K_DEPTH, cam_to_world), np.stack([u, v], -1), atol=2e-3)


def test_four_pixel_hand_example():
    # fx = 2, fy = 4, cx = cy = 0.5; camera translated by (10, 20, 30), no rotation.
    k = torch.tensor([[2.0, 0.0, 0.5], [0.0, 4.0, 0.5], [0.0, 0.0, 1.0]])
    cam_to_world = torch.eye(4)
    cam_to_world[:3, 3] = torch.tensor([10.0, 20.0, 30.0])
    depth = torch.tensor([[[1.0, 2.0], [4.0, 8.0]]])
    points, valid = unproject(depth, k, cam_to_world[None])
    # (u, v, z) -> ((u - .5) z / 2, (v - .5) z / 4, z) + t
    expected = torch.tensor(
        [
            [[-0.25 + 10, -0.125 + 20, 1 + 30], [0.5 + 10, -0.25 + 20, 2 + 30]],
            [[-1.0 + 10, 0.5 + 20, 4 + 30], [2.0 + 10, 1.0 + 20, 8 + 30]],
        ]
    )
    assert valid.all()
    torch.testing.assert_close(points[0], expected, rtol=0, atol=0)


def test_invalid_depth_and_pose_are_dropped():
    depth = torch.tensor([[[0.0, float("nan")], [float("inf"), -1.0]], [[1.0, 2.0], [3.0, 0.0]]])
    poses = torch.eye(4).repeat(2, 1, 1)
    points, valid = unproject(depth, torch.eye(3), poses)
    assert valid.tolist() == [[[False, False], [False, False]], [[True, True], [True, False]]]
    assert torch.isnan(points[~valid]).all() and torch.isfinite(points[valid]).all()
    poses[1, 0, 0] = -float("inf")  # ScanNet's lost-tracking pose
    _, valid = unproject(depth, torch.eye(3), poses)
    assert not valid.any()


def test_scale_intrinsics_round_trip_and_rays():
    k = torch.tensor(K_DEPTH)
    small = scale_intrinsics(k, (480, 640), (30, 40))
    torch.testing.assert_close(scale_intrinsics(small, (30, 40), (480, 640)), k)
    # ScanNet colour 968 x 1296 resized to 640 x 864 (a non-integer factor), batched input.
    k_color = torch.tensor(
        [[1170.2, 0.0, 647.8], [0.0, 1170.2, 483.8], [0.0, 0.0, 1.0]], dtype=torch.float64
    )
    k2 = scale_intrinsics(k_color.expand(2, 3, 3), (968, 1296), (640, 864))[1].numpy()
    sx, sy = 864 / 1296, 640 / 968
    # The principal point's resized coordinate (centre convention) is the new principal point,
    # and the optical axis still passes through it.
    cx, cy = k_color[0, 2].item(), k_color[1, 2].item()
    np.testing.assert_allclose(k2[:2, 2], [(cx + 0.5) * sx - 0.5, (cy + 0.5) * sy - 0.5])
    np.testing.assert_allclose(np.linalg.solve(k2, [*k2[:2, 2], 1.0]), [0, 0, 1], atol=1e-12)
    # Any 3D point lands on the resized coordinate of its old pixel; the image edges
    # (-0.5 and W - 0.5) are the same rays before and after.
    world = np.random.default_rng(0).uniform([-1, -1, 1], [1, 1, 5], (100, 3))
    uv = project(world, k_color.double().numpy(), np.eye(4))
    uv2 = project(world, k2, np.eye(4))
    np.testing.assert_allclose(uv2, (uv + 0.5) * [sx, sy] - 0.5, atol=1e-9)
    kc = k_color.double().numpy()
    for (u, v), (u2, v2) in [((-0.5, -0.5), (-0.5, -0.5)), ((1295.5, 967.5), (863.5, 639.5))]:
        np.testing.assert_allclose(
            np.linalg.solve(kc, [u, v, 1.0]), np.linalg.solve(k2, [u2, v2, 1.0]), atol=1e-12
        )


@pytest.mark.parametrize(
    "src,dst", [((480, 640), (30, 40)), ((480, 640), (40, 54)), ((7, 5), (3, 4))]
)
def test_nearest_downsample_matches_numpy_and_torch(src, dst):
    depth = torch.rand(2, *src)
    out = nearest_downsample(depth, dst)
    rows = np.floor((np.arange(dst[0]) + 0.5) * src[0] / dst[0]).astype(int)
    cols = np.floor((np.arange(dst[1]) + 0.5) * src[1] / dst[1]).astype(int)
    np.testing.assert_array_equal(out.numpy(), depth.numpy()[:, rows][:, :, cols])
    # torch's nearest-exact computes (i + 0.5) * (W / w) in float and so may pick the lower
    # pixel when a cell centre falls exactly on a pixel edge (640 -> 54: column 40 of 54, centre 480.0);
    # ours takes the pixel starting at that edge (integer arithmetic). Elsewhere they agree.
    ref = F.interpolate(depth[:, None], size=dst, mode="nearest-exact")[:, 0]
    differ = (out != ref).any(0)
    bad_cols = torch.nonzero(differ.any(0)).flatten().tolist()
    assert bad_cols == ([40] if dst == (40, 54) else [])
    assert all(((2 * c + 1) * src[1]) % (2 * dst[1]) == 0 for c in bad_cols)  # exact ties
    if src == (480, 640) and dst == (30, 40):  # factor 16: pixel 16 i + 8
        assert rows.tolist() == [16 * i + 8 for i in range(30)]
    labels = torch.randint(0, 40, (1, *src), dtype=torch.uint8)  # any dtype, values copied
    assert set(nearest_downsample(labels, dst).unique().tolist()) <= set(labels.unique().tolist())


def test_patch_points_are_patch_centres():
    # A wall at 3 m: each patch point projects (full-resolution K) to its patch centre 16 j + 7.5.
    cam_to_world = pose(2)
    depth = torch.full((1, 480, 640), 3.0)
    points, valid = patch_points(
        depth, torch.tensor(K_DEPTH).float(), torch.tensor(cam_to_world)[None].float(), (30, 40)
    )
    assert points.shape == (1, 30, 40, 3) and valid.all()
    uv = project(points[0].double().numpy(), K_DEPTH, cam_to_world)
    i, j = np.mgrid[0:30, 0:40]
    np.testing.assert_allclose(uv, np.stack([16 * j + 7.5, 16 * i + 7.5], -1), atol=2e-3)
    depth[0, 8, 8] = 0.0  # the pixel patch (0, 0) reads
    depth[0, 7, 7] = float("nan")  # not read
    _, valid = patch_points(depth, torch.tensor(K_DEPTH), torch.eye(4)[None], (30, 40))
    assert not valid[0, 0, 0] and valid.sum() == 30 * 40 - 1


def test_geometry_input_errors():
    k = torch.eye(3)
    with pytest.raises(ValueError, match="depth of dtype torch.int32"):
        unproject(torch.ones(1, 2, 2, dtype=torch.int32), k, torch.eye(4)[None])
    with pytest.raises(ValueError, match=r"intrinsics of shape \(2, 3, 3\)"):
        unproject(torch.ones(1, 2, 2), torch.eye(3).repeat(2, 1, 1), torch.eye(4)[None])
    with pytest.raises(ValueError, match=r"cam_to_world of shape \(4, 4\)"):
        unproject(torch.ones(1, 2, 2), k, torch.eye(4))
    with pytest.raises(ValueError, match=r"to_hw=\(0, 4\)"):
        scale_intrinsics(k, (2, 2), (0, 4))
    with pytest.raises(ValueError, match=r"grid=\(2.5, 4\)"):
        patch_points(torch.ones(1, 8, 8), k, torch.eye(4)[None], (2.5, 4))
    with pytest.raises(ValueError, match=r"depth of shape \(8, 8\)"):
        patch_points(torch.ones(8, 8), k, torch.eye(4)[None], (2, 2))


# ----------------------------------------------------------------------------- VoxelMap


@pytest.mark.parametrize("lattice", ["round", "floor"])
@pytest.mark.parametrize("voxel_size", [0.05, 0.2, 0.3])
def test_voxel_means_equal_numpy(voxel_size, lattice):
    points, feats = random_cloud(3000, 12, seed=1)
    vmap = VoxelMap(voxel_size, 12, lattice=lattice)
    vmap.add(points, feats)
    uniq, counts, means = numpy_voxel_means(points.numpy(), feats.numpy(), voxel_size, lattice)
    assert len(vmap) == len(uniq)
    np.testing.assert_array_equal(vmap.indices.numpy(), uniq)
    np.testing.assert_array_equal(vmap.counts.numpy(), counts)
    np.testing.assert_allclose(vmap.means().numpy(), means, rtol=1e-12, atol=1e-15)
    centres, unit = vmap.features()
    if lattice == "round":  # RayFronts' centres: float32(index) * v in float32, bit for bit
        expect = uniq.astype(np.float32) * np.float32(voxel_size)
        np.testing.assert_array_equal(centres.numpy(), expect)
    else:
        np.testing.assert_allclose(centres.numpy(), ((uniq + 0.5) * voxel_size), atol=1e-6)
    ref = means / np.maximum(np.linalg.norm(means, axis=1, keepdims=True), 1e-12)
    assert unit.dtype == torch.float32 and centres.dtype == torch.float32
    np.testing.assert_allclose(unit.numpy(), ref, atol=1e-6)


def test_voxel_means_do_not_depend_on_splits_or_order(monkeypatch):
    monkeypatch.setattr(voxels_module, "_CHUNK_ELEMENTS", 40)  # exercise the chunked scatter
    points, feats = random_cloud(2000, 8, seed=2)
    uniq, counts, means = numpy_voxel_means(points.numpy(), feats.numpy(), 0.1)
    rng = np.random.default_rng(3)
    for _ in range(4):
        order = torch.from_numpy(rng.permutation(len(points)))
        cuts = np.sort(
            rng.choice(np.arange(1, len(points)), size=rng.integers(1, 30), replace=False)
        )
        vmap = VoxelMap(0.1, 8)
        for chunk in np.split(order.numpy(), cuts):
            vmap.add(points[chunk], feats[chunk])
        vmap.add(points[:0], feats[:0])  # an empty frame is a no-op
        np.testing.assert_array_equal(vmap.indices.numpy(), uniq)
        np.testing.assert_array_equal(vmap.counts.numpy(), counts)
        np.testing.assert_allclose(vmap.means().numpy(), means, rtol=1e-12, atol=1e-15)
    ref = means / np.linalg.norm(means, axis=1, keepdims=True)
    np.testing.assert_allclose(vmap.features()[1].numpy(), ref, atol=1e-6)  # chunked rows


def test_voxel_means_equal_open3d_voxel_down_sample():
    """Open3D's VoxelDownSample as a second reference (test-only; skipped if not importable).

    Open3D's grid starts at the cloud's minimum minus half a voxel, so a point at
    (v/2, v/2, v/2) that is the minimum on every axis puts its grid edges at 0, ours. Its
    output (mean position and mean colour per voxel, hash-map order) is sorted by voxel.
    """
    o3d = open3d()
    v = 0.25
    rng = np.random.default_rng(9)
    xyz = np.concatenate([[[v / 2] * 3], rng.uniform(v / 2 + 1e-6, 3.0, (3000, 3))])
    rgb = rng.uniform(0, 1, (len(xyz), 3))
    cloud = o3d.geometry.PointCloud(o3d.utility.Vector3dVector(xyz))
    cloud.colors = o3d.utility.Vector3dVector(rgb)
    down = cloud.voxel_down_sample(v)
    ref_xyz, ref_rgb = np.asarray(down.points), np.asarray(down.colors)
    order = np.lexsort(np.floor(ref_xyz / v).T[::-1])
    vmap = VoxelMap(v, 6, lattice="floor")
    vmap.add(torch.from_numpy(xyz), torch.from_numpy(np.concatenate([xyz, rgb], 1)))
    assert len(vmap) == len(ref_xyz)
    np.testing.assert_array_equal(vmap.indices.numpy(), np.floor(ref_xyz[order] / v))
    np.testing.assert_allclose(vmap.means().numpy()[:, :3], ref_xyz[order], rtol=1e-12)
    np.testing.assert_allclose(vmap.means().numpy()[:, 3:], ref_rgb[order], rtol=1e-12)


def test_voxel_boundaries_and_large_coordinates():
    # floor: points exactly on voxel faces belong to the upper voxel; -0.05 to index -1.
    pts = torch.tensor(
        [[0.0, 0.0, 0.0], [0.05, -0.05, 0.0999], [-1e-9, 0.0, 0.0], [1000.0, -2000.0, 50.0]],
        dtype=torch.float64,
    )
    vmap = VoxelMap(0.05, 2, lattice="floor")
    vmap.add(pts, torch.ones(4, 2))
    expected = np.floor(pts.numpy() / 0.05).astype(np.int64)
    np.testing.assert_array_equal(vmap.indices.numpy(), np.unique(expected, axis=0))
    # round: voxel faces at (i + 1/2) v, a point exactly on one goes to the even index
    # (torch.round, as RayFronts): at 0.25 m, +-0.125 -> 0, 0.375 -> 2; 0.24 -> 1, -0.26 -> -1.
    half = torch.tensor([[0.125, -0.125, 0.375], [0.24, 0.26, -0.26]], dtype=torch.float64)
    rmap = VoxelMap(0.25, 2)
    rmap.add(half, torch.ones(2, 2))
    assert sorted(map(tuple, rmap.indices.tolist())) == [(0, 0, 2), (1, 1, -1)]
    with pytest.raises(ValueError, match="voxel indices beyond"):
        vmap.add(torch.tensor([[1e6, 0.0, 0.0]]), torch.ones(1, 2))


def test_voxel_map_device_and_growth():
    meta = VoxelMap(0.1, 4, device="meta")
    assert meta.device == torch.device("meta") and len(meta) == 0
    assert meta._sums.device.type == "meta" and meta.centres().device.type == "meta"
    vmap = VoxelMap(0.1, 4, device=torch.device("cpu"))
    for seed in range(5):  # several capacity increases
        points, feats = random_cloud(200 * (seed + 1), 4, seed)
        vmap.add(points * (seed + 1), feats.double())
    for t in (vmap.counts, vmap.indices, vmap.centres(), *vmap.features(), vmap._sums):
        assert t.device == vmap.device


def test_voxel_map_reserve_clone_and_nbytes():
    points, feats = random_cloud(500, 4, seed=10)
    vmap = VoxelMap(0.5, 4)
    vmap.add(points[:250], feats[:250])
    m = len(vmap)
    vmap.reserve(1000)
    # sums and counts of 1000 rows; the keys (and the index's sentinel) and a hash table of
    # 256 int32 slots (the first power of two that holds 96 keys at most 70% full)
    assert m == 96
    assert vmap.nbytes == 1000 * (4 * 8 + 8) + (m + 1) * 8 + 256 * 4
    copy = vmap.clone()
    copy.add(points[250:], feats[250:])
    assert len(vmap) == m and vmap.counts.sum() == 250 and copy.counts.sum() == 500
    # no more accumulator rows within the reserve
    assert copy.nbytes - copy._index.nbytes == 1000 * 40
    uniq, counts, means = numpy_voxel_means(points.numpy(), feats.numpy(), 0.5)
    np.testing.assert_allclose(copy.means().numpy(), means, rtol=1e-12)


@pytest.mark.skipif(not torch.cuda.is_available(), reason="needs CUDA")
def test_voxel_map_cuda_equals_cpu():
    points, feats = random_cloud(5000, 16, seed=4)
    cpu, gpu = VoxelMap(0.1, 16), VoxelMap(0.1, 16, device="cuda")
    for chunk in torch.arange(5000).split(700):
        cpu.add(points[chunk], feats[chunk])
        gpu.add(points[chunk].cuda(), feats[chunk].cuda())
    assert all(t.is_cuda for t in (*gpu.features(), gpu.counts, gpu.indices))
    torch.testing.assert_close(gpu.indices.cpu(), cpu.indices)
    torch.testing.assert_close(gpu.means().cpu(), cpu.means(), rtol=1e-12, atol=1e-15)
    labels = LabelVoxelMap(0.1, 5, device="cuda")
    labels.add(points.cuda(), torch.arange(5000).cuda() % 7)
    ref = LabelVoxelMap(0.1, 5)
    ref.add(points, torch.arange(5000) % 7)
    torch.testing.assert_close(labels.votes.cpu(), ref.votes)
    cls = classify(gpu.features()[1], torch.randn(5, 16, device="cuda"))
    assert cls.is_cuda


def test_voxel_map_input_errors():
    for bad in (0, -0.1, float("nan"), float("inf"), "a", True):
        with pytest.raises(ValueError, match="voxel_size="):
            VoxelMap(bad, 4)
    with pytest.raises(ValueError, match="dim=0"):
        VoxelMap(0.1, 0)
    vmap = VoxelMap(0.1, 4)
    with pytest.raises(ValueError, match=r"features of shape \(3, 5\): the map has dim=4"):
        vmap.add(torch.zeros(3, 3), torch.zeros(3, 5))
    with pytest.raises(ValueError, match=r"points of shape \(3, 2\)"):
        vmap.add(torch.zeros(3, 2), torch.zeros(3, 4))
    with pytest.raises(ValueError, match=r"expected 2 rows"):
        vmap.add(torch.zeros(3, 3), torch.zeros(2, 4))
    with pytest.raises(ValueError, match="non-finite"):
        vmap.add(torch.tensor([[0.0, float("nan"), 0.0]]), torch.zeros(1, 4))
    assert len(vmap) == 0


# ----------------------------------------------------------------------------- LabelVoxelMap


def test_label_votes_and_argmax_equal_numpy():
    points, _ = random_cloud(4000, 1, seed=5)
    rng = np.random.default_rng(5)
    labels = rng.choice([0, 1, 2, 3, 4, 255, -1, 7], size=4000, p=[0.2] * 4 + [0.05] * 4)
    lmap = LabelVoxelMap(0.2, 5)
    for chunk in np.array_split(rng.permutation(4000), 7):
        lmap.add(points[chunk], torch.from_numpy(labels[chunk]).to(torch.int16))
    keep = (labels >= 0) & (labels < 5)
    idx = numpy_index(points.numpy()[keep], 0.2, "round")
    uniq, inv = np.unique(idx, axis=0, return_inverse=True)
    votes = np.zeros((len(uniq), 5), dtype=np.int64)
    np.add.at(votes, (inv.reshape(-1), labels[keep]), 1)
    np.testing.assert_array_equal(lmap.indices.numpy(), uniq)
    np.testing.assert_array_equal(lmap.votes.numpy(), votes)
    centres, winners = lmap.labels()
    np.testing.assert_array_equal(winners.numpy(), np.argmax(votes, axis=1))  # first max
    np.testing.assert_allclose(centres.numpy(), uniq * 0.2, atol=1e-6)
    assert lmap.ignored == int((labels == 255).sum())
    assert lmap.out_of_range == int(((labels == -1) | (labels == 7)).sum())


def test_label_tie_goes_to_lowest_id_and_ignored_make_no_voxel():
    lmap = LabelVoxelMap(1.0, 6, ignore_index=255)
    inside = torch.tensor([[0.1, 0.1, 0.1]]).repeat(4, 1)
    lmap.add(inside, torch.tensor([3, 1, 3, 1]))  # 2 votes each for 3 and 1
    lmap.add(torch.tensor([[5.5, 0.0, 0.0], [6.5, 0.0, 0.0]]), torch.tensor([255, 255]))
    centres, winners = lmap.labels()
    assert winners.tolist() == [1] and centres.tolist() == [[0.0, 0.0, 0.0]]
    assert lmap.counts.tolist() == [4] and lmap.ignored == 2 and lmap.out_of_range == 0
    with pytest.raises(ValueError, match="ignore_index=3"):
        LabelVoxelMap(1.0, 6, ignore_index=3)
    with pytest.raises(ValueError, match="labels of dtype torch.float32"):
        lmap.add(inside, torch.zeros(4))


# ----------------------------------------------------------------------------- queries


def test_nearest_and_transfer_equal_brute_force():
    rng = np.random.default_rng(6)
    source, targets = rng.uniform(-3, 3, (700, 3)), rng.uniform(-3.5, 3.5, (400, 3))
    labels = rng.integers(0, 37, 700)
    dists = np.linalg.norm(targets[:, None] - source[None], axis=2)
    ref = np.argmin(dists, axis=1)
    got = nearest(torch.from_numpy(source).float(), torch.from_numpy(targets).float())
    assert got.dtype == torch.int64
    np.testing.assert_array_equal(got.numpy(), ref)
    moved = transfer_labels(
        torch.from_numpy(source), torch.from_numpy(labels), torch.from_numpy(targets)
    )
    np.testing.assert_array_equal(moved.numpy(), labels[ref])
    with pytest.raises(ValueError, match=r"labels of shape \(3,\)"):
        transfer_labels(torch.from_numpy(source), torch.zeros(3), torch.from_numpy(targets))
    with pytest.raises(ValueError, match="source of shape"):
        nearest(torch.zeros(0, 3), torch.zeros(2, 3))


def test_classify_equals_numpy_cosine_argmax(monkeypatch):
    from resireg.mapping import query

    monkeypatch.setattr(query, "_CHUNK_ELEMENTS", 64)  # several chunks
    rng = np.random.default_rng(7)
    feats, protos = (
        rng.normal(size=(500, 16)),
        rng.normal(size=(7, 16)) * rng.uniform(0.1, 9, (7, 1)),
    )
    feats[0] = 0.0  # zero feature: all cosines 0 -> class 0
    fn = feats / np.maximum(np.linalg.norm(feats, axis=1, keepdims=True), 1e-12)
    pn = protos / np.linalg.norm(protos, axis=1, keepdims=True)
    ref = np.argmax(fn @ pn.T, axis=1)
    got = classify(torch.from_numpy(feats).float(), torch.from_numpy(protos).float())
    np.testing.assert_array_equal(got.numpy(), ref)
    with pytest.raises(ValueError, match=r"prototypes of shape \(7, 15\)"):
        classify(torch.from_numpy(feats), torch.zeros(7, 15))


def test_fused_plane_frames_map_to_wall_voxels():
    """End to end: two frames of one wall fuse into the voxels a numpy pipeline predicts."""
    k = torch.tensor(K_DEPTH).float()
    poses = torch.tensor(np.stack([pose(8), pose(8)]))
    poses[1, :3, 3] += torch.tensor([0.03, 0.0, 0.0], dtype=torch.float64)  # a small step
    depth = torch.full((2, 480, 640), 2.0)
    points, valid = patch_points(depth, k, poses.float(), (30, 40))
    feats = torch.randn(2, 30, 40, 6)
    vmap = VoxelMap(0.1, 6)
    vmap.add(points[valid], feats[valid])
    # numpy: patch centre pixels (16 j + 7.5, 16 i + 7.5) with the full-resolution K
    i, j = np.mgrid[0:30, 0:40]
    rays = (
        np.stack(
            [
                (16 * j + 7.5 - K_DEPTH[0, 2]) / K_DEPTH[0, 0],
                (16 * i + 7.5 - K_DEPTH[1, 2]) / K_DEPTH[1, 1],
                np.ones((30, 40)),
            ],
            -1,
        )
        * 2.0
    )
    world = np.concatenate([rays.reshape(-1, 3) @ p[:3, :3].T + p[:3, 3] for p in poses.numpy()])
    uniq, counts, means = numpy_voxel_means(world, feats.reshape(-1, 6).numpy(), 0.1)
    np.testing.assert_array_equal(vmap.indices.numpy(), uniq)
    np.testing.assert_allclose(vmap.means().numpy(), means, rtol=1e-6, atol=1e-6)


# ----------------------------------------------------------------------------- the benchmark


def test_bench_mapping_smoke_and_its_room_is_the_box():
    """benchmarks/bench_mapping.py: sections 1 and 4 run, and its ray-cast depth lies on the
    room."""
    import importlib.util

    path = ROOT / "benchmarks" / "bench_mapping.py"
    spec = importlib.util.spec_from_file_location("bench_mapping", path)
    bench = importlib.util.module_from_spec(spec)
    spec.loader.exec_module(bench)
    report = bench.main(["--smoke", "--sections", "1", "4"])
    assert set(report) == {"fusion", "lifting"} and report["fusion"]["ReSiReg"]["voxels"] > 0
    assert [r["grid"] for r in report["lifting"]] == ["VLM", "ReSiReg"]
    assert all(r["pairs_per_patch"] >= 1 and r["pairs"] > 0 for r in report["lifting"])
    depth, k, poses = next(bench.room_frames(3, (48, 64), batch=3))
    points, valid = unproject(depth, k, poses)
    assert 0.9 < valid.float().mean() < 1.0  # 2% holes
    p = points[valid].double().numpy()
    room = np.array(bench.ROOM)
    # Distance to the nearest face of the 8 x 8 x 3 m box: depth noise only (sigma 1 cm along
    # the ray, so at most ~5 sigma off the face).
    face_dist = np.minimum(np.abs(p), np.abs(p - room)).min(axis=1)
    assert face_dist.max() < 0.06 and np.median(face_dist) < 0.01


def test_coordinates_beyond_int64_are_refused_before_packing():
    """A coordinate whose voxel index does not fit int64 (1e20 m at 5 cm: 2e21) is refused
    before the cast, which would turn it into -2**63 and pack it into a wrong voxel; the map
    keeps what it had."""
    vmap = VoxelMap(0.05, 2)
    vmap.add(torch.tensor([[1.0, 2.0, 3.0]]), torch.ones(1, 2))
    for far in (1e20, 1e30, 3.4e38):
        with pytest.raises(ValueError, match="voxel indices beyond"):
            vmap.add(torch.tensor([[far, 0.0, 0.0]]), torch.ones(1, 2))
        with pytest.raises(ValueError, match="voxel indices beyond"):
            voxel_indices(torch.tensor([[0.0, -far, 0.0]], dtype=torch.float64), 0.05)
    assert vmap.indices.tolist() == [[20, 40, 60]]
