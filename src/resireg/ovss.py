"""Open-vocabulary semantic segmentation (OVSS): vocabularies, text prototypes, metric.

The protocol follows the paper's appendix (docs/method.md#2d-evaluation-ovss): one text prototype
per class from the 80 OpenAI ImageNet templates, cosine similarity with dense features,
nearest upsampling to the label size, softmax with temperature 100, argmax; mIoU over
classes present, ignore index 255.
"""

from __future__ import annotations

from collections.abc import Callable, Sequence

import numpy as np
import open_clip
import torch
import torch.nn.functional as F
from torch import Tensor

from resireg.specs.prompts import TEMPLATE_SET, TEMPLATE_SETS

__all__ = [
    "TEMPLATES",
    "template_set",
    "template_label",
    "ADE20K_CLASSES",
    "ORAD3D_CLASSES",
    "NYU40_CLASSES",
    "SCANNET_CLASSES",
    "VOCABULARIES",
    "vocabulary",
    "class_prompts",
    "average_prompts",
    "text_prototypes",
    "class_similarity",
    "predict",
    "predict_grid",
    "label_problem",
    "SegmentationMetric",
]

#: The 80 prompt templates of OpenAI's CLIP ImageNet evaluation, as shipped by open_clip.
TEMPLATES: tuple[Callable[[str], str], ...] = tuple(open_clip.OPENAI_IMAGENET_TEMPLATES)


def template_set(templates: str) -> tuple[Callable[[str], str], ...]:
    """The templates of the set named ``templates`` (:data:`resireg.specs.prompts.TEMPLATE_SETS`:
    open_clip's ``openai_imagenet``, the 80 above, or ``simple_imagenet``, 7 of them); a
    ValueError naming the value and the choices otherwise."""
    check, expected = TEMPLATE_SET
    if not check(templates):
        raise ValueError(f"templates={templates!r}: expected {expected}")
    return tuple(getattr(open_clip, TEMPLATE_SETS[templates]))


def template_label(templates: str) -> str:
    """How a run's protocol record names the set ``templates``: open_clip's constant and the
    count, e.g. ``open_clip OPENAI_IMAGENET_TEMPLATES (80)``."""
    return f"open_clip {TEMPLATE_SETS[templates]} ({len(template_set(templates))})"


#: ADE20K-150 class names in the form used by the training-free OVSS line of work that
#: RADSeg evaluates with (one name per class, label order 0..149 after reduce_zero_label).
ADE20K_CLASSES: tuple[str, ...] = (
    "wall", "building", "sky", "floor", "tree", "ceiling", "road", "bed", "windowpane",
    "grass", "cabinet", "sidewalk", "person", "earth", "door", "table", "mountain", "plant",
    "curtain", "chair", "car", "water", "painting", "sofa", "shelf", "house", "sea",
    "mirror", "rug", "field", "armchair", "seat", "fence", "desk", "rock", "wardrobe",
    "lamp", "bathtub", "railing", "cushion", "base", "box", "column", "signboard",
    "chestofdrawers", "counter", "sand", "sink", "skyscraper", "fireplace", "refrigerator",
    "grandstand", "path", "stairs", "runway", "case", "pooltable", "pillow", "screendoor",
    "stairway", "river", "bridge", "bookcase", "blind", "coffeetable", "toilet", "flower",
    "book", "hill", "bench", "countertop", "stove", "palm", "kitchenisland", "computer",
    "swivelchair", "boat", "bar", "arcademachine", "hovel", "bus", "towel", "light",
    "truck", "tower", "chandelier", "awning", "streetlight", "booth", "televisionreceiver",
    "airplane", "dirttrack", "apparel", "pole", "land", "bannister", "escalator", "ottoman",
    "bottle", "buffet", "poster", "stage", "van", "ship", "fountain", "conveyerbelt",
    "canopy", "washer", "plaything", "swimmingpool", "stool", "barrel", "basket",
    "waterfall", "tent", "bag", "minibike", "cradle", "oven", "ball", "food", "step",
    "tank", "tradename", "microwave", "pot", "animal", "bicycle", "lake", "dishwasher",
    "screen", "blanket", "sculpture", "hood", "sconce", "vase", "trafficlight", "tray",
    "ashcan", "fan", "pier", "crtscreen", "plate", "monitor", "bulletinboard", "shower",
    "radiator", "glass", "clock", "flag",
)  # fmt: skip

