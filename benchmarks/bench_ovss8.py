"""CPU cost per image of ``sweep=ovss8``'s jobs with the smoke model: sliding windows (the
field's protocol, conf/protocol/ovss8.yaml) against one pass over the whole image, per variant.

    python benchmarks/bench_ovss8.py [--images 8] [--repeats 3] [--threads 2]

A VOC21-shaped set is written in VOC's layout (``--images`` photographs of 375 x 500 with palette
labels, VOC21's 21 classes and their names from conf/classes/voc21.txt) and read by the ``voc``
reader. The tiny model of ``experiment=smoke`` (random init: the cost does not depend on the
weights) scores it through the OVSS engine at shorter side 336:

- ``slide``: ``dataset=voc21`` as conf/ sets it (224 px windows every 112 px: 6 windows per
  375 x 500 image, logits bilinear to each window, averaged, bilinear to the label, background
  threshold);
- ``whole``: the same with ``dataset.slide_crop=null`` (one 336 x 448 pass, logits bilinear).

Each variant alone (bb, calib, lite, full: the encoder pass is in every row) and the four
together (the sweep's job: one encoder pass per window shared by the four). Milliseconds per
image, medians of ``--repeats`` passes after one that also embeds the class names' prompts.
"""

from __future__ import annotations

import argparse
import statistics
import sys
import tempfile
import time
from pathlib import Path

import numpy as np
import torch
from PIL import Image

sys.path.insert(0, str(Path(__file__).resolve().parent))
from _common import build_model, resireg_defaults  # noqa: E402

from resireg.variants import build_variants  # noqa: E402
from resireg_train.data.segmentation import build_segmentation_set  # noqa: E402
from resireg_train.data.specs import dataset_conf  # noqa: E402
from resireg_train.engine import StageTimer  # noqa: E402
from resireg_train.ovss.engine import OVSSEngine  # noqa: E402

CONFIGURATIONS = (("bb",), ("calib",), ("lite",), ("full",), ("bb", "calib", "lite", "full"))


def write_voc(root: Path, images: int) -> None:
    """``images`` noisy photographs of 375 x 500 with palette labels of 4 classes and a 255
    band, in VOCdevkit/VOC2012's layout."""
    rng = np.random.default_rng(0)
    (root / "JPEGImages").mkdir(parents=True)
    (root / "SegmentationClass").mkdir()
    (root / "ImageSets" / "Segmentation").mkdir(parents=True)
    ids = [f"2007_{i:06d}" for i in range(images)]
    for i in ids:
        pixels = (rng.random((375, 500, 3)) * 255).astype(np.uint8)
        Image.fromarray(pixels).save(root / "JPEGImages" / f"{i}.jpg")
        label = np.zeros((375, 500), dtype=np.uint8)
        label[:, 125:250], label[:, 250:375], label[:, 375:] = 15, 7, 12
        label[:, 248:252] = 255
        png = Image.fromarray(label, mode="P")
        png.putpalette([v for c in range(256) for v in (c, c, c)])
        png.save(root / "SegmentationClass" / f"{i}.png")
    (root / "ImageSets" / "Segmentation" / "val.txt").write_text("".join(f"{i}\n" for i in ids))


def cost(model, root: Path, images: int, repeats: int, slide: bool) -> dict[str, dict[str, float]]:
    """Milliseconds per image of each configuration: total, and its stages."""
    over = {} if slide else {"slide_crop": None, "slide_stride": None}
    spec = dataset_conf("voc21", path=str(root), **over)
    data = build_segmentation_set(spec, model.input_rule.patch_size)
    defaults = resireg_defaults()
    out = {}
    for names in CONFIGURATIONS:
        variants = build_variants(list(names), defaults)
        engine = OVSSEngine(data, batch_size=1, num_workers=0)
        engine.run(model, variants)  # warm-up; embeds the prompts once
        totals, stages = [], []
        for _ in range(repeats):
            timer = StageTimer()
            start = time.perf_counter()
            engine.run(model, variants, timer=timer)
            totals.append(time.perf_counter() - start)
            stages.append(timer.seconds)
        row = {"total": 1000 * statistics.median(totals) / images}
        for stage in sorted({s for t in stages for s in t}):
            row[stage] = 1000 * statistics.median(t.get(stage, 0.0) for t in stages) / images
        out["+".join(names)] = row
    return out


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.split("\n")[0])
    parser.add_argument("--images", type=int, default=8)
    parser.add_argument("--repeats", type=int, default=3)
    parser.add_argument("--threads", type=int, default=2)
    args = parser.parse_args()
    torch.set_num_threads(args.threads)
    torch.manual_seed(0)
    model = build_model(tiny=True)
    with tempfile.TemporaryDirectory() as tmp:
        root = Path(tmp) / "VOC2012"
        write_voc(root, args.images)
        results = {mode: cost(model, root, args.images, args.repeats, mode == "slide")
                   for mode in ("whole", "slide")}  # fmt: skip
    print(f"ms per image (median of {args.repeats}; {args.images} VOC-sized images, "
          f"{args.threads} threads, smoke model)")  # fmt: skip
    print(f"{'configuration':<20} {'whole':>9} {'slide':>9} {'slide/whole':>12}   "
          "slide: encoder / reconstruction / metric")
    for names in results["whole"]:
        whole, slide = results["whole"][names], results["slide"][names]
        recon = sum(v for k, v in slide.items() if k.startswith("reconstruction/"))
        print(f"{names:<20} {whole['total']:9.1f} {slide['total']:9.1f} "
              f"{slide['total'] / whole['total']:12.2f}   "
              f"{slide.get('encoder', 0):.1f} / {recon:.1f} / {slide.get('metric', 0):.1f}")


if __name__ == "__main__":
    main()
