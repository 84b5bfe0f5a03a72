"""The parts the 2D and 3D evaluation engines share (docs/architecture.md#adding-a-task).

The engines (:class:`resireg_train.evaluation.ovss.engine.OVSSEngine`, 2D;
:class:`resireg_train.evaluation.mapping.engine.MappingEngine`, 3D) derive from :class:`EvalEngine`: one
batch-size check, one class-prototype text path (:class:`ClassPrototypes`), one loader
(:func:`eval_loader`) and one variant check over the batches (:func:`check_variants_on`); both
pass the encoder through :func:`inference` and time stages with :class:`StageTimer`.
"""

from __future__ import annotations

import time
from abc import ABC, abstractmethod
from collections import defaultdict
from collections.abc import Callable, Iterable, Iterator, Mapping, Sequence
from contextlib import contextmanager
from typing import Any

import torch
from torch import Tensor, nn
from torch.utils.data import DataLoader, Dataset

from resireg.method.checks import NonFiniteError, check_features
from resireg.models import DenseEncoder, DenseOutput
from resireg.ovss import TEMPLATES, average_prompts, class_prompts
from resireg.specs.rules import check_batch_size
from resireg_train.evaluation.specs import PRECISIONS

__all__ = [
    "ClassPrototypes",
    "EvalEngine",
    "StageTimer",
    "check_variants_on",
    "eval_loader",
    "inference",
    "no_timer",
    "nonfinite_output",
]


class StageTimer:
    """Wall seconds per stage (``with timer("encoder"): ...``); CUDA is synchronised."""

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
def no_timer(stage: str) -> Iterator[None]:
    """A stage timer that times nothing: the engines' default where no StageTimer is given."""
    yield


@contextmanager
def inference(encoder: DenseEncoder, precision: str) -> Iterator[None]:
    """An evaluation pass of ``encoder`` (2D and 3D): every module in eval mode (each
    module's mode restored afterwards), autocast as ``precision`` says: ``"32"`` disables it
    explicitly (fp32 even inside a ``bf16-mixed`` training run), ``"bf16"`` enables it."""
    if str(precision) not in PRECISIONS:
        raise ValueError(f"precision={precision!r}: expected one of {sorted(PRECISIONS)}")
    name = PRECISIONS[str(precision)]
    dtype = getattr(torch, name) if name else None
    modes = {m: m.training for m in encoder.modules()}
    encoder.eval()
    try:
        with torch.autocast(
            encoder.device.type, dtype=dtype or torch.float32, enabled=dtype is not None
        ):
            yield
    finally:
        for module, mode in modes.items():
            module.training = mode


def nonfinite_output(out: DenseOutput) -> str | None:
    """Why the encoder's output for a batch cannot be scored, or ``None``: the engines check
    it once as it enters them (fresh or from the feature cache), with the variants' own rule
    (:func:`resireg.method.checks.check_features`), so a batch whose ``intermediates``, ``language``
    tokens or per-block intermediates hold NaN or inf is skipped and counted (each of its
    images a skipped sample with this reason) instead of scored: in Full one NaN spreads to
    every image of the batch. A non-floating output is an encoder bug and raises."""
    named = [("intermediates", out.intermediates), ("language", out.language)]
    named += [(f"layers[{k}]", v) for k, v in sorted((out.layers or {}).items())]
    for name, tensor in named:
        try:
            check_features(f"encoder output {name}", tensor)
        except NonFiniteError as err:
            return f"{err}; its batch of {tensor.shape[0]} was not scored"
    return None


