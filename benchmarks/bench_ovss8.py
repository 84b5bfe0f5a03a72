"""CPU cost per image of ``sweep=ovss8``'s jobs with the smoke model: sliding windows (the
field's protocol, conf/protocol/ovss8.yaml) against one pass over the whole image, per variant.

    python benchmarks/bench_ovss8.py [--images 4] [--repeats 3] [--threads 1]

A VOC21-shaped set is written in VOC's layout (``--images`` photographs of 375 x 500 with palette
labels, VOC21's 21 classes and their names from conf/classes/voc21.txt) and read by the ``voc``
reader. The tiny model of ``experiment=smoke`` (random init: the cost does not depend on the
weights) scores it through the OVSS engine at shorter side 336:

- ``slide``: ``dataset=voc21`` as conf/ sets it (224 px windows every 112 px: 6 windows per
  375 x 500 image, logits bilinear to each window, averaged, bilinear to the label, background
  threshold);
- ``whole``: the same with ``dataset.slide_crop=null`` (one 336 x 448 pass, logits bilinear).

Each variant alone (bb, calib, lite, full: the encoder pass is in every row) and the four
together (the sweep's job: one encoder pass per window shared by the four). The cost is the
process's CPU time (``time.process_time``, every thread's) per image, median of ``--repeats``
passes after one that also embeds the class names' prompts: on a shared machine CPU time
moves far less than wall time (one thread by default, so the two agree on an idle machine).
The split by stage is the engine's wall-time ``StageTimer``, as a share of the pass.
"""

from __future__ import annotations

import argparse
import statistics
import tempfile
import time
from pathlib import Path

import numpy as np
import torch
from PIL import Image

from _common import build_model, resireg_defaults
from resireg.method.variants import build_variants
from resireg_train.data.segmentation import build_segmentation_set
from resireg_train.data.specs import dataset_conf
from resireg_train.evaluation.ovss.engine import OVSSEngine, StageTimer

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
    """CPU milliseconds per image of each configuration (``cpu``), and each stage's share of
    the pass's wall time."""
    over = {} if slide else {"slide_crop": None, "slide_stride": None}
    spec = dataset_conf("voc21", path=str(root), **over)
    data = build_segmentation_set(spec, model.input_rule.patch_size)
    defaults = resireg_defaults()
    out = {}
    for names in CONFIGURATIONS:
        variants = build_variants(list(names), defaults)
        engine = OVSSEngine(data, batch_size=1, num_workers=0)
        engine.run(model, variants)  # warm-up; embeds the prompts once
        cpu, shares = [], []
        for _ in range(repeats):
            timer = StageTimer()
            start, wall = time.process_time(), time.perf_counter()
            engine.run(model, variants, timer=timer)
            cpu.append(time.process_time() - start)
            wall = time.perf_counter() - wall
            shares.append({k: v / wall for k, v in timer.seconds.items()})
        row = {"cpu": 1000 * statistics.median(cpu) / images}
        for stage in sorted({s for t in shares for s in t}):
            row[stage] = statistics.median(t.get(stage, 0.0) for t in shares)
        out["+".join(names)] = row
    return out


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.split("\n")[0])
    parser.add_argument("--images", type=int, default=4)
    parser.add_argument("--repeats", type=int, default=3)
    parser.add_argument("--threads", type=int, default=1)
    args = parser.parse_args()
    torch.set_num_threads(args.threads)
    torch.manual_seed(0)
    model = build_model(tiny=True)
    with tempfile.TemporaryDirectory() as tmp:
        root = Path(tmp) / "VOC2012"
        write_voc(root, args.images)
        results = {mode: cost(model, root, args.images, args.repeats, mode == "slide")
                   for mode in ("whole", "slide")}  # fmt: skip
    print(f"CPU ms per image (median of {args.repeats}; {args.images} VOC-sized images, "
          f"{args.threads} thread(s), smoke model)")  # fmt: skip
    print(
        f"{'configuration':<20} {'whole':>8} {'slide':>8} {'slide/whole':>12}   "
        "slide, share of the pass: encoder / reconstruction / metric"
    )
    for names in results["whole"]:
        whole, slide = results["whole"][names], results["slide"][names]
        recon = sum(v for k, v in slide.items() if k.startswith("reconstruction/"))
        print(
            f"{names:<20} {whole['cpu']:8.0f} {slide['cpu']:8.0f} "
            f"{slide['cpu'] / whole['cpu']:12.2f}   "
            f"{slide.get('encoder', 0):.0%} / {recon:.0%} / {slide.get('metric', 0):.0%}"
        )


if __name__ == "__main__":
    main()
