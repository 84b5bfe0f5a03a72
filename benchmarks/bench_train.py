"""Training throughput: Lightning against a bare PyTorch loop, and the text-cache effect.

    python benchmarks/bench_train.py [--steps 48] [--repeats 3]

1. Framework overhead: the smoke configuration (tiny models, stage-1 losses) trained for
   ``--steps`` optimizer steps through ``lightning.Trainer`` (logging every step, as in the
   smoke experiment, checkpointing off) and through a bare loop doing the same work
   (``ResiregModule.losses``, backward, the module's own optimizer and schedule, logit
   clamp). Both consume the same pre-built batches, so data loading is out of the
   comparison; runs alternate, and the median of ``--repeats`` is reported.
2. Text cache: a bare-loop epoch over the same batches twice, with the frozen text tower at
   SigLIP 2 B/16 text size (768 wide, 12 layers, random init, CLIP BPE tokenizer); the
   second epoch's captions all come from the cache.

Figures are ratios measured in one run (these machines are noisy).
"""

from __future__ import annotations

import argparse
import statistics
import time
import warnings

import lightning as L
import torch
from hydra import compose, initialize_config_dir

from resireg_train.cli.job import CONFIG_DIR
from resireg_train.jobs.train import build

#: The 25M VLM's trained head on a ViT-S/16-sized backbone (random init, no download) at a
#: reduced crop and batch, so a CPU step costs about what a real step costs on a GPU.
VITS = [
    "model.backbone.embed_dim=384", "model.backbone.depth=12", "model.backbone.num_heads=6",
    "model.head.out_dim=512", "model.head.drop_path=0.3", "data.crop_size=224",
    "data.batch_size=8", "data.sources.synthetic.image_size=[240,256]",
]  # fmt: skip
#: The SigLIP 2 B/16 text tower's size (random init, CLIP BPE tokenizer).
SIGLIP2_TEXT = ["model.text.width=768", "model.text.layers=12", "model.text.heads=12",
                "model.text.out_dim=768"]  # fmt: skip


def _module(*overrides: str):
    """The smoke experiment's module and data module, with Hydra overrides."""
    with initialize_config_dir(str(CONFIG_DIR), version_base="1.3"):
        cfg = compose("train", overrides=["experiment=smoke", *overrides])
    module, data = build(cfg)
    module.setup("fit")  # the teacher (and distillation head) are built per process in setup
    return module, data


def _batches(data, steps: int) -> list[dict]:
    data.steps_per_epoch = steps
    return list(data.train_dataloader())


def _bare(module, batches: list[dict]) -> float:
    """Seconds for one pass of the bare loop over ``batches``."""
    optimizer, scheduler = module.build_optimizer(len(batches))
    module.train()
    start = time.perf_counter()
    for step, batch in enumerate(batches):
        loss, _ = module.losses(batch, step)
        optimizer.zero_grad(set_to_none=True)
        loss.backward()
        optimizer.step()
        scheduler.step()
        with torch.no_grad():
            module.logit_scale.clamp_(max=module.max_log_scale)
    return time.perf_counter() - start


class _Timer(L.Callback):
    def on_train_start(self, trainer, pl_module):
        self.start = time.perf_counter()

    def on_train_end(self, trainer, pl_module):
        self.seconds = time.perf_counter() - self.start


class _Replay:
    """The pre-built batches as one iterable (a plain list would be read as many loaders)."""

    def __init__(self, batches: list[dict]) -> None:
        self.batches = batches

    def __len__(self) -> int:
        return len(self.batches)

    def __iter__(self):
        return iter(self.batches)


def _lightning(module, batches: list[dict], tmp: str, log_every: int) -> float:
    timer = _Timer()
    trainer = L.Trainer(
        max_epochs=1, accelerator="cpu", logger=L.pytorch.loggers.CSVLogger(tmp),
        enable_checkpointing=False, enable_progress_bar=False, enable_model_summary=False,
        log_every_n_steps=log_every, callbacks=[timer], default_root_dir=tmp,
    )  # fmt: skip
    trainer.fit(module, train_dataloaders=_Replay(batches))
    return timer.seconds


def _overhead(title: str, module, batches: list[dict], repeats: int) -> None:
    import tempfile

    steps = len(batches)
    _bare(module, batches[:2])  # warm-up (allocations, text cache)
    state = {k: v.clone() for k, v in module.state_dict().items()}
    with tempfile.TemporaryDirectory() as tmp:
        runs = {
            "bare PyTorch loop": lambda: _bare(module, batches),
            "Lightning, metrics written every step": lambda: _lightning(module, batches, tmp, 1),
            "Lightning, every 10 steps (default)": lambda: _lightning(module, batches, tmp, 10),
        }
        times: dict[str, list[float]] = {name: [] for name in runs}
        for _ in range(repeats):
            for name, run in runs.items():
                module.load_state_dict(state)
                times[name].append(run())
    bare = statistics.median(times["bare PyTorch loop"])
    print(f"\n{title}, {steps} steps, median of {repeats}:\n")
    print("| loop | steps/s | ms/step | time vs bare |")
    print("|---|---|---|---|")
    for name, values in times.items():
        t = statistics.median(values)
        print(
            f"| {name} | {steps / t:.2f} | {1000 * t / steps:.1f} | {100 * (t / bare - 1):+.1f}% |"
        )


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    parser.add_argument("--steps", type=int, default=48)
    parser.add_argument("--repeats", type=int, default=3)
    args = parser.parse_args()
    warnings.filterwarnings("ignore")
    import logging

    logging.getLogger("lightning").setLevel(logging.ERROR)
    for title, overrides, steps in (
        ("smoke configuration (tiny models, 64 px crops, batch 16)", [], args.steps),
        ("ViT-S/16-sized backbone + 25M head (224 px crops, batch 8)", VITS, args.steps // 4),
    ):
        torch.manual_seed(0)
        module, data = _module(*overrides)
        _overhead(title, module, _batches(data, steps), args.repeats)

    big, data = _module(*SIGLIP2_TEXT)
    batches = _batches(data, args.steps)
    first = _bare(big, batches)
    misses = big.vlm.text.misses
    second = _bare(big, batches)
    print(f"\nText cache, SigLIP 2 B-sized text tower: epoch 1 {args.steps / first:.1f} steps/s "
          f"({misses} tower calls for {args.steps * len(batches[0]['caption'])} captions), "
          f"epoch 2 {args.steps / second:.1f} steps/s (all cached): {first / second:.2f}x faster")  # fmt: skip


if __name__ == "__main__":
    main()