def check_variants_on(
    variants: Mapping[str, nn.Module],
    shapes: Iterable[tuple[int, int, int]],
    patch: int,
    dataset: str,
    batch_size: int,
    unit: str = "images",
    key: str = "",
) -> None:
    """Fail before any encoding if a variant cannot run on a batch of ``(images, height,
    width)`` in ``shapes`` (e.g. more prototypes than the batch has points); the error names
    ``key.<variant>`` and the batch: ``dataset 'x' with batch_size=B has a batch of b <unit>
    of h x w px``."""
    for name, variant in variants.items():
        check = getattr(variant, "check_grid", None)
        if check is None:
            continue
        for b, h, w in sorted(set(shapes)):
            try:
                check(b, h // patch, w // patch)
            except ValueError as err:
                label = f"{key}.{name}" if key else name
                raise ValueError(
                    f"{label}: {err}; dataset {dataset!r} with batch_size={batch_size} has a "
                    f"batch of {b} {unit} of {h} x {w} px"
                ) from err


class ClassPrototypes:
    """The class-prototype text path of every task: the ``K x T`` class prompts
    (:func:`resireg.ovss.class_prompts`), embedded once by the encoder's frozen text part
    (``text_features``, ``prompt_batch_size`` prompts per call), then per call the encoder's
    *current* ``dense_text`` and the per-class average (:func:`resireg.ovss.average_prompts`),
    so a training run re-embeds nothing per epoch.

    Args:
        classes: the class names, in label order.
        templates: prompt templates (default: the 80 OpenAI ImageNet templates).
        prompt_batch_size: prompts per text-tower call.
    """

    def __init__(
        self,
        classes: Sequence[str],
        templates: Sequence[Callable[[str], str]] = TEMPLATES,
        prompt_batch_size: int = 1024,
    ) -> None:
        self.classes = tuple(classes)
        self.prompts = class_prompts(self.classes, templates)
        self.prompt_batch_size = prompt_batch_size
        self.tower_calls = 0
        self._text_features: Tensor | None = None

    @torch.no_grad()
    def __call__(self, encoder: DenseEncoder) -> Tensor:
        """Class prototypes ``[K, Dl]`` (unit norm) from the once-computed text features and
        the encoder's current ``dense_text``."""
        if self._text_features is None:
            step = self.prompt_batch_size
            chunks = [
                encoder.text_features(self.prompts[i : i + step])
                for i in range(0, len(self.prompts), step)
            ]
            self.tower_calls += len(chunks)
            self._text_features = torch.cat(chunks)
        return average_prompts(encoder.dense_text(self._text_features), len(self.classes))


def eval_loader(
    dataset: Dataset, batches: list[list[int]], collate: Callable, num_workers: int
) -> DataLoader:
    """The DataLoader of an evaluation pass: ``batches`` (index lists, the dataset's own batch
    rule) in order, ``collate`` into one batch dict each, decoded by ``num_workers`` workers."""
    return DataLoader(dataset, batch_sampler=batches, collate_fn=collate, num_workers=num_workers)


class EvalEngine(ABC):
    """The skeleton of the 2D and 3D engines: the dataset, its batches of ``batch_size``
    (checked once, :func:`resireg.specs.rules.check_batch_size`), the loader
    (:func:`eval_loader` with the subclass's ``collate``), the class prototypes
    (:class:`ClassPrototypes` of the dataset's classes) and the variant check over every batch
    shape (:meth:`batch_shapes`, :func:`check_variants_on`).

    Args:
        dataset: a dataset with ``classes``, ``name``, ``patch_size`` and
            ``batches(batch_size, *shard)``.
        batch_size: images (frames) per batch; ReSiReg Full's scene.
        num_workers: DataLoader workers.
        templates, prompt_batch_size: :class:`ClassPrototypes`.
    """

    #: ``collate(items) -> batch`` of the dataset's items (a ``staticmethod``).
    collate: Callable[[list], dict[str, Any]]
    #: What a batch holds, for errors (``images``, ``frames``).
    unit = "images"

    def __init__(
        self,
        dataset: Any,
        batch_size: int,
        num_workers: int = 0,
        templates: Sequence[Callable[[str], str]] = TEMPLATES,
        prompt_batch_size: int = 1024,
    ) -> None:
        self.batch_size = check_batch_size(batch_size)
        self.dataset = dataset
        self.num_workers = num_workers
        self.text = ClassPrototypes(dataset.classes, templates, prompt_batch_size)

    @property
    def prompts(self) -> list[str]:
        return self.text.prompts

    @property
    def tower_calls(self) -> int:
        """Text-tower calls so far (one task embeds its prompts once)."""
        return self.text.tower_calls

    def prototypes(self, encoder: DenseEncoder) -> Tensor:
        """Class prototypes ``[K, Dl]`` (:class:`ClassPrototypes`)."""
        return self.text(encoder)

    def loader(self, *shard: int) -> DataLoader:
        """The loader of this task's batches (``shard``: ``rank, world_size`` where the
        dataset's ``batches`` takes them)."""
        batches = self.dataset.batches(self.batch_size, *shard)
        return eval_loader(self.dataset, batches, self.collate, self.num_workers)

    @abstractmethod
    def batch_shapes(self) -> list[tuple[int, int, int]]:
        """``(items, height, width)`` of every batch (of the encoder input)."""

    def check_variants(self, variants: Mapping[str, nn.Module], key: str = "") -> None:
        """Fail before any encoding if a variant cannot run on some batch of this task (e.g.
        more prototypes than a batch has points); the error names ``key.<variant>``."""
        check_variants_on(variants, self.batch_shapes(), self.dataset.patch_size,
                          self.dataset.name, self.batch_size, self.unit, key)  # fmt: skip
