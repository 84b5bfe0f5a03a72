"""Cost of one ``ReSiRegEval`` pass against one training epoch, and where the pass spends it.

    python benchmarks/bench_eval.py [--repeats 3] [--vits-images 8]

1. Smoke configuration (tiny models, the smoke experiment's eval set: 32 synthetic images,
   BB / Lite / Full): one training epoch through ``lightning.Trainer`` (8 steps, eval
   callback off) against one evaluation pass of the configured ``ReSiRegEval`` callback.
   The first pass also embeds the class prompts (once per run); later passes do not.
2. The evaluation protocol's size: a ViT-S/16-sized backbone with the 25M head (random
   init, no download) on ``--vits-images`` images of 576 x 768 (ADE20K's common aspect at
   short side 576), batch 8, BB / Lite / Full with the paper's defaults.

Each pass is split into data (decode + resize), backbone, head, reconstruction per
variant and metric (prediction at label size + confusion matrix). Figures are ratios
measured in one run (these machines are noisy); medians of ``--repeats``.
"""

from __future__ import annotations

import argparse
import statistics
import time
import warnings

import hydra
import lightning as L
import torch
from hydra import compose, initialize_config_dir

from resireg.method.variants import build_variants
from resireg_train.cli.job import CONFIG_DIR
from resireg_train.data.segmentation import build_segmentation_set
from resireg_train.data.specs import dataset_conf
from resireg_train.evaluation.ovss.engine import OVSSEngine, StageTimer
from resireg_train.jobs.train import build

STAGES = ("data", "encoder", "reconstruction/bb", "reconstruction/lite",
          "reconstruction/full", "metric")  # fmt: skip


class _EpochTimer(L.Callback):
    def __init__(self) -> None:
        self.seconds: list[float] = []

    def on_train_epoch_start(self, trainer, pl_module) -> None:
        self._start = time.perf_counter()

    def on_train_epoch_end(self, trainer, pl_module) -> None:
        self.seconds.append(time.perf_counter() - self._start)


def _split(timers: list[StageTimer]) -> dict[str, float]:
    return {s: statistics.median(t.seconds.get(s, 0.0) for t in timers) for s in STAGES}


def _print_split(split: dict[str, float], total: float) -> None:
    for stage, seconds in split.items():
        print(f"    {stage:<22} {1000 * seconds:9.1f} ms  {100 * seconds / total:5.1f} %")


def smoke(repeats: int) -> None:
    with initialize_config_dir(str(CONFIG_DIR), version_base="1.3"):
        cfg = compose("train", overrides=["experiment=smoke"])
    module, data = build(cfg)
    timer = _EpochTimer()
    trainer = L.Trainer(accelerator="cpu", devices=1, max_epochs=repeats + 1, logger=False,
                        enable_checkpointing=False, enable_progress_bar=False,
                        enable_model_summary=False, callbacks=[timer])  # fmt: skip
    trainer.fit(module, datamodule=data)
    epoch = statistics.median(timer.seconds[1:])  # the first epoch warms up

    callback = hydra.utils.instantiate(cfg.callbacks.resireg_eval, _convert_="all")
    callback.setup(trainer, module, "fit")
    (engine,) = callback.engines.values()
    timers = []
    for _ in range(repeats + 1):
        timers.append(StageTimer())
        start = time.perf_counter()
        engine.run(module.vlm, callback.variants, timer=timers[-1])
        timers[-1].seconds["total"] = time.perf_counter() - start
    first = timers[0].seconds["total"]
    warm = statistics.median(t.seconds["total"] for t in timers[1:])
    print(f"smoke: training epoch ({cfg.data.steps_per_epoch} steps) {1000 * epoch:.0f} ms")
    print(f"  eval pass ({len(engine.dataset)} images, {list(callback.variants)}): "
          f"{1000 * warm:.0f} ms = {warm / epoch:.2f} x an epoch "
          f"(first pass, embedding {len(engine.prompts)} prompts: {1000 * first:.0f} ms = "
          f"{first / epoch:.2f} x)")  # fmt: skip
    _print_split(_split(timers[1:]), warm)


def vits(repeats: int, images: int) -> None:
    from _common import TINY_TEXT
    from resireg.models import ResiregVLM

    backbone = {"model_name": "eupe_vit_s16", "weights": None}  # ViT-S/16, random init
    head = {"out_dim": 512, "depth": 2, "num_heads": 8}
    vlm = ResiregVLM.build(backbone, head, TINY_TEXT).eval()
    spec = dataset_conf("synthetic", size=images, image_size=[432, 576], short_side=576)
    task = OVSSEngine(build_segmentation_set(spec, vlm.input_rule.patch_size), batch_size=8)
    variants = build_variants(
        ["bb", "lite", "full"], {"lite": {"alpha": 10.0}, "full": {"n_prototypes": 36}}
    )
    task.prototypes(vlm)  # once per run; not part of a pass
    timers = []
    for _ in range(repeats):
        timers.append(StageTimer())
        start = time.perf_counter()
        task.run(vlm, variants, timer=timers[-1])
        timers[-1].seconds["total"] = time.perf_counter() - start
    total = statistics.median(t.seconds["total"] for t in timers)
    print(
        f"ViT-S/16 + 25M head, {images} images at 576 x 768, batch 8: "
        f"{1000 * total / images:.0f} ms per image"
    )
    _print_split(_split(timers), total)


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    parser.add_argument("--repeats", type=int, default=3)
    parser.add_argument("--vits-images", type=int, default=8)
    args = parser.parse_args()
    warnings.filterwarnings("ignore")
    torch.manual_seed(0)
    print(f"torch {torch.__version__}, {torch.get_num_threads()} threads")
    smoke(args.repeats)
    vits(args.repeats, args.vits_images)


if __name__ == "__main__":
    main()