#: ORAD-3D's 10 classes (label ids 0..9 in this order).
ORAD3D_CLASSES: tuple[str, ...] = (
    "road", "traversable ground", "car", "person", "water", "snow", "grass on road",
    "rock", "sky", "background",
)  # fmt: skip

#: The NYU40 class names by id - 1 (id 1 = wall ... 40 = otherprop): ScanNet's label set.
NYU40_CLASSES: tuple[str, ...] = (
    "wall", "floor", "cabinet", "bed", "chair", "sofa", "table", "door", "window",
    "bookshelf", "picture", "counter", "blinds", "desk", "shelves", "curtain", "dresser",
    "pillow", "mirror", "floor mat", "clothes", "ceiling", "books", "refrigerator",
    "television", "paper", "towel", "shower curtain", "box", "whiteboard", "person",
    "night stand", "toilet", "sink", "lamp", "bathtub", "bag", "otherstructure",
    "otherfurniture", "otherprop",
)  # fmt: skip

#: ScanNet's NYU40 classes without the three catch-all "other" classes (37 classes).
SCANNET_CLASSES: tuple[str, ...] = tuple(
    c for c in NYU40_CLASSES if c not in ("otherstructure", "otherfurniture", "otherprop")
)

VOCABULARIES: dict[str, tuple[str, ...]] = {
    "ade20k": ADE20K_CLASSES,
    "orad3d": ORAD3D_CLASSES,
    "scannet": SCANNET_CLASSES,
}


def vocabulary(name: str) -> tuple[str, ...]:
    """Class names of a named vocabulary (``ade20k``, ``orad3d``, ``scannet``)."""
    try:
        return VOCABULARIES[name]
    except KeyError:
        raise ValueError(
            f"unknown vocabulary {name!r}; choose one of {sorted(VOCABULARIES)}"
        ) from None


def class_prompts(
    class_names: Sequence[str], templates: Sequence[Callable[[str], str]] = TEMPLATES
) -> list[str]:
    """Every template filled with every class name, class-major: ``K * T`` prompts."""
    if not class_names:
        raise ValueError("class_names is empty")
    return [t(name) for name in class_names for t in templates]


def average_prompts(embeddings: Tensor, num_classes: int) -> Tensor:
    """Class-major prompt embeddings ``[K * T, D]`` -> unit-norm class prototypes ``[K, D]``.

    Each embedding is L2-normalised, the ``T`` embeddings of a class are averaged, and
    the average is renormalised.
    """
    if embeddings.shape[0] % num_classes:
        raise ValueError(
            f"{embeddings.shape[0]} prompt embeddings do not split into {num_classes} classes"
        )
    embeds = F.normalize(embeddings.float(), dim=-1).reshape(num_classes, -1, embeddings.shape[-1])
    return F.normalize(embeds.mean(dim=1), dim=-1)


@torch.no_grad()
def text_prototypes(
    encode_text: Callable[[list[str]], Tensor],
    class_names: Sequence[str],
    templates: Sequence[Callable[[str], str]] = TEMPLATES,
    batch_size: int = 1024,
) -> Tensor:
    """Text prototype per class: :func:`class_prompts` embedded, then :func:`average_prompts`.

    Args:
        encode_text: maps a list of strings to ``[M, D]`` embeddings.
        class_names: ``K`` class names.
        templates: prompt templates (callables ``name -> prompt``).
        batch_size: prompts per ``encode_text`` call.

    Returns:
        ``[K, D]`` unit-norm prototypes.
    """
    prompts = class_prompts(class_names, templates)
    embeds = torch.cat(
        [encode_text(prompts[i : i + batch_size]) for i in range(0, len(prompts), batch_size)]
    )
    return average_prompts(embeds, len(class_names))


