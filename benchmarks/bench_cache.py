"""The feature cache: reading stored encoder outputs against encoding again, and disk cost.

One evaluation pass of the 25M architecture (EUPE ViT-S/16 + the 25M head, random init) over
``--images`` generated images at ``--short-side`` (4:3, so 576 px gives the 36 x 48 grid of
an ADE20K-like image) is run three times through the engine (``OVSSEngine.run`` with the ``bb``
variant, so ReSiReg adds nothing): without a cache, filling a new cache, and reading it in a
fresh :class:`~resireg_train.evaluation.cache.FeatureCache` (what a later job of a sweep does). Reported:
the engine's seconds per stage (``encoder``, ``cache``), images per second of encoding and of
reading, and the bytes per image on disk, with the disk cost this gives for ADE20K val
(2,000 images) and for the 12 ScanNet scenes (about 500 kept frames each at frame skip 10, at
640 x 864: a 40 x 54 grid). The read is from the page cache when the shards were just written
(the usual case for a sweep on one node); a cold network file system reads slower.

    python benchmarks/bench_cache.py                               # 16 images at 576 px
    python benchmarks/bench_cache.py --images 4 --short-side 128   # quick
"""

from __future__ import annotations

import argparse
import tempfile
import time

import torch

from _common import build_model, generated_spec
from resireg.method.variants import build_variants
from resireg_train.data.segmentation import build_segmentation_set
from resireg_train.evaluation.cache import FeatureCache
from resireg_train.evaluation.ovss.engine import OVSSEngine, StageTimer

ADE20K_VAL_IMAGES = 2000
SCANNET_FRAMES = 12 * 500  # 12 scenes, ~5,000 frames each at frame skip 10
SCANNET_GRID = (640 // 16) * (864 // 16)


def main(argv: list[str] | None = None) -> None:
    parser = argparse.ArgumentParser(
        description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter
    )
    parser.add_argument("--images", type=int, default=16)
    parser.add_argument("--short-side", type=int, default=576)
    parser.add_argument("--batch-size", type=int, default=8)
    parser.add_argument("--threads", type=int, default=None, help="torch threads")
    args = parser.parse_args(argv)
    if args.threads:
        torch.set_num_threads(args.threads)
    torch.manual_seed(0)
    model = build_model()
    spec = generated_spec(args.images, args.short_side)
    dataset = build_segmentation_set(spec, model.input_rule.patch_size)
    task = OVSSEngine(dataset, batch_size=args.batch_size)
    task.prototypes(model)
    variants = build_variants(["bb"])
    key = FeatureCache.key_for(model, {"kind": "bench"}, spec, model.input_rule.patch_size, "32")
    rows = []
    with tempfile.TemporaryDirectory() as root:
        for label, cache in (
            ("encode (no cache)", None),
            ("encode + write", FeatureCache(root, key, dataset.describe)),
            ("read", None),
        ):
            if label == "read":
                cache = FeatureCache(root, key, dataset.describe)  # a later job
            timer = StageTimer()
            start = time.perf_counter()
            task.run(model, variants, timer=timer, cache=cache)
            total = time.perf_counter() - start
            rows.append((label, total, timer.seconds, cache))
        per_image = rows[1][3].disk_bytes() / args.images
        height, width = spec["image_size"]
        print(f"{args.images} images at {height} x {width} px, batch {args.batch_size}, "
              f"{torch.get_num_threads()} threads")  # fmt: skip
        print("| pass | total s | encoder s | cache s | images/s of the stage |")
        print("|---|---:|---:|---:|---:|")
        for label, total, seconds, _ in rows:
            stage = seconds.get("cache" if label == "read" else "encoder", float("nan"))
            print(f"| {label} | {total:.2f} | {seconds.get('encoder', 0.0):.2f} | "
                  f"{seconds.get('cache', 0.0):.3f} | {args.images / stage:.1f} |")  # fmt: skip
        enc, read = rows[0][2]["encoder"], rows[2][2]["cache"]
        print(f"\nreading is {enc / read:.0f}x faster than encoding; "
              f"{per_image / 2**20:.2f} MiB per image on disk")  # fmt: skip
        height, width = dataset.grid_sizes()[0]  # the resized canvas, multiples of the patch
        grid = (height // 16) * (width // 16)
        per_patch = per_image / grid
        print(f"ADE20K val ({ADE20K_VAL_IMAGES} images at this size): "
              f"{per_image * ADE20K_VAL_IMAGES / 2**30:.1f} GiB; ScanNet, 12 scenes "
              f"(~{SCANNET_FRAMES} frames at 640 x 864): "
              f"{per_patch * SCANNET_GRID * SCANNET_FRAMES / 2**30:.1f} GiB")  # fmt: skip


if __name__ == "__main__":
    main()
