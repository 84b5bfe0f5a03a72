"""Cost of 3D semantic mapping with ``resireg.mapping``: fusion, per-frame split, scene memory.

Setting. A synthetic ScanNet-like recording: a depth camera (480 x 640, ScanNet's depth
intrinsics) walks two loops of an ellipse inside an 8 x 8 x 3 m room (height 1.2-1.6 m, yaw
two full turns, pitch -25 to -5 degrees) and sees the room's six faces; depth is ray-cast
exactly against the box, with 1 cm Gaussian noise and 2% of the pixels dropped (depth 0) like
a sensor's holes. Frame ``i`` of ``n`` is the ``i``-th of ``n`` equally spaced poses of the
loop, so ``--frames 500`` is a ScanNet scene of ~5,000 frames at frame skip 10. Features are
random unit vectors (the fusion cost does not depend on their values), ``--dim 512``.
The RGB frame is 640 x 864 at patch 16: the VLM's grid is 40 x 54 (``bb``), ReSiReg's (upscale
2) 80 x 108; the depth is nearest-downsampled to the feature grid (``patch_points``).

1. Fusion throughput: ``VoxelMap.add`` of every frame's valid patch points (voxel
   ``--voxel`` 0.05 m), frame after frame into one growing map, for both grids; the points
   are unprojected before the timed loop. Points per second = points fused / seconds in
   ``add``.
2. Per-frame cost split at 640 x 864 with a batch of ``--batch`` (8) consecutive frames: the
   25M VLM's ``encode`` (random weights of the real architecture, built as in
   ``bench_throughput.py``: ``conf/model/backbone/eupe_vit_s16.yaml`` with ``weights: null``
   and the head of ``conf/model/vlm25m.yaml``; fp32 on the CPU), ReSiReg Lite and Full on its
   output (``conf/resireg/default.yaml``), ``patch_points`` of the 8 depth frames to
   ReSiReg's grid, and ``VoxelMap.add`` of the 8 frames into a map already holding the first
   ``--frames`` // 5 frames (with reserve for the new voxels: no capacity increase is timed). Each stage is warmed up once, then timed ``--repeats`` times;
   the median per batch and per frame are reported.
3. Whole-scene memory: ``--frames`` frames fused at ReSiReg's grid (and the VLM's) at 0.05
   and 0.2 m, each in a fresh process (``multiprocessing`` spawn) so that its peak resident
   set (``VmHWM``, :func:`peak_rss_mb`) is its own; reported with the resident set before the
   first frame, the bytes the map's tensors hold (``VoxelMap.nbytes``, reserve included), the
   voxel count and the seconds spent in ``add``.

4. Lifting under the literal reading (``dataset.points: pixel``) against today's per-patch
   fusion (``points: patch``), per frame at the protocol's RGB-D resolution 640 x 864 (the
   room ray-cast at that size, ScanNet's intrinsics scaled by ``c s``), ``--dim`` features, voxel
   ``--voxel``, for both grids: ``patch`` = ``patch_points`` + ``VoxelMap.add``; ``pairs`` =
   ``pixel_pairs`` + ``VoxelMap.add_pairs`` (every pixel at its patch's depth, fused as (patch,
   voxel, count) pairs); ``per pixel`` = ``pixel_points`` + ``VoxelMap.add`` of every pixel with
   its patch's feature (the same voxel means, computed point by point). Each into a copy of a
   map already holding ``--warm`` frames lifted the same way (with reserve), one frame per call;
   the three alternate within each of ``--repeats`` rounds (after a warm-up round), medians
   reported, with the ratio to ``patch`` and the (patch, voxel) pairs per patch.

``--smoke`` runs everything with tiny sizes (tiny VLM, 48 x 64 depth, 64 x 96 images, 12
frames, dim 16): seconds for sections 1 and 2, about half a minute with section 3 (its four
processes each import torch).

    python benchmarks/bench_mapping.py [--frames 500] [--dim 512] [--voxel 0.05] [--batch 8]
        [--repeats 3] [--warm 10] [--threads N] [--sections 1 2 3 4] [--smoke]

On a shared machine, ``--threads 1`` gives steadier figures: with more threads than free
cores, torch's OpenMP workers wait on each other (here, 2 cores under a load of 8: ``argsort``
and ``index_add_`` 10-20x slower at 2 threads than at 1).
"""

from __future__ import annotations