def predict_grid(dense: Tensor, prototypes: Tensor, temperature: float = 100.0) -> Tensor:
    """Class prediction ``[B, h, w]`` (int64) at the features' own grid, from dense features
    ``[B, D, h, w]`` and class prototypes ``[K, D]``: cosine similarity, softmax with
    ``temperature``, argmax. :func:`predict` brings it to the label size.

    The softmax does not change the argmax; it is kept so the computation is the protocol's
    as written (docs/method.md#2d-evaluation-ovss).
    """
    logits = class_similarity(dense, prototypes)
    return torch.softmax(temperature * logits, dim=1).argmax(dim=1)


def class_similarity(dense: Tensor, prototypes: Tensor) -> Tensor:
    """Cosine similarity ``[B, K, h, w]`` (float32) of dense features ``[B, D, h, w]`` with
    class prototypes ``[K, D]``: the logits :func:`predict_grid` takes the softmax of."""
    dense = F.normalize(dense.float(), dim=1)
    protos = F.normalize(prototypes.float().to(dense.device), dim=1)
    return torch.einsum("bdhw,kd->bkhw", dense, protos)


def predict(
    dense: Tensor, prototypes: Tensor, size: tuple[int, int], temperature: float = 100.0
) -> Tensor:
    """Per-pixel class prediction ``[B, H, W]`` (int64) from dense features ``[B, D, h, w]``.

    :func:`predict_grid`'s labels brought to the label size ``(H, W)`` with nearest
    upsampling. Nearest upsampling copies whole logit vectors, so taking the argmax before
    upsampling gives exactly the label map of upsampling first, at a fraction of the memory
    (``K x H x W`` floats per image for ADE20K's 150 classes).
    """
    labels = predict_grid(dense, prototypes, temperature).unsqueeze(1).float()
    return F.interpolate(labels, size=size, mode="nearest").squeeze(1).long()


def _nearest_source(grid: tuple[int, int], size: tuple[int, int]) -> Tensor:
    """``[H * W]`` (int64): the cell of a ``grid`` that nearest upsampling to ``size`` copies
    into each pixel, taken from ``F.interpolate`` itself so it is :func:`predict`'s rule."""
    h, w = grid
    cells = torch.arange(h * w, dtype=torch.float64).view(1, 1, h, w)
    return F.interpolate(cells, size=size, mode="nearest").reshape(-1).long()


def label_problem(
    label: Tensor | np.ndarray,
    num_classes: int,
    ignore_index: int = 255,
    reduce_zero_label: bool = False,
) -> str | None:
    """Why ``label`` (class ids as stored in the file) cannot be scored, or ``None``.

    Valid values are ``0..num_classes-1`` and ``ignore_index``; with ``reduce_zero_label``
    (ADE20K) they are ``0..num_classes`` (0 = "other", not scored) and ``ignore_index``. The
    message names the value as it is stored, so it can be found in the file.
    """
    if not isinstance(label, Tensor):
        label = torch.from_numpy(np.asarray(label).astype(np.int64, copy=False))
    values = label.reshape(-1).long()
    top = num_classes if reduce_zero_label else num_classes - 1
    bad = values[((values < 0) | (values > top)) & (values != ignore_index)].unique()
    if bad.numel() == 0:
        return None
    zero = " (0 = other, not scored)" if reduce_zero_label else ""
    ids = ", ".join(str(int(v)) for v in bad[:5]) + (", ..." if bad.numel() > 5 else "")
    noun = "class id" if bad.numel() == 1 else "class ids"
    return f"label holds {noun} {ids}; valid ids are 0..{top}{zero} and {ignore_index} (ignored)"


