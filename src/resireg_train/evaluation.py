"""OVSS evaluation of a :class:`~resireg.models.ResiregVLM` for BB, ReSiReg Lite and ReSiReg Full.

One engine serves the ``ReSiRegEval`` training callback, ``resireg-eval`` and
``benchmarks/bench_eval.py``, so a number logged during training is recomputed exactly by
``resireg-eval`` on the exported model.

Per batch (images of one size, see :meth:`SegmentationSet.batches`): the backbone and the
language head run once; each variant turns (EUPE patch tokens, head patch tokens) into
dense features (``bb``: the head's tokens; ``lite`` / ``full``: ReSiReg); every image is
then predicted against the text prototypes (:func:`resireg.ovss.predict`) at its label's
full resolution and scored in one confusion matrix per variant.
"""

from __future__ import annotations

import time
from collections import Counter, defaultdict
from collections.abc import Callable, Iterator, Mapping, Sequence
from contextlib import contextmanager
from dataclasses import dataclass, field

import torch
import torch.nn.functional as F
from torch import Tensor, nn
from torch.utils.data import DataLoader

from resireg.models import ResiregVLM, dense_text_half
from resireg.ovss import TEMPLATES, SegmentationMetric, average_prompts, class_prompts, predict
from resireg.reconstruct import ReSiRegFull, ReSiRegLite
from resireg_train.segmentation import SegmentationSet, collate_segmentation

__all__ = ["VARIANTS", "PRECISIONS", "build_variants", "OVSSTask", "OVSSResult", "StageTimer"]

#: Dense-feature variants: the head alone, ReSiReg Lite, ReSiReg Full.
VARIANTS = ("bb", "lite", "full")
#: Evaluation precisions -> autocast dtype (``None``: fp32, no autocast).
PRECISIONS = {"32": None, "32-true": None, "bf16": torch.bfloat16, "bf16-mixed": torch.bfloat16}


def build_variants(
    variants: Sequence[str],
    lite: Mapping | None = None,
    full: Mapping | None = None,
    key: str = "variants",
) -> dict[str, nn.Module | None]:
    """``{"bb": None, "lite": ReSiRegLite(**lite), "full": ReSiRegFull(**full)}`` for the names given."""
    if not variants:
        raise ValueError(f"{key}=[]: name at least one of {list(VARIANTS)}")
    bad = [v for v in variants if v not in VARIANTS]
    if bad:
        raise ValueError(f"{key}={list(variants)}: unknown {bad}; choose from {list(VARIANTS)}")
    modules: dict[str, nn.Module | None] = {}
    for name in variants:
        if name == "bb":
            modules[name] = None
        elif name == "lite":
            modules[name] = ReSiRegLite(**dict(lite or {}))
        else:
            modules[name] = ReSiRegFull(**dict(full or {}))
    return modules


class StageTimer:
    """Wall seconds per stage (``with timer("backbone"): ...``); CUDA is synchronised."""

    def __init__(self) -> None:
        self.seconds: dict[str, float] = defaultdict(float)

    @contextmanager
    def __call__(self, stage: str) -> Iterator[None]:
        if torch.cuda.is_available():
            torch.cuda.synchronize()
        start = time.perf_counter()
        try:
            yield
        finally:
            if torch.cuda.is_available():
                torch.cuda.synchronize()
            self.seconds[stage] += time.perf_counter() - start


@contextmanager
def _no_timer(stage: str) -> Iterator[None]:
    yield


@dataclass
class OVSSResult:
    """Confusion matrices per variant and counts of one evaluation pass."""

    dataset: str
    metrics: dict[str, SegmentationMetric]
    images: int = 0
    skipped: int = 0
    batch_sizes: dict[int, int] = field(default_factory=dict)

    def reduce(self, all_reduce: Callable[[Tensor], Tensor]) -> None:
        """Sum confusion matrices and counts across ranks with ``all_reduce`` (a sum)."""
        names = list(self.metrics)
        packed = torch.cat(
            [self.metrics[n].confusion.reshape(-1) for n in names]
            + [torch.tensor([self.images, self.skipped], dtype=torch.int64)]
        )
        total = all_reduce(packed).to(torch.int64).cpu()
        offset = 0
        for n in names:
            size = self.metrics[n].confusion.numel()
            self.metrics[n].confusion = (
                total[offset : offset + size].reshape(self.metrics[n].confusion.shape).clone()
            )
            offset += size
        self.images, self.skipped = int(total[offset]), int(total[offset + 1])

    def scores(self, prefix: str = "val/ovss") -> dict[str, float]:
        """``{"<prefix>/<dataset>/miou_<variant>": ..., ".../fmiou_<variant>": ...}``."""
        out = {}
        for variant, metric in self.metrics.items():
            computed = metric.compute()
            out[f"{prefix}/{self.dataset}/miou_{variant}"] = float(computed["miou"])
            out[f"{prefix}/{self.dataset}/fmiou_{variant}"] = float(computed["fmiou"])
        return out

    def per_class_iou(self) -> dict[str, list[float]]:
        return {v: m.compute()["per_class_iou"] for v, m in self.metrics.items()}


