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
import statistics
import time

import torch

from _common import build_model, generated_spec
from resireg.method.variants import build_variants
from resireg.models import ResiregVLM
from resireg_train.data.segmentation import build_segmentation_set
from resireg_train.evaluation.ovss.engine import OVSSEngine, StageTimer

BATCH_SIZES = (2, 4, 6, 8, 16, 24, 32)
COUNTS = tuple(range(24, 133, 12))


def _seconds(
    task: OVSSEngine, model: ResiregVLM, names: list[str], timer: StageTimer | None = None
) -> tuple[float, float]:
    """Wall and process CPU seconds of one evaluation pass scoring ``names`` (its stages
    added to ``timer``)."""
    variants = build_variants(names, {"full": {"n_components": None}})
    start, cpu = time.perf_counter(), time.process_time()
    task.run(model, variants, timer=timer)
    return time.perf_counter() - start, time.process_time() - cpu


def _total(times: list[tuple[float, float]]) -> tuple[float, float]:
    return sum(t[0] for t in times), sum(t[1] for t in times)


def _median(times: list[tuple[float, float]]) -> tuple[float, float]:
    return statistics.median(t[0] for t in times), statistics.median(t[1] for t in times)


def main(argv: list[str] | None = None) -> None:
    parser = argparse.ArgumentParser(
        description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter
    )
    parser.add_argument("--vits", action="store_true", help="the 25M architecture")
    parser.add_argument("--images", type=int, default=32)
    parser.add_argument("--short-side", type=int, default=None)
    parser.add_argument("--batch-sizes", type=int, nargs="+", default=list(BATCH_SIZES))
    parser.add_argument("--counts", type=int, nargs="+", default=list(COUNTS))
    parser.add_argument("--threads", type=int, default=None, help="torch threads")
    parser.add_argument(
        "--no-jobs", action="store_true", help="skip the one-pass-per-setting form (slowest)"
    )
    parser.add_argument(
        "--repeats", type=int, default=1,
        help="rounds of the forms, interleaved (load drifts over minutes on a shared machine); "
        "the table shows each form's median and the ratios' range over the rounds",
    )  # fmt: skip
    parser.add_argument(
        "--stages", action="store_true",
        help="print the stage seconds (encoder, each configuration, metric) of the last round's "
        "configuration form at the largest batch size",
    )  # fmt: skip
    args = parser.parse_args(argv)
    if args.threads:
        torch.set_num_threads(args.threads)
    torch.manual_seed(0)
    model = build_model(tiny=not args.vits)
    # The smoke experiment's eval set (72 x 88 px at short side 64), or 3:4 images.
    if args.short_side is None:
        spec = generated_spec(args.images, 64, image_size=[72, 88])
    else:
        spec = generated_spec(args.images, args.short_side)
    dataset = build_segmentation_set(spec, model.input_rule.patch_size)
    tasks = {b: OVSSEngine(dataset, batch_size=b) for b in args.batch_sizes}
    for task in tasks.values():
        task.prototypes(model)  # the class prompts, once (not timed)
    configs = [f"full@n_prototypes:{n}" for n in args.counts]
    rounds: dict[str, list[tuple[float, float]]] = {"jobs": [], "together": [], "single": []}
    for _ in range(max(1, args.repeats)):
        if not args.no_jobs:
            rounds["jobs"].append(
                _total([_seconds(t, model, [c]) for t in tasks.values() for c in configs])
            )
        timer = StageTimer()  # the largest batch size's pass (--stages)
        rounds["together"].append(
            _total([_seconds(t, model, configs, timer if b == max(tasks) else None)
                    for b, t in tasks.items()])
        )  # fmt: skip
        rounds["single"].append(_total([_seconds(t, model, configs[:1]) for t in tasks.values()]))
    jobs = _median(rounds["jobs"]) if rounds["jobs"] else None
    together, single = _median(rounds["together"]), _median(rounds["single"])
    size = "25M (ViT-S/16)" if args.vits else "smoke"
    n_b, n_c = len(args.batch_sizes), len(configs)
    print(f"{size}: {args.images} images, batch sizes {args.batch_sizes}, counts {args.counts}")
    print(f"{torch.get_num_threads()} threads; CPU = process CPU seconds (all threads), less "
          "sensitive than wall time to other jobs on the machine")  # fmt: skip
    print(f"| form | passes | wall s | x {n_b} x 1 | CPU s | x {n_b} x 1 |\n"
          "|---|---:|---:|---:|---:|---:|")  # fmt: skip
    forms = [(f"{n_b} x {n_c}", n_b, together), (f"{n_b} x 1", n_b, single)]
    if jobs is not None:
        forms.insert(0, (f"{n_b * n_c} jobs", n_b * n_c, jobs))
    for form, passes, (wall, cpu) in forms:
        print(f"| {form} | {passes} | {wall:.2f} | {wall / single[0]:.2f} | {cpu:.2f} | "
              f"{cpu / single[1]:.2f} |")  # fmt: skip
    if args.stages:
        print(f"stages of the {n_b} x {n_c} form at batch size {max(tasks)}, last round (s): "
              + ", ".join(f"{k} {v:.2f}" for k, v in timer.seconds.items()))  # fmt: skip
    if len(rounds["single"]) > 1:
        for key, form in (("jobs", f"{n_b * n_c} jobs"), ("together", f"{n_b} x {n_c}")):
            ratios = [a[0] / b[0] for a, b in zip(rounds[key], rounds["single"], strict=False)]
            if ratios:
                print(f"{form} / {n_b} x 1, wall, per round: "
                      + ", ".join(f"{r:.2f}" for r in ratios))  # fmt: skip


if __name__ == "__main__":
    main()
