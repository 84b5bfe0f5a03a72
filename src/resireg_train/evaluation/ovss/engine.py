"""OVSS evaluation of any :class:`~resireg.models.DenseEncoder` for the ReSiReg variants.

One engine serves the ``ReSiRegEval`` training callback, ``resireg-eval`` and
``benchmarks/bench_eval.py``, so a number logged during training is recomputed exactly by
``resireg-eval`` on the exported model.

Per batch (images of one size, see :meth:`SegmentationSet.batches`): the encoder runs once
(``encode``); each variant of :func:`resireg.method.variants.build_variants` turns its
(intermediates, language tokens) into dense features; every image is then predicted
against the text prototypes at the features' grid (:func:`resireg.ovss.predict_grid`) and
scored at its label's full resolution in one confusion matrix per variant (docs/method.md#2d-evaluation-ovss): each label is counted once per batch against the grid's cells
(:meth:`SegmentationMetric.blocks`), which gives the confusion of the nearest-upsampled
prediction (:func:`resireg.ovss.predict`) without upsampling it for every configuration.

A configuration ``<variant>@layer:<block>`` (``lite@layer:5``; the CLIP layer sweep, docs/method.md#2d-evaluation-ovss) runs on that encoder block's intermediates instead of the encoder's own: the
encoder's ``encode_layers`` returns every block the configurations ask for from the same
single pass (``DenseOutput.layers``), and each configuration takes its block's tensor. Work
the configurations of a batch share (:func:`resireg.method.variants.apply_variant`) is shared only
between configurations on the same block.
"""

from __future__ import annotations

from collections import Counter, defaultdict
from collections.abc import Callable, Iterable, Mapping, Sequence
from dataclasses import dataclass, field
from typing import TYPE_CHECKING, Any

import torch
from torch import Tensor, nn

from resireg.method.variants import apply_variant
from resireg.models import DenseEncoder, DenseOutput
from resireg.ovss import SegmentationMetric, class_similarity, predict_grid, template_set
from resireg.specs.metrics import METRIC_SPECS
from resireg.specs.variants import BASELINE, VARIANTS, parse_variant, takes_prior, variant_layer
from resireg_train.data.segmentation import SegmentationSet, SkippedSample, collate_segmentation
from resireg_train.data.windows import window_rules
from resireg_train.evaluation.engine import (  # shared with the 3D engine; importable from here too
    ClassPrototypes,
    EvalEngine,
    StageTimer,
    check_variants_on,
    inference,
    no_timer,
    nonfinite_output,
)
from resireg_train.evaluation.ovss.slide import (
    classify,
    crop_windows,
    stitch,
    to_label,
    window_boxes,
    window_logits,
    window_shape,
)
from resireg_train.evaluation.specs import TASK_SPECS

if TYPE_CHECKING:
    from resireg_train.evaluation.cache import FeatureCache

__all__ = [
    "METRIC_PREFIX",
    "OVSSEngine",
    "OVSSResult",
    "StageTimer",
    "check_variants_on",
    "configuration_layers",
    "inference",
    "requested_layers",
]

#: What the scores' names start with, ``val/ovss/``: the task table's
#: (:attr:`resireg_train.evaluation.specs.TaskSpec.metric_prefix`), also the training callback's.
METRIC_PREFIX = TASK_SPECS["ovss"].metric_prefix
#: The variants that read the intermediates: all but the backbone alone (the @layer: error).
_INTERMEDIATE_VARIANTS = tuple(v for v in VARIANTS if v != BASELINE)

#: The scores logged per configuration (the metric table's pixel scorer).
_LOGGED = METRIC_SPECS["pixels"].logged