class OVSSTask:
    """OVSS of one dataset: its batches, its class prompts and the scoring.

    The frozen text tower embeds the ``K x 80`` class prompts once per task (the tower
    never changes); every :meth:`prototypes` call applies the model's *current* text
    projection to those cached outputs, so a training run re-embeds nothing per epoch.

    Args:
        dataset: the segmentation dataset.
        batch_size: images per batch; for ReSiReg Full the batch is one scene (its
            prototypes are shared across the batch), so the score depends on it.
        num_workers: DataLoader workers decoding and resizing images.
        templates: prompt templates (default: the 80 OpenAI ImageNet templates).
        temperature: softmax temperature of the prediction.
        prompt_batch_size: prompts per text-tower call.
    """

    def __init__(
        self,
        dataset: SegmentationSet,
        batch_size: int = 8,
        num_workers: int = 0,
        templates: Sequence[Callable[[str], str]] = TEMPLATES,
        temperature: float = 100.0,
        prompt_batch_size: int = 1024,
    ) -> None:
        if batch_size < 1:
            raise ValueError(f"batch_size must be >= 1, got {batch_size}")
        self.dataset = dataset
        self.batch_size = batch_size
        self.num_workers = num_workers
        self.prompts = class_prompts(dataset.classes, templates)
        self.temperature = temperature
        self.prompt_batch_size = prompt_batch_size
        self.tower_calls = 0
        self._tower_out: Tensor | None = None

    @torch.no_grad()
    def prototypes(self, vlm: ResiregVLM) -> Tensor:
        """Class prototypes ``[K, 512]`` from the cached tower outputs and the current projection."""
        if self._tower_out is None:
            step = self.prompt_batch_size
            chunks = [
                vlm.text(self.prompts[i : i + step], cache=False)
                for i in range(0, len(self.prompts), step)
            ]
            self.tower_calls += len(chunks)
            self._tower_out = torch.cat(chunks)
        projected = vlm.text_proj(self._tower_out.to(vlm.device, torch.float32))
        return average_prompts(dense_text_half(projected), len(self.dataset.classes))

    def loader(self, rank: int = 0, world_size: int = 1) -> DataLoader:
        return DataLoader(
            self.dataset,
            batch_sampler=self.dataset.batches(self.batch_size, rank, world_size),
            collate_fn=collate_segmentation,
            num_workers=self.num_workers,
        )

    @torch.no_grad()
    def run(
        self,
        vlm: ResiregVLM,
        variants: Mapping[str, nn.Module | None],
        rank: int = 0,
        world_size: int = 1,
        precision: str = "32",
        timer: StageTimer | None = None,
    ) -> OVSSResult:
        """Score this rank's share of the batches (``reduce`` the result across ranks).

        Args:
            vlm: the model (its modules are put in eval mode for the pass and restored).
            variants: ``build_variants`` output.
            rank, world_size: this process's share: batches ``rank::world_size``.
            precision: ``"32"`` (fp32, the protocol's default) or ``"bf16"`` (autocast).
            timer: collects seconds per stage (``data``, ``backbone``, ``head``,
                ``reconstruction/<variant>``, ``metric``).
        """
        if str(precision) not in PRECISIONS:
            raise ValueError(f"precision={precision!r}: expected one of {sorted(PRECISIONS)}")
        dtype = PRECISIONS[str(precision)]
        timed = timer or _no_timer
        k = len(self.dataset.classes)
        metrics = {
            v: SegmentationMetric(k, self.dataset.ignore_index, self.dataset.reduce_zero_label)
            for v in variants
        }
        result = OVSSResult(self.dataset.name, metrics)
        result.batch_sizes = dict(
            sorted(Counter(len(b) for b in self.dataset.batches(self.batch_size)).items())
        )
        if rank == 0:  # images whose header was unreadable (counted once across ranks)
            result.skipped = len(self.dataset.unreadable)
        modes = {m: m.training for m in vlm.modules()}
        vlm.eval()
        try:
            protos = self.prototypes(vlm)
            device = vlm.device
            with torch.autocast(
                device.type, dtype=dtype or torch.float32, enabled=dtype is not None
            ):
                batches = iter(self.loader(rank, world_size))
                while True:
                    with timed("data"):
                        batch = next(batches, None)
                    if batch is None:
                        break
                    result.skipped += batch["skipped"]
                    if batch["image"] is None:
                        continue
                    self._score(vlm, batch, variants, protos, metrics, timed)
                    result.images += len(batch["label"])
        finally:
            for module, mode in modes.items():
                module.training = mode
        return result

    def _score(self, vlm, batch, variants, protos, metrics, timed) -> None:
        x = vlm.preprocess(batch["image"])
        with timed("backbone"):
            feats = vlm.backbone(x)
        with timed("head"):
            lang = vlm.head(feats).patches
        for name, module in variants.items():
            with timed(f"reconstruction/{name}"):
                dense = (
                    F.normalize(lang.float(), dim=1)
                    if module is None
                    else module(feats.patches, lang)
                )
            with timed("metric"):
                for i, label in enumerate(batch["label"]):
                    pred, _ = predict(
                        dense[i : i + 1], protos, tuple(label.shape), self.temperature
                    )
                    metrics[name].update(pred[0], label)