class SegmentationMetric:
    """Confusion-matrix segmentation metric accumulated over batches.

    Args:
        num_classes: number of classes ``K`` (predictions and labels in ``0..K-1``).
        ignore_index: label value excluded from scoring.
        reduce_zero_label: map label 0 to ``ignore_index`` and ``c`` to ``c - 1`` first
            (ADE20K's convention, where 0 means "other").

    ``update`` takes ``pred`` and ``target`` of the same shape. ``compute`` returns mIoU
    (mean over classes with non-empty union), frequency-weighted IoU, pixel accuracy and
    per-class IoU (NaN for classes with empty union). The confusion matrix (rows: ground
    truth, columns: prediction) is public so distributed runs can sum it across ranks.
    """

    def __init__(
        self, num_classes: int, ignore_index: int = 255, reduce_zero_label: bool = False
    ) -> None:
        if num_classes < 1:
            raise ValueError(f"num_classes must be >= 1, got {num_classes}")
        self.num_classes = num_classes
        self.ignore_index = ignore_index
        self.reduce_zero_label = reduce_zero_label
        self.confusion = torch.zeros(num_classes, num_classes, dtype=torch.int64)

    def reset(self) -> None:
        self.confusion.zero_()

    def _scored(self, target: Tensor) -> tuple[Tensor, Tensor]:
        """``target`` flattened with ``reduce_zero_label`` applied, and the mask of its
        scored pixels (not ``ignore_index``); a ValueError names an invalid class id."""
        target = target.detach().reshape(-1).long().cpu()
        problem = label_problem(target, self.num_classes, self.ignore_index, self.reduce_zero_label)
        if problem:
            raise ValueError(problem)
        if self.reduce_zero_label:
            target = torch.where(
                (target == 0) | (target == self.ignore_index),
                torch.full_like(target, self.ignore_index),
                target - 1,
            )
        return target, target != self.ignore_index

    def _check_pred(self, pred: Tensor) -> None:
        if bool(((pred < 0) | (pred >= self.num_classes)).any()):
            raise ValueError(f"pred holds a class outside 0..{self.num_classes - 1}")

    def update(self, pred: Tensor, target: Tensor) -> None:
        if pred.shape != target.shape:
            raise ValueError(
                f"pred shape {tuple(pred.shape)} does not match target shape {tuple(target.shape)}"
            )
        pred = pred.detach().reshape(-1).long().cpu()
        target, valid = self._scored(target)
        pred, target = pred[valid], target[valid]
        self._check_pred(pred)
        k = self.num_classes
        self.confusion += torch.bincount(target * k + pred, minlength=k * k).reshape(k, k)

    def blocks(self, target: Tensor, grid: tuple[int, int]) -> Tensor:
        """``[h * w, K]`` (int32): for each cell of a prediction ``grid``, how many scored
        pixels of each class of ``target`` ``[H, W]`` it covers under :func:`predict`'s
        nearest upsampling.

        What :meth:`update_grid` needs of a label. It depends on the label and the grid only,
        so an evaluation that scores several configurations of one batch computes it once per
        image instead of preparing the full-size label for every configuration.
        """
        cells = _nearest_source(grid, tuple(target.shape[-2:]))
        target, valid = self._scored(target)
        k, n_cells = self.num_classes, grid[0] * grid[1]
        counts = torch.bincount(cells[valid] * k + target[valid], minlength=n_cells * k)
        return counts.reshape(n_cells, k).int()

    def update_grid(self, pred: Tensor, blocks: Tensor) -> None:
        """Add a prediction at the grid (``[h, w]``, :func:`predict_grid`) against a label's
        :meth:`blocks`: the same confusion as ``update(predict(...), target)``, whose
        upsampled prediction gives every pixel its cell's class."""
        pred = pred.detach().reshape(-1).long().cpu()
        if pred.numel() != blocks.shape[0]:
            raise ValueError(f"pred has {pred.numel()} cells, blocks {blocks.shape[0]}")
        self._check_pred(pred)
        k = self.num_classes
        by_pred = torch.zeros(k, k, dtype=blocks.dtype).index_add_(0, pred, blocks)
        self.confusion += by_pred.T  # rows: ground truth, columns: prediction

    def compute(self) -> dict[str, float | list[float]]:
        cm = self.confusion.double()
        tp = cm.diag()
        gt = cm.sum(1)
        union = gt + cm.sum(0) - tp
        present = union > 0
        iou = torch.where(present, tp / union.clamp_min(1), torch.full_like(tp, float("nan")))
        total = gt.sum()
        miou = iou[present].mean().item() if bool(present.any()) else float("nan")
        fmiou = (gt[present] / total * iou[present]).sum().item() if total > 0 else float("nan")
        acc = (tp.sum() / total).item() if total > 0 else float("nan")
        return {"miou": miou, "fmiou": fmiou, "acc": acc, "iou": iou.tolist()}  # SCORE_SPECS
