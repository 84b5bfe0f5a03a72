"""Throughput of ``resireg-map``'s path on this CPU: bag decoding, fusion, end to end, memory.

Setting. The ray-cast room of :mod:`resireg_train.data.room_bag` recorded as a ROS 2 bag
(sqlite3) at ``--size`` (480 x 640, a RealSense / ScanNet depth resolution; PNG colour as
``CompressedImage``, 16UC1 depth, CameraInfo, the tf tree with a static camera offset),
``--frames`` frames. Models: the tests' tiny VLM and the 25M architecture (EUPE ViT-S/16 +
the head of ``conf/model/vlm25m.yaml``), both with random weights (``_common.build_model``),
ReSiReg's parameters from ``conf/resireg/default.yaml``, the map's from ``conf/map.yaml``
(``variant: full``, voxel 0.05 m, ``points: patch``, float64 sums).

1. Bag decoding alone: iterating :class:`resireg.sources.rosbag.BagSource` (both passes:
   stamps and poses, then PNG colour and depth decoding, tf lookups), frames per second.
2. Fusion alone: :meth:`SemanticMap.fuse` of random unit features at ReSiReg's grid (upscale 2:
   60 x 80 for 480 x 640) and ``D`` = 48 (tiny) / 512 (25M), windows of 8 frames.
3. End to end: bag -> :func:`resireg.sources.frames.windows` -> :meth:`SemanticMap.add`
   (encode, ReSiReg Full on the window, lift, fuse), for both models and windows of 4 and 8;
   frames per second, each measured once after one warm-up window.
4. Peak memory of a ScanNet-size recording: ``--scene-frames`` (500: a ~5,500-frame scene at
   ScanNet's frame skip 10) frames fused at 0.05 m with D = 512 in a fresh process (a random
   walk of the room's trajectory, random features), peak resident set (``VmHWM``) and the map's
   bytes (``SemanticMap.nbytes``), float64 and float32 sums.

    python benchmarks/bench_robot_map.py [--frames 16] [--size 480 640] [--threads 2]
        [--scene-frames 500] [--sections 1 2 3 4] [--smoke]
"""

from __future__ import annotations

import argparse
import json
import multiprocessing
import tempfile
import time
from pathlib import Path

from _common import CONF, build_model, load_yaml, resireg_defaults


def _peak_rss_mb() -> float:
    with open("/proc/self/status") as f:
        for line in f:
            if line.startswith("VmHWM:"):
                return int(line.split()[1]) / 1024
    return float("nan")


def _bag(folder: Path, frames: int, size: tuple[int, int]) -> Path:
    from resireg_train.data.room_bag import room_frames, write_bag

    focal = 0.9 * size[1]  # ~58 degrees horizontally, as ScanNet's depth camera
    return write_bag(folder / "bag", room_frames(frames, size, focal), decoys=False)


def _source(path: Path):
    from resireg.sources.rosbag import BagSource, BagTopics
    from resireg_train.data.room_bag import TOPICS

    topics = BagTopics(colour=TOPICS["colour"], depth=TOPICS["depth"], camera_info=TOPICS["info"])
    return BagSource(path, topics)


def _map(model, cfg):
    from resireg.mapping import SemanticMap

    params = {k: resireg_defaults()[k] for k in ("calib", "lite", "full")}
    return SemanticMap(model, cfg["variant"], cfg["voxel_size"], params=params,
                       points=cfg["points"], lattice=cfg["lattice"], sum_dtype=cfg["sum_dtype"])  # fmt: skip


def decoding(path: Path) -> dict:
    start = time.perf_counter()
    n = sum(1 for _ in _source(path))
    seconds = time.perf_counter() - start
    return {"frames": n, "seconds": seconds, "fps": n / seconds}


def fusion(path: Path, dim: int, cfg: dict) -> dict:
    import torch

    from resireg.mapping import SemanticMap
    from resireg.sources.frames import FrameCounts, windows

    smap = SemanticMap(None, "bb", cfg["voxel_size"], points=cfg["points"], colour=False)
    batches = list(windows(_source(path), 8, FrameCounts()))
    g = torch.Generator().manual_seed(0)
    seconds = n = 0
    for b in batches:
        h, w = b["depth"].shape[-2] // 8, b["depth"].shape[-1] // 8  # patch 16, upscale 2
        feats = torch.nn.functional.normalize(
            torch.randn(len(b["name"]), dim, h, w, generator=g), dim=1
        )
        start = time.perf_counter()
        smap.fuse(feats, b["depth"], b["intrinsics"], b["pose"])
        seconds += time.perf_counter() - start
        n += len(b["name"])
    return {"frames": n, "seconds": seconds, "fps": n / seconds, "voxels": len(smap)}


