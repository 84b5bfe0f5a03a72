"""The prototype/batch ablation three ways, in one run on the same data and model:

- ``70 jobs``: one evaluation pass per (batch size, prototype count), what
  ``sweep=prototype_batch_jobs`` runs (process start-up, ~15 s per job, not counted);
- ``7 x 10``: one pass per batch size scoring the 10 prototype counts as configurations
  (``full@n_prototypes:<n>``), what ``sweep=prototype_batch`` runs;
- ``7 x 1``: one pass per batch size with a single configuration (the reference the
  configuration form is measured against: target at most 1.5x).

    python benchmarks/bench_ablation.py                       # smoke size (tiny models)
    python benchmarks/bench_ablation.py --vits --images 8 --short-side 288

Rows: the smoke model on the smoke experiment's 32 synthetic images (72 x 88 px, short side 64), and
``--vits``: the 25M architecture (EUPE ViT-S/16, random init, the 25M head) on generated
images at ``--short-side``. Class prompts are embedded once per task and not timed.
"""

from __future__ import annotations

import argparse
import time

import torch

from resireg.models import TINY_BACKBONE, TINY_HEAD, TINY_TEXT, ResiregVLM
from resireg.variants import build_variants
from resireg_train.ovss.datasets import build_segmentation_set
from resireg_train.ovss.engine import OVSSTask

BATCH_SIZES = (2, 4, 6, 8, 16, 24, 32)
COUNTS = tuple(range(24, 133, 12))


def _model(vits: bool) -> ResiregVLM:
    if vits:
        backbone = {"model_name": "eupe_vit_s16", "weights": None}
        head = {"out_dim": 512, "depth": 2, "num_heads": 8, "drop_path": 0.0}
        return ResiregVLM.build(backbone, head, TINY_TEXT).eval()
    return ResiregVLM.build(TINY_BACKBONE, TINY_HEAD, TINY_TEXT).eval()


def _seconds(task: OVSSTask, model: ResiregVLM, names: list[str]) -> float:
    variants = build_variants(names, {"full": {"n_components": None}})
    start = time.perf_counter()
    task.run(model, variants)
    return time.perf_counter() - start


def main(argv: list[str] | None = None) -> None:
    parser = argparse.ArgumentParser(
        description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter
    )
    parser.add_argument("--vits", action="store_true", help="the 25M architecture")
    parser.add_argument("--images", type=int, default=32)
    parser.add_argument("--short-side", type=int, default=None)
    parser.add_argument("--batch-sizes", type=int, nargs="+", default=list(BATCH_SIZES))
    parser.add_argument("--counts", type=int, nargs="+", default=list(COUNTS))
    args = parser.parse_args(argv)
    torch.manual_seed(0)
    model = _model(args.vits)
    # The smoke experiment's eval set (72 x 88 px at short side 64), or 3:4 images.
    short = args.short_side or 64
    size = [72, 88] if args.short_side is None else [short, short * 4 // 3]
    spec = {"kind": "synthetic", "size": args.images, "short_side": short, "image_size": size}
    dataset = build_segmentation_set(spec, model.input_rule.patch_size)
    tasks = {b: OVSSTask(dataset, batch_size=b) for b in args.batch_sizes}
    for task in tasks.values():
        task.prototypes(model)  # the class prompts, once (not timed)
    configs = [f"full@n_prototypes:{n}" for n in args.counts]
    jobs = sum(_seconds(t, model, [c]) for t in tasks.values() for c in configs)
    together = sum(_seconds(t, model, configs) for t in tasks.values())
    single = sum(_seconds(t, model, configs[:1]) for t in tasks.values())
    size = "25M (ViT-S/16)" if args.vits else "smoke"
    n_b, n_c = len(args.batch_sizes), len(configs)
    print(f"{size}: {args.images} images, batch sizes {args.batch_sizes}, counts {args.counts}")
    print(f"| form | passes | seconds | x {n_b} x 1 |\n|---|---:|---:|---:|")
    for form, passes, seconds in ((f"{n_b * n_c} jobs", n_b * n_c, jobs),
                                  (f"{n_b} x {n_c}", n_b, together),
                                  (f"{n_b} x 1", n_b, single)):  # fmt: skip
        print(f"| {form} | {passes} | {seconds:.2f} | {seconds / single:.2f} |")


if __name__ == "__main__":
    main()