def configuration_layers(
    encoder: DenseEncoder, names: Iterable[str], key: str = "variants"
) -> dict[str, int | None]:
    """Each configuration's encoder block (``@layer:<block>``, as the encoder's 0-based index)
    or ``None`` (the encoder's own intermediates). Fails before any encoding, naming the
    configuration and ``key``, when the encoder returns no per-block intermediates (it needs
    ``encode_layers`` and ``check_layers``, as :class:`~resireg.models.zoo.clip.ClipEncoder` has),
    when the block does not exist, or for ``bb`` (it uses no intermediates)."""
    out: dict[str, int | None] = {}
    for name in names:
        layer = variant_layer(name)
        out[name] = layer
        if layer is None:
            continue
        if parse_variant(name)[0] == BASELINE:
            raise ValueError(
                f"{key}: {name!r}: {BASELINE} scores the language tokens alone; @layer: applies to "
                f"the variants that use the intermediates ({', '.join(_INTERMEDIATE_VARIANTS)})"
            )
        check = getattr(encoder, "check_layers", None)
        if check is None or not callable(getattr(encoder, "encode_layers", None)):
            raise ValueError(
                f"{key}: {name!r}: {type(encoder).__name__} returns no per-block intermediates "
                "(encode_layers); @layer: needs a CLIP encoder (encoder=clip_vit_b16 or "
                "clip_vit_l14_336)"
            )
        (out[name],) = check([layer], f"{key}: {name!r}: layer")
    return out


def requested_layers(
    encoder: DenseEncoder, names: Iterable[str], key: str = "variants"
) -> tuple[int, ...]:
    """The encoder blocks the configurations ``names`` run on (:func:`configuration_layers`),
    sorted, each once; ``()`` when none asks for one (then ``encode`` runs, not
    ``encode_layers``)."""
    return _blocks(configuration_layers(encoder, names, key))


def _blocks(layer_of: Mapping[str, int | None]) -> tuple[int, ...]:
    """The blocks of :func:`configuration_layers`' output, sorted, each once."""
    return tuple(sorted({layer for layer in layer_of.values() if layer is not None}))


@dataclass
class OVSSResult:
    """Confusion matrices per variant and counts of one evaluation pass.

    ``batch_sizes`` counts the batches *scored* per number of images (a batch that lost an
    image to a skip counts at its smaller size); ``skipped_samples`` names every image that
    was not scored and why.
    """

    dataset: str
    metrics: dict[str, SegmentationMetric]
    max_batch_size: int
    images: int = 0
    skipped_samples: list[SkippedSample] = field(default_factory=list)
    batch_sizes: Counter[int] = field(default_factory=Counter)

    @property
    def skipped(self) -> int:
        return len(self.skipped_samples)

    def reduce(
        self,
        all_reduce: Callable[[Tensor], Tensor],
        all_gather_object: Callable[[Any], list[Any]],
        device: torch.device,
    ) -> None:
        """Combine the ranks' results: confusion matrices, image count and batch-size
        histogram are summed with ``all_reduce`` (one tensor), the skipped samples gathered
        with ``all_gather_object``. Every rank must call this at the same point.

        The packed tensor is moved to ``device`` first: NCCL reduces only tensors on the
        rank's GPU (gloo takes either), so pass the module's device.
        """
        names = list(self.metrics)
        histogram = torch.zeros(self.max_batch_size + 1, dtype=torch.int64)
        for size, count in self.batch_sizes.items():
            histogram[size] = count
        packed = torch.cat(
            [self.metrics[n].confusion.reshape(-1) for n in names]
            + [torch.tensor([self.images], dtype=torch.int64), histogram]
        ).to(device)
        total = all_reduce(packed).to(torch.int64).cpu()
        offset = 0
        for n in names:
            size = self.metrics[n].confusion.numel()
            self.metrics[n].confusion = (
                total[offset : offset + size].reshape(self.metrics[n].confusion.shape).clone()
            )
            offset += size
        self.images = int(total[offset])
        sizes = total[offset + 1 :].tolist()
        self.batch_sizes = Counter({b: int(n) for b, n in enumerate(sizes) if n})
        gathered = all_gather_object(self.skipped_samples)
        self.skipped_samples = sorted((s for part in gathered for s in part), key=lambda s: s.index)

    def skip_report(self) -> str:
        """One line: how many images were skipped, each named with its reason."""
        scored = self.images + self.skipped
        named = "; ".join(f"{s.file}: {s.reason}" for s in self.skipped_samples)
        return f"{self.dataset}: skipped {self.skipped} of {scored} images ({named})"

    def scores(self, prefix: str = METRIC_PREFIX) -> dict[str, float]:
        """``{"<prefix><dataset>/miou_<variant>": ..., ".../fmiou_<variant>": ...}`` (``prefix``
        ends with ``/``; :data:`METRIC_PREFIX`, the task table's, by default)."""
        out = {}
        for variant, metric in self.metrics.items():
            computed = metric.compute()
            for name in _LOGGED:
                out[f"{prefix}{self.dataset}/{name}_{variant}"] = float(computed[name])
        return out

    def per_class_iou(self) -> dict[str, list[float]]:
        return {v: m.compute()["iou"] for v, m in self.metrics.items()}