def end_to_end(path: Path, tiny: bool, window: int, cfg: dict) -> dict:
    import torch

    from resireg.sources.frames import FrameCounts, windows

    torch.manual_seed(0)
    model = build_model(tiny)
    smap = _map(model, cfg)
    batches = windows(_source(path), window, FrameCounts())
    first = next(batches)  # warm-up window (and the bag's first pass), not timed
    smap.add(first["image"], first["depth"], first["intrinsics"], first["pose"])
    start = time.perf_counter()
    n = 0
    for b in batches:
        smap.add(b["image"], b["depth"], b["intrinsics"], b["pose"])
        n += len(b["name"])
    seconds = time.perf_counter() - start
    return {"frames": n, "seconds": seconds, "fps": n / seconds if n else float("nan"),
            "voxels": len(smap)}  # fmt: skip


def _scene_memory(frames: int, dim: int, sum_dtype: str, size, queue) -> None:
    import numpy as np
    import torch

    from resireg.mapping import SemanticMap
    from resireg_train.data.scannet_room import SyntheticRoom

    torch.set_num_threads(1)
    room = SyntheticRoom(size=(8.0, 8.0, 3.0), image_size=size, focal=0.9 * size[1], frames=frames,
                         bad_pose_frame=None, objects=[])  # fmt: skip
    k = torch.from_numpy(room.intrinsics).float()
    smap = SemanticMap(None, "bb", 0.05, sum_dtype=sum_dtype, colour=False)
    before = _peak_rss_mb()
    g = torch.Generator().manual_seed(0)
    h, w = size[0] // 8, size[1] // 8
    start = time.perf_counter()
    for i in range(0, frames, 8):
        ids = range(i, min(i + 8, frames))
        depth = torch.from_numpy(np.stack([room.render(j)[0] for j in ids]).astype(np.float32))
        pose = torch.from_numpy(np.stack([room.pose(j) for j in ids]))
        feats = torch.nn.functional.normalize(torch.randn(len(ids), dim, h, w, generator=g), dim=1)
        smap.fuse(feats, depth, k, pose)
    queue.put({"frames": frames, "sum_dtype": sum_dtype, "voxels": len(smap),
               "map_mib": smap.nbytes / 2**20, "rss_before_mib": before,
               "peak_rss_mib": _peak_rss_mb(), "seconds": time.perf_counter() - start})  # fmt: skip


def scene_memory(frames: int, size, dtype: str) -> dict:
    ctx = multiprocessing.get_context("spawn")
    queue = ctx.Queue()
    proc = ctx.Process(target=_scene_memory, args=(frames, 512, dtype, size, queue))
    proc.start()
    out = queue.get()
    proc.join()
    return out


def main(argv: list[str] | None = None) -> None:
    parser = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    parser.add_argument("--frames", type=int, default=16)
    parser.add_argument("--size", type=int, nargs=2, default=[480, 640])
    parser.add_argument("--threads", type=int, default=2)
    parser.add_argument("--scene-frames", type=int, default=500)
    parser.add_argument("--sections", type=int, nargs="+", default=[1, 2, 3, 4])
    parser.add_argument("--smoke", action="store_true", help="tiny sizes: seconds")
    args = parser.parse_args(argv)
    import torch

    torch.set_num_threads(args.threads)
    if args.smoke:
        args.frames, args.size, args.scene_frames = 6, [96, 128], 16
    size = tuple(args.size)
    cfg = load_yaml(CONF / "map.yaml")
    out: dict = {"setting": {"frames": args.frames, "size": list(size), "threads": args.threads}}
    with tempfile.TemporaryDirectory() as tmp:
        path = _bag(Path(tmp), args.frames, size)
        if 1 in args.sections:
            out["decoding"] = decoding(path)
        if 2 in args.sections:
            out["fusion"] = {d: fusion(path, d, cfg) for d in (48, 512)}
        if 3 in args.sections:
            out["end_to_end"] = {
                f"{'tiny' if tiny else '25M'}/window={w}": end_to_end(path, tiny, w, cfg)
                for tiny in (True, False) for w in (4, 8)
            }  # fmt: skip
    if 4 in args.sections:
        out["scene_memory"] = [
            scene_memory(args.scene_frames, size, d) for d in ("float64", "float32")
        ]
    print(json.dumps(out, indent=2))


if __name__ == "__main__":
    main()
