"""The OVSS field's prediction path (docs/protocol.md section 6): sliding windows, logits
resized bilinearly to the label, class names as synonyms, the background threshold.

- :func:`window_boxes`: the windows of mmsegmentation's ``EncoderDecoder.slide_inference`` (and
  SCLIP's / NACLIP's ``forward_slide``): ``ceil((side - crop) / stride) + 1`` positions per axis,
  each ``stride`` apart, the last one moved back to end at the border, a window the image is
  smaller than cut to the image.
- :func:`crop_windows`: the windows' pixels, padded at the bottom / right to whole patches when a
  window is not a multiple of the patch size (only when the image is smaller than the window;
  the padding's logits are cut off again, as ProxyCLIP's and SCLIP's later ``forward_slide``).
- :func:`window_logits`: a window's class logits (cosine of each name's prototype) resized
  bilinearly from the feature grid to the window (``align_corners=False``), as the peers'
  ``forward_feature``.
- :func:`stitch`: the windows' logits added where they lie and divided by how many windows
  cover each pixel (``preds / count_mat``).
- :func:`to_label`: logits resized bilinearly to the label's resolution (mmseg's ``resize``
  to ``ori_shape``).
- :func:`classify`: softmax over every name at the protocol's scale, each class's best name,
  the argmax, and class 0 where the highest probability is below the threshold (the peers'
  ``postprocess_result``).
"""

from __future__ import annotations

from collections.abc import Iterable, Sequence

import torch
import torch.nn.functional as F
from torch import Tensor

from resireg.ovss import class_similarity

__all__ = [
    "Box", "classify", "crop_windows", "stitch", "to_label", "window_boxes", "window_logits",
    "window_shape",
]  # fmt: skip

#: A window ``(y1, y2, x1, x2)`` in pixels of the resized image (end exclusive).
Box = tuple[int, int, int, int]


def window_boxes(height: int, width: int, crop: int, stride: int) -> list[Box]:
    """The sliding windows of an image of ``height x width``, row-major (mmseg's order)."""
    if crop < 1 or stride < 1:
        raise ValueError(f"crop={crop}, stride={stride}: expected positive integers")
    rows = max(height - crop + stride - 1, 0) // stride + 1
    cols = max(width - crop + stride - 1, 0) // stride + 1
    boxes = []
    for r in range(rows):
        for c in range(cols):
            y2, x2 = min(r * stride + crop, height), min(c * stride + crop, width)
            boxes.append((max(y2 - crop, 0), y2, max(x2 - crop, 0), x2))
    return boxes


def window_shape(height: int, width: int, crop: int, multiple: int) -> tuple[int, int]:
    """The encoder's input of one window of an image of ``height x width``: the window's side
    (``crop``, or the image's side where it is smaller) rounded up to ``multiple``."""
    up = lambda n: -(-n // multiple) * multiple  # noqa: E731
    return up(min(crop, height)), up(min(crop, width))


def crop_windows(images: Tensor, boxes: Sequence[Box], crop: int, multiple: int = 1) -> Tensor:
    """``[B, C, H, W]`` -> ``[B * len(boxes), C, h, w]`` (image-major): every window of every
    image, zero-padded at the bottom / right to a multiple of ``multiple`` (the encoder's patch
    size; ``(h, w)`` is :func:`window_shape`)."""
    h, w = window_shape(images.shape[-2], images.shape[-1], crop, multiple)
    crops = []
    for image in images:
        for y1, y2, x1, x2 in boxes:
            crop = image[:, y1:y2, x1:x2]
            crops.append(F.pad(crop, (0, w - crop.shape[-1], 0, h - crop.shape[-2])))
    return torch.stack(crops)


def window_logits(dense: Tensor, prototypes: Tensor, size: tuple[int, int]) -> Tensor:
    """Class logits ``[B, Q, *size]`` (float32): the cosine of dense features ``[B, D, h, w]``
    with the names' prototypes ``[Q, D]`` (:func:`resireg.ovss.class_similarity`), resized
    bilinearly from the feature grid to ``size`` (the window or the whole input)."""
    logits = class_similarity(dense, prototypes)
    if tuple(logits.shape[-2:]) == tuple(size):
        return logits
    return F.interpolate(logits, size=tuple(size), mode="bilinear", align_corners=False)


def stitch(windows: Iterable[Tensor], boxes: Sequence[Box], size: tuple[int, int]) -> Tensor:
    """The windows' logits (each ``[Q, h, w]`` at least its box's size; a padded window's extra
    rows and columns are cut) placed in an image of ``size`` ``(H, W)``, summed, divided by the
    number of windows over each pixel: ``[Q, H, W]``. Every pixel must be covered. ``windows``
    may be a generator: one window's logits are held at a time (COCO-Stuff's 171 classes at
    224 x 224 are 34 MB a window)."""
    out = count = None
    for logits, (y1, y2, x1, x2) in zip(windows, boxes, strict=True):
        if out is None:
            out = logits.new_zeros((logits.shape[0], *size))
            count = logits.new_zeros((1, *size))
        out[:, y1:y2, x1:x2] += logits[:, : y2 - y1, : x2 - x1]
        count[:, y1:y2, x1:x2] += 1
    if out is None or bool((count == 0).any()):
        raise ValueError(f"the windows {list(boxes)} leave pixels of {size} uncovered")
    return out / count


def to_label(logits: Tensor, size: tuple[int, int]) -> Tensor:
    """``[Q, h, w]`` logits resized bilinearly (``align_corners=False``) to the label's ``size``."""
    if tuple(logits.shape[-2:]) == tuple(size):
        return logits
    return F.interpolate(logits[None], size=tuple(size), mode="bilinear", align_corners=False)[0]


def classify(
    logits: Tensor,
    name_class: Tensor,
    threshold: float | None = None,
    scale: float | None = None,
) -> Tensor:
    """Labels ``[..., H, W]`` (int64) from name logits ``[..., Q, H, W]`` (``Q`` names,
    ``name_class[q]`` the class of name ``q``, class-major): each class's score is its
    best-scoring name's, the label its best class; with ``threshold``, a pixel whose highest
    probability ``softmax(scale * logits)`` over all ``Q`` names is below it is labelled 0
    (background). Equal to the peers' rule (softmax over names, max per class, argmax, then the
    threshold) because the softmax keeps the order of a pixel's names, and a class's best name's
    probability is the class's."""
    dim = logits.ndim - 3
    value, best = logits.max(dim=dim)
    labels = name_class.to(best.device)[best]
    if threshold is not None:
        if scale is None:
            raise ValueError("a background threshold needs the scale of its softmax")
        # the highest softmax probability, exp(s * max - logsumexp(s * logits)), without
        # materialising the softmax (Q x H x W at the label's resolution)
        scaled = float(scale) * logits.float()
        top = torch.exp(float(scale) * value.float() - torch.logsumexp(scaled, dim=dim))
        labels = torch.where(top < threshold, torch.zeros_like(labels), labels)
    return labels