import argparse
import math
import multiprocessing
import resource
import statistics
import time
from collections.abc import Iterator, Sequence
from typing import Any

import torch

from _common import build_model, median_seconds, resireg_defaults
from resireg.mapping import VoxelMap, patch_points, pixel_pairs, pixel_points

ROOM = (8.0, 8.0, 3.0)
#: ScanNet's depth intrinsics (scene0050_00, 480 x 640).
K_DEPTH = torch.tensor(
    [[577.59, 0.0, 318.91], [0.0, 578.73, 242.68], [0.0, 0.0, 1.0]], dtype=torch.float64
)


# --------------------------------------------------------------------------- the synthetic scene
def camera_pose(t: float) -> torch.Tensor:
    """Camera-to-world ``[4, 4]`` at loop parameter ``t`` in ``[0, 1)`` (OpenCV camera axes)."""
    a = 4 * math.pi * t  # two loops of the ellipse
    position = torch.tensor(
        [4 + 2.5 * math.cos(a), 4 + 2.0 * math.sin(a), 1.4 + 0.2 * math.sin(3 * a)],
        dtype=torch.float64,
    )
    yaw = 2 * a + 0.5 * math.sin(5 * a)
    pitch = math.radians(-15 + 10 * math.sin(7 * a))
    forward = torch.tensor(
        [math.cos(yaw) * math.cos(pitch), math.sin(yaw) * math.cos(pitch), math.sin(pitch)],
        dtype=torch.float64,
    )
    right = torch.linalg.cross(forward, torch.tensor([0.0, 0.0, 1.0], dtype=torch.float64))
    right = right / right.norm()
    down = torch.linalg.cross(forward, right)
    pose = torch.eye(4, dtype=torch.float64)
    pose[:3, :3] = torch.stack([right, down, forward], dim=1)
    pose[:3, 3] = position
    return pose


def ray_cast(pose: torch.Tensor, hw: tuple[int, int], k: torch.Tensor, gen: torch.Generator):
    """Depth ``[H, W]`` float32 of the room's inside faces seen from ``pose`` (noise, holes)."""
    h, w = hw
    v, u = torch.meshgrid(
        torch.arange(h, dtype=torch.float64), torch.arange(w, dtype=torch.float64), indexing="ij"
    )
    rays = torch.stack([u, v, torch.ones_like(u)], -1) @ torch.linalg.inv(k).T  # camera z = 1
    d = rays @ pose[:3, :3].T  # world directions; distance along them = z-depth
    o = pose[:3, 3]
    hi = torch.tensor(ROOM, dtype=torch.float64)
    with torch.no_grad():
        t_hi = torch.where(d > 0, (hi - o) / d, math.inf)
        t_lo = torch.where(d < 0, (0 - o) / d, math.inf)
    depth = torch.minimum(t_hi, t_lo).amin(-1)
    depth = depth + 0.01 * torch.randn(depth.shape, generator=gen, dtype=torch.float64)
    depth[torch.rand(depth.shape, generator=gen) < 0.02] = 0.0
    return depth.to(torch.float32)


def room_frames(
    n_frames: int, hw: tuple[int, int], batch: int = 1, seed: int = 0
) -> Iterator[tuple[torch.Tensor, torch.Tensor, torch.Tensor]]:
    """Batches of consecutive frames: depth ``[b, H, W]``, intrinsics ``[3, 3]``, poses ``[b, 4, 4]``."""
    k = K_DEPTH.clone()
    if hw != (480, 640):
        k[0] *= hw[1] / 640
        k[1] *= hw[0] / 480
    gen = torch.Generator().manual_seed(seed)
    for start in range(0, n_frames, batch):
        idx = range(start, min(start + batch, n_frames))
        poses = torch.stack([camera_pose(i / n_frames) for i in idx])
        depth = torch.stack([ray_cast(p, hw, k, gen) for p in poses])
        yield depth, k.to(torch.float32), poses.to(torch.float32)


def random_features(n: int, dim: int, gen: torch.Generator) -> torch.Tensor:
    f = torch.randn(n, dim, generator=gen)
    return f / f.norm(dim=1, keepdim=True)


def scene_points(n_frames: int, hw, grid, seed: int = 0) -> list[torch.Tensor]:
    """Valid patch points ``[n_i, 3]`` of every frame."""
    out = []
    for depth, k, poses in room_frames(n_frames, hw, batch=8, seed=seed):
        points, valid = patch_points(depth, k, poses, grid)
        out.extend(p[m] for p, m in zip(points, valid, strict=True))
    return out