class OVSSEngine(EvalEngine):
    """OVSS of one dataset: its batches, its class prompts and the scoring.

    The class prototypes are the tasks' shared text path
    (:class:`resireg_train.evaluation.base.ClassPrototypes`: the ``K x T`` class prompts embedded
    once by ``text_features``; every :meth:`prototypes` call applies the encoder's *current*
    ``dense_text``), so a training run re-embeds nothing per epoch.

    Args:
        dataset: the segmentation dataset.
        batch_size: images per batch; for ReSiReg Full the batch is one scene (its
            prototypes are shared across the batch), so the score depends on it.
        num_workers: DataLoader workers decoding and resizing images.
        templates: prompt templates; ``None``: the dataset's set (its entry's ``templates``:
            the 80 OpenAI ImageNet templates in the paper's and the OVSS field's protocols).
        temperature: softmax temperature of the prediction.
        prompt_batch_size: prompts per text-tower call.
    """

    collate = staticmethod(collate_segmentation)
    unit = "images"

    def __init__(
        self,
        dataset: SegmentationSet,
        batch_size: int = 8,
        num_workers: int = 2,
        templates: Sequence[Callable[[str], str]] | None = None,
        temperature: float = 100.0,
        prompt_batch_size: int = 1024,
    ) -> None:
        templates = template_set(dataset.templates) if templates is None else templates
        super().__init__(dataset, batch_size, num_workers, templates, prompt_batch_size)
        self.temperature = temperature
        # Every name of every class is prompted (synonyms, conf/classes/): one prototype per
        # name, ``name_class`` its class (the identity when each class has one name).
        names = getattr(dataset, "names", None) or tuple((c,) for c in dataset.classes)
        self.name_class = torch.tensor([k for k, n in enumerate(names) for _ in n])
        if len(self.name_class) != len(dataset.classes):
            self.text = ClassPrototypes([x for n in names for x in n], templates, prompt_batch_size)
        self.windows = getattr(dataset, "windows", None) or window_rules("paper")

    def batch_shapes(self) -> list[tuple[int, int, int]]:
        """``(inputs, height, width)`` of every encoder pass: a batch's images (one size), or
        with sliding windows every window of them (:func:`~resireg_train.evaluation.ovss.slide.
        window_shape`)."""
        sizes = self.dataset.grid_sizes()
        shapes = []
        for b in self.dataset.batches(self.batch_size):
            h, w = sizes[b[0]]
            if self.windows.sliding:
                crop, stride = self.windows.slide_crop, self.windows.slide_stride
                n = len(window_boxes(h, w, crop, stride))
                shapes.append((len(b) * n, *window_shape(h, w, crop, self.dataset.patch_size)))
            else:
                shapes.append((len(b), h, w))
        return shapes

    @torch.no_grad()
    def run(
        self,
        encoder: DenseEncoder,
        variants: Mapping[str, nn.Module],
        rank: int = 0,
        world_size: int = 1,
        precision: str = "32",
        timer: StageTimer | None = None,
        cache: FeatureCache | None = None,
        prior: Callable[[Tensor], Tensor] | None = None,
    ) -> OVSSResult:
        """Score this rank's share of the batches (``reduce`` the result across ranks).

        Args:
            encoder: the model (its modules are put in eval mode for the pass and restored).
            variants: ``resireg.method.variants.build_variants`` output.
            rank, world_size: this process's share: batches ``rank::world_size``.
            precision: ``"32"`` (fp32, the protocol's default) or ``"bf16"`` (autocast).
            timer: collects seconds per stage (``data``, ``encoder``, ``cache`` (reads),
                ``prior``, ``reconstruction/<variant>``, ``metric``).
            cache: stored encoder outputs of this dataset (read where present, written
                where missing); its key must match ``encoder``, the dataset,
                ``precision`` and the blocks the configurations run on
                (:meth:`resireg_train.evaluation.cache.FeatureCache.key_for` with
                ``layers=requested_layers(encoder, variants)``).
            prior: segmentation-prior provider (:class:`resireg.priors.SamPrior`), needed
                when a configuration takes the prior (``full+prior``): called once per batch
                on its resized images before normalisation (timer stage ``prior``); its map
                goes to every ``+prior`` configuration, the others get none.
        """
        needs_prior = [v for v in variants if takes_prior(v)]
        if needs_prior and prior is None:
            raise ValueError(f"variants {needs_prior} take a segmentation prior; pass prior=")
        layer_of = configuration_layers(encoder, variants)
        layers = _blocks(layer_of)
        if cache is not None and tuple(cache.layers) != layers:
            raise ValueError(
                f"the feature cache {cache.folder} holds the intermediates of blocks "
                f"{list(cache.layers)}, the configurations run on {list(layers)}: build its key "
                "with FeatureCache.key_for(..., layers=requested_layers(encoder, variants))"
            )
        if cache is not None and self.windows.sliding:
            raise ValueError(
                "feature_cache stores whole images' encoder outputs; the dataset's "
                "protocol slides windows (dataset.slide_crop): run without a cache"
            )
        timed = timer or no_timer
        k = len(self.dataset.classes)
        metrics = {
            v: SegmentationMetric(k, self.dataset.ignore_index, self.dataset.reduce_zero_label)
            for v in variants
        }
        result = OVSSResult(self.dataset.name, metrics, self.batch_size)
        self.dataset.grid_sizes()  # reads the headers once; unreadable ones are listed
        if rank == 0:  # images whose header was unreadable (reported once across ranks)
            result.skipped_samples.extend(self.dataset.unreadable)
        try:
            with inference(encoder, precision):
                with torch.autocast(encoder.device.type, enabled=False):
                    protos = self.prototypes(encoder)  # the text path in fp32, whatever precision
                batches = iter(self.loader(rank, world_size))
                while True:
                    with timed("data"):
                        batch = next(batches, None)
                    if batch is None:
                        break
                    result.skipped_samples.extend(batch["skipped"])
                    if batch["image"] is None:
                        continue
                    bad = self._score(encoder, batch, variants, protos, metrics, timed, cache,
                                      prior, layer_of)  # fmt: skip
                    if bad is not None:  # non-finite encoder output: skipped and counted
                        result.skipped_samples.extend(
                            SkippedSample(i, self.dataset.describe(i), bad) for i in batch["index"]
                        )
                        continue
                    result.images += len(batch["label"])
                    result.batch_sizes[len(batch["label"])] += 1
        finally:
            if cache is not None:
                cache.flush()
        return result

    @staticmethod
    def _encode(encoder, batch, timed, cache, layers=()) -> tuple[DenseOutput, str | None]:
        """The encoder's outputs for the batch: from ``cache`` when it holds every image,
        else one ``encode`` (``encode_layers`` when configurations run on ``layers``; stored
        in ``cache`` if given), and why they cannot be scored (:func:`nonfinite_output`) or
        ``None``. A non-finite output is not stored in the cache."""
        if cache is not None:
            with timed("cache"):
                out = cache.get(batch["index"], encoder.device)
            if out is not None:
                return out, nonfinite_output(out)
        x = encoder.input_rule.normalize(batch["image"].to(encoder.device))
        with timed("encoder"):
            out = encoder.encode_layers(x, layers) if layers else encoder.encode(x)
        bad = nonfinite_output(out)
        if cache is not None and bad is None:
            cache.put(batch["index"], out)
        return out, bad

    def _score(
        self, encoder, batch, variants, protos, metrics, timed, cache=None, prior=None,
        layer_of=None,
    ) -> str | None:  # fmt: skip
        """Score one batch with every configuration; returns why it was not scored (a
        non-finite encoder output, :func:`nonfinite_output`) or ``None``."""
        layer_of = layer_of or dict.fromkeys(variants)
        boxes = None
        if self.windows.sliding:  # every window of every image, one encoder pass
            h, w = batch["image"].shape[-2:]
            boxes = window_boxes(h, w, self.windows.slide_crop, self.windows.slide_stride)
            batch = {**batch, "image": crop_windows(batch["image"], boxes,
                                                    self.windows.slide_crop,
                                                    self.dataset.patch_size)}  # fmt: skip
        out, bad = self._encode(encoder, batch, timed, cache, _blocks(layer_of))
        if bad is not None:
            return bad
        seg = None  # the prior's instance map, once per batch, shared by the +prior configs
        if prior is not None and any(takes_prior(v) for v in variants):
            with timed("prior"):
                seg = prior(batch["image"]).to(out.intermediates.device)
        # Work common to the configurations of this batch on one block (apply_variant).
        shared: dict[int | None, dict] = defaultdict(dict)
        # Each label against a prediction grid (bb's patch grid, Lite's and Full's upsampled
        # one), computed once per grid whatever the number of configurations on it.
        blocks: dict[tuple[int, ...], list[Tensor]] = {}
        for name, variant in variants.items():
            s = seg if takes_prior(name) else None
            layer = layer_of[name]
            inter = out.intermediates if layer is None else out.layers[layer]
            with timed(f"reconstruction/{name}"):
                dense = apply_variant(variant, inter, out.language, s, shared=shared[layer])
            with timed("metric"):
                if self.windows.upsample == "bilinear":
                    self._score_logits(dense, batch, protos, metrics[name], boxes)
                    continue
                grid = tuple(dense.shape[-2:])
                if grid not in blocks:
                    blocks[grid] = [metrics[name].blocks(label, grid) for label in batch["label"]]
                for i, label_blocks in enumerate(blocks[grid]):  # per image: K x h x w logits
                    metrics[name].update_grid(self._grid_labels(dense[i : i + 1], protos)[0],
                                              label_blocks)  # fmt: skip
        return None

    def _grid_labels(self, dense: Tensor, protos: Tensor) -> Tensor:
        """The paper's path: labels ``[B, h, w]`` at the feature grid (softmax with the
        temperature, argmax; each class by its best name; the background rule on the grid's
        probabilities when the entry sets one)."""
        rule = self.windows
        if len(self.name_class) == len(self.dataset.classes) and rule.background_threshold is None:
            return predict_grid(dense, protos, self.temperature)  # one name per class
        logits = class_similarity(dense, protos)
        return classify(logits, self.name_class, rule.background_threshold,
                        rule.background_logit_scale)  # fmt: skip

    def _score_logits(self, dense, batch, protos, metric, boxes) -> None:
        """The OVSS field's path (:mod:`resireg_train.evaluation.ovss.slide`): per image, the logits
        bilinear to each window (or the whole input), the windows averaged, bilinear to the
        label, then each class's best name, the argmax and the background threshold."""
        rule = self.windows
        size = tuple(batch["image"].shape[-2:])  # the windows' (padded) or the input's size
        per_image = len(boxes) if boxes else 1
        for i, label in enumerate(batch["label"]):
            part = dense[i * per_image : (i + 1) * per_image]
            if boxes:
                image_size = (boxes[-1][1], boxes[-1][3])  # the last window ends at the corner
                windows = (
                    window_logits(part[j : j + 1], protos, size)[0] for j in range(per_image)
                )  # one window at a time
                logits = stitch(windows, boxes, image_size)
            else:
                logits = window_logits(part, protos, size)[0]
            logits = to_label(logits, tuple(label.shape[-2:]))
            pred = classify(logits, self.name_class, rule.background_threshold,
                            rule.background_logit_scale)  # fmt: skip
            metric.update(pred, label)