# --------------------------------------------------------------------------- measurements
def fusion_throughput(frames: list[torch.Tensor], voxel: float, dim: int) -> dict[str, float]:
    """Fuse the frames one by one into a new map; seconds in ``add`` only."""
    gen = torch.Generator().manual_seed(1)
    pool = [random_features(max(len(p) for p in frames), dim, gen) for _ in range(4)]
    VoxelMap(voxel, dim).add(frames[0], pool[0][: len(frames[0])])  # warm-up
    vmap = VoxelMap(voxel, dim)
    seconds = 0.0
    for i, p in enumerate(frames):
        f = pool[i % len(pool)][: len(p)]
        start = time.perf_counter()
        vmap.add(p, f)
        seconds += time.perf_counter() - start
    n = sum(len(p) for p in frames)
    return {"points": n, "seconds": seconds, "voxels": len(vmap), "mb": vmap.nbytes / 2**20}


def cost_split(args: argparse.Namespace) -> list[tuple[str, float]]:
    """Median seconds per batch of each stage (section 2 of the docstring)."""
    from resireg.method.variants import build_variant

    torch.manual_seed(0)
    model = build_model(args.smoke)
    cfg = resireg_defaults()
    lite, full = build_variant("lite", **cfg["lite"]), build_variant("full", **cfg["full"])
    x = torch.randn(args.batch, 3, *args.image)
    with torch.no_grad():
        out = model.encode(x)
        rows = [("encode (VLM, bb)", median_seconds(lambda: model.encode(x), args.repeats))]
        for name, variant in (("ReSiReg Lite", lite), ("ReSiReg Full", full)):
            seconds = median_seconds(
                lambda v=variant: v(out.intermediates, out.language), args.repeats
            )
            rows.append((name, seconds))
        grid = tuple(lite(out.intermediates, out.language).shape[-2:])
    depth, k, poses = next(room_frames(args.batch, args.depth_hw, batch=args.batch, seed=3))
    rows.append(
        (
            f"unproject ({grid[0]} x {grid[1]})",
            median_seconds(lambda: patch_points(depth, k, poses, grid), args.repeats),
        )
    )
    points, valid = patch_points(depth, k, poses, grid)
    feats = random_features(int(valid.sum()), args.dim, torch.Generator().manual_seed(2))
    warm = scene_points(max(1, args.frames // 5), args.depth_hw, grid, seed=4)
    base = VoxelMap(args.voxel, args.dim)
    gen = torch.Generator().manual_seed(5)
    for p in warm:
        base.add(p, random_features(len(p), args.dim, gen))

    # A copy of the warm map per call, so every timed call adds to the same state, with room
    # for every new point, so no call pays for a capacity increase (their amortised cost is in
    # section 1's figures). The first call is the warm-up.
    times = []
    for _ in range(args.repeats + 1):
        vmap = base.clone()
        vmap.reserve(len(base) + len(feats))
        start = time.perf_counter()
        vmap.add(points[valid], feats)
        times.append(time.perf_counter() - start)
    rows.append((f"fuse ({len(base):,}-voxel map)", statistics.median(times[1:])))
    return rows


def lifting_cost(args: argparse.Namespace, grids: dict[str, tuple[int, int]]) -> list[dict]:
    """Section 4 of the docstring: seconds per frame of the three liftings, per grid."""
    hw = args.image
    frames = list(room_frames(args.warm + 1, hw, batch=1, seed=8))
    *warm, (depth, k, pose) = frames
    gen = torch.Generator().manual_seed(9)
    out = []
    for name, grid in grids.items():
        feats = random_features(grid[0] * grid[1], args.dim, gen)

        def patch(d, kk, p, vmap, grid=grid, feats=feats):
            points, valid = patch_points(d, kk, p, grid)
            vmap.add(points[valid], feats[valid.reshape(-1)])

        def pairs(d, kk, p, vmap, grid=grid, feats=feats):
            index, source, count = pixel_pairs(d, kk, p, grid, args.voxel)
            vmap.add_pairs(index, count, feats, source)

        def per_pixel(d, kk, p, vmap, grid=grid, feats=feats):
            points, valid, cell = pixel_points(d, kk, p, grid)
            vmap.add(points[valid], feats[cell.expand_as(valid)[valid]])

        ways = {"patch": patch, "pairs": pairs, "per pixel": per_pixel}
        bases = {}
        for way, fn in ways.items():
            base = VoxelMap(args.voxel, args.dim)
            for d, kk, p in warm:
                (pairs if way == "per pixel" else fn)(d, kk, p, base)  # same map either way
            bases[way] = base
        n_pairs = len(pixel_pairs(depth, k, pose, grid, args.voxel)[0])
        n_patches = int(patch_points(depth, k, pose, grid)[1].sum())
        # room for every voxel the frame can add (at most one per patch / per pair)
        room = {"patch": n_patches, "pairs": n_pairs, "per pixel": n_pairs}
        seconds: dict[str, list[float]] = {way: [] for way in ways}
        for _ in range(args.repeats + 1):  # the first round warms up
            for way, fn in ways.items():
                vmap = bases[way].clone()
                vmap.reserve(len(vmap) + room[way])
                start = time.perf_counter()
                fn(depth, k, pose, vmap)
                seconds[way].append(time.perf_counter() - start)
        row = {"grid": name, "hw": grid, "pairs_per_patch": n_pairs / n_patches}
        row.update({way: statistics.median(t[1:]) for way, t in seconds.items()})
        out.append(row)
    return out


def peak_rss_mb() -> float:
    """Peak resident set of this process's address space (``VmHWM`` of /proc/self/status).

    Not ``getrusage``'s ``ru_maxrss``: Linux carries that across fork and exec, so a spawned
    child would report its parent's peak.
    """
    with open("/proc/self/status") as f:
        for line in f:
            if line.startswith("VmHWM:"):
                return int(line.split()[1]) / 1024
    return resource.getrusage(resource.RUSAGE_SELF).ru_maxrss / 1024


def _scene_job(job: dict[str, Any]) -> dict[str, Any]:
    """One whole scene in a fresh process: resident set before and at peak, map figures."""
    torch.set_num_threads(job["threads"])
    gen = torch.Generator().manual_seed(6)
    vmap = VoxelMap(job["voxel"], job["dim"])
    n_points, seconds = 0, 0.0
    rss_before = None
    for depth, k, poses in room_frames(job["frames"], job["depth_hw"], batch=8, seed=0):
        points, valid = patch_points(depth, k, poses, job["grid"])
        p = points[valid]
        f = random_features(len(p), job["dim"], gen)
        if rss_before is None:
            rss_before = peak_rss_mb()
        start = time.perf_counter()
        vmap.add(p, f)
        seconds += time.perf_counter() - start
        n_points += len(p)
    return {
        **job,
        "points": n_points,
        "voxels": len(vmap),
        "map_mb": vmap.nbytes / 2**20,
        "rss_before_mb": rss_before,
        "rss_peak_mb": peak_rss_mb(),
        "seconds": seconds,
    }


def scene_memory(args: argparse.Namespace, grids: dict[str, tuple[int, int]]) -> list[dict]:
    jobs = [
        {
            "voxel": v,
            "grid": g,
            "grid_name": name,
            "dim": args.dim,
            "frames": args.frames,
            "depth_hw": args.depth_hw,
            "threads": torch.get_num_threads(),
        }
        for name, g in grids.items()
        for v in args.scene_voxels
    ]
    ctx = multiprocessing.get_context("spawn")
    results = []
    for job in jobs:  # one process per job, one at a time
        with ctx.Pool(1) as pool:
            results.append(pool.apply(_scene_job, (job,)))
    return results


# --------------------------------------------------------------------------- main
def _parse(argv: Sequence[str] | None) -> argparse.Namespace:
    parser = argparse.ArgumentParser(
        description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter
    )
    parser.add_argument("--frames", type=int, default=500, help="frames of the scene")
    parser.add_argument("--dim", type=int, default=512)
    parser.add_argument("--voxel", type=float, default=0.05)
    parser.add_argument("--scene-voxels", type=float, nargs="+", default=[0.05, 0.2])
    parser.add_argument("--batch", type=int, default=8)
    parser.add_argument("--repeats", type=int, default=3)
    parser.add_argument("--warm", type=int, default=10, help="frames in the map (section 4)")
    parser.add_argument(
        "--sections",
        type=int,
        nargs="+",
        choices=[1, 2, 3, 4],
        default=[1, 2, 3, 4],
        help="which measurements to run (docstring)",
    )
    parser.add_argument("--smoke", action="store_true", help="tiny sizes (docstring)")
    parser.add_argument(
        "--threads", type=int, default=None, help="torch threads (default: torch's choice)"
    )
    args = parser.parse_args(argv)
    args.image, args.depth_hw, args.patch = (640, 864), (480, 640), 16
    if args.smoke:
        args.image, args.depth_hw, args.frames, args.dim = (64, 96), (48, 64), 12, 16
        args.batch, args.repeats, args.warm = 2, 1, 2
    return args


def main(argv: Sequence[str] | None = None) -> dict[str, Any]:
    args = _parse(argv)
    if args.threads:
        torch.set_num_threads(args.threads)
    h, w = (s // args.patch for s in args.image)
    grids = {"VLM": (h, w), "ReSiReg": (2 * h, 2 * w)}
    print(
        f"threads {torch.get_num_threads()}, image {args.image[0]}x{args.image[1]}, depth "
        f"{args.depth_hw[0]}x{args.depth_hw[1]}, {args.frames} frames, dim {args.dim}"
    )

    report: dict[str, Any] = {}
    if 1 in args.sections:
        print(f"\n1. Fusion throughput, VoxelMap on CPU, voxel {args.voxel} m, dim {args.dim}")
        print(
            "grid      | points/frame | points   | seconds | points/s  | ms/frame | voxels  | map MB"
        )
        report["fusion"] = {}
        for name, grid in grids.items():
            frames = scene_points(args.frames, args.depth_hw, grid)
            r = fusion_throughput(frames, args.voxel, args.dim)
            report["fusion"][name] = r
            print(
                f"{name:7s} {grid[0]:>3d}x{grid[1]:<3d} | {r['points'] / len(frames):12,.0f} | "
                f"{r['points']:8,d} | {r['seconds']:7.2f} | {r['points'] / r['seconds']:9,.0f} | "
                f"{1000 * r['seconds'] / len(frames):8.2f} | {r['voxels']:7,d} | {r['mb']:6.1f}"
            )

    if 2 in args.sections:
        print(
            f"\n2. Per-frame cost at {args.image[0]}x{args.image[1]}, batch of {args.batch} "
            f"consecutive frames, median of {args.repeats}"
        )
        rows = cost_split(args)
        total = sum(s for name, s in rows if name != "ReSiReg Lite")
        print("stage                      | s/batch | ms/frame | share of bb+Full+map")
        for name, s in rows:
            share = "" if name == "ReSiReg Lite" else f"{s / total:6.1%}"
            print(f"{name:26s} | {s:7.3f} | {1000 * s / args.batch:8.1f} | {share}")
        report["split"] = rows

    if 3 in args.sections:
        print(f"\n3. Whole-scene memory, {args.frames} frames, dim {args.dim}, one process each")
        print(
            "grid    | voxel m | points     | voxels  | map MB | peak RSS before 1st add MB "
            "| peak RSS MB | add s"
        )
        report["scene"] = scene_memory(args, grids)
        for r in report["scene"]:
            print(
                f"{r['grid_name']:7s} | {r['voxel']:7.2f} | {r['points']:10,d} | "
                f"{r['voxels']:7,d} | {r['map_mb']:6.1f} | {r['rss_before_mb']:26.0f} | "
                f"{r['rss_peak_mb']:11.0f} | {r['seconds']:5.1f}"
            )
    if 4 in args.sections:
        print(
            f"\n4. Lifting per frame at {args.image[0]}x{args.image[1]}, dim {args.dim}, voxel "
            f"{args.voxel} m, into a {args.warm}-frame map, median of {args.repeats} alternating"
        )
        print("grid          | pairs per patch | patch ms | pairs ms | per pixel ms | "
              "pairs / patch (time) | per pixel / patch (time)")  # fmt: skip
        report["lifting"] = lifting_cost(args, grids)
        for r in report["lifting"]:
            print(
                f"{r['grid']:7s} {r['hw'][0]:>3d}x{r['hw'][1]:<3d} | {r['pairs_per_patch']:15.2f} | "
                f"{1000 * r['patch']:8.1f} | {1000 * r['pairs']:8.1f} | "
                f"{1000 * r['per pixel']:12.1f} | {r['pairs'] / r['patch']:20.2f} | "
                f"{r['per pixel'] / r['patch']:24.1f}"
            )
    return report


if __name__ == "__main__":
    main()
