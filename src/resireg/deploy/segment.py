"""One image, a few labels, a segmentation: :func:`segment` and its figures (``resireg-segment``).

The prediction is the evaluation protocol's (:mod:`resireg.ovss`, docs/method.md#2d-evaluation-ovss):
one text prototype per label from the 80 ImageNet templates (:func:`~resireg.ovss.text_prototypes`),
cosine similarity with the dense features (:func:`~resireg.ovss.class_similarity`), softmax
with temperature 100 and argmax, brought to the image's size by nearest upsampling
(:func:`~resireg.ovss.predict`). Any encoder of the zoo works: a
:class:`~resireg.models.DenseEncoder`, an export folder or Hub repo id of our VLM, or
``build_encoder`` keywords.

An image of more than ``max_pixels`` pixels (:data:`~resireg.deploy.photo.MAX_PIXELS` by
default, sized for the 25M VLM) is resized, its aspect kept, before it becomes the model's
input, and a file is decoded with its memory bounded (:mod:`resireg.deploy.photo`); the
segmentation is at that size.

The figures (overlay with a legend, similarity maps) need matplotlib (the ``export`` extra);
:func:`segment` itself needs the core only.
"""

from __future__ import annotations

import os
import re
from collections.abc import Callable, Mapping, Sequence
from dataclasses import dataclass
from pathlib import Path
from typing import Any

import numpy as np
import torch
import torch.nn.functional as F
from PIL import Image

from resireg.deploy.labels import parse_labels
from resireg.deploy.photo import (
    MAX_PIXELS,
    check_max_pixels,
    load_photo,
    reduce_photo,
    reduced_size,
)
from resireg.errors import arguments_under
from resireg.models.images import patch_grid_size, pil_to_tensor
from resireg.models.interface import DenseEncoder
from resireg.ovss import TEMPLATES, class_similarity, predict, text_prototypes

__all__ = [
    "SegmentationResult",
    "load_encoder",
    "overlay_figure",
    "parse_labels",
    "save_outputs",
    "segment",
]


@dataclass
class SegmentationResult:
    """A segmentation of one image, everything at the image's size ``(H, W)`` (after
    ``max_pixels``: see :func:`segment`).

    Attributes:
        labels: the ``K`` labels, in order (the label map's ids are their indices).
        label_map: ``[H, W]`` int64, the predicted label index of every pixel.
        scores: ``[K, H, W]`` float32, per-class probabilities (softmax of ``temperature``
            times the similarities; their argmax is ``label_map``).
        similarity: ``[K, H, W]`` float32, the cosine similarity of every pixel's feature
            with each label's text prototype.
        variant: the ReSiReg variant the features came from (``bb``, ``lite``, ``full``...).
    """

    labels: tuple[str, ...]
    label_map: np.ndarray
    scores: np.ndarray
    similarity: np.ndarray
    variant: str

    @property
    def size(self) -> tuple[int, int]:
        return tuple(self.label_map.shape)  # type: ignore[return-value]

    def shares(self) -> dict[str, float]:
        """The fraction of the image's pixels given to each label."""
        counts = np.bincount(self.label_map.ravel(), minlength=len(self.labels))
        return {
            name: float(c) / self.label_map.size
            for name, c in zip(self.labels, counts, strict=True)
        }


def load_encoder(encoder: Any, device: str | torch.device = "cpu") -> DenseEncoder:
    """A :class:`DenseEncoder` from ``encoder``: one itself, an export folder or Hugging Face
    repo id of our VLM (:meth:`ResiregVLM.from_pretrained`), or ``build_encoder`` keywords
    (``{"kind": "clip", "model_name": "ViT-B-16", ...}``, as ``conf/encoder/*.yaml`` give)."""
    if isinstance(encoder, DenseEncoder):
        return encoder
    from resireg.models.factory import build_encoder, encoder_arguments, load_resireg_vlm

    if isinstance(encoder, (str, os.PathLike)):
        with arguments_under("encoder", {"path": "encoder"}):  # our argument is the path
            return load_resireg_vlm(os.fspath(encoder), device).eval()
    if isinstance(encoder, Mapping):
        keys = dict(encoder)
        with arguments_under("encoder", (*keys, *encoder_arguments(keys.get("kind")))):
            return build_encoder(**keys, device=device).eval()
    raise TypeError(
        "encoder must be a DenseEncoder, an export folder / Hub repo id, or build_encoder "
        f"keywords; got {type(encoder).__name__}"
    )


def _image_tensor(image: Any, max_pixels: int | None = None) -> torch.Tensor:
    """uint8 RGB ``[3, H, W]`` of a path, PIL image, ``[H, W, 3]`` / ``[H, W]`` array or tensor,
    with at most ``max_pixels`` pixels (a file or PIL image reduced by PIL before it becomes a
    tensor: :func:`~resireg.deploy.photo.load_photo`; an array or tensor by
    :func:`_fit`)."""
    if isinstance(image, (str, os.PathLike)):
        return pil_to_tensor(load_photo(image, max_pixels))
    if isinstance(image, Image.Image):
        return pil_to_tensor(reduce_photo(image, max_pixels))
    if isinstance(image, np.ndarray):
        arr = image if image.ndim == 3 else np.repeat(image[..., None], 3, axis=2)
        if arr.ndim != 3 or arr.shape[2] != 3:
            raise ValueError(f"image: expected an [H, W, 3] array, got shape {image.shape}")
        if arr.dtype != np.uint8:
            arr = np.clip(np.rint(arr * 255.0 if arr.max() <= 1.0 else arr), 0, 255).astype(
                np.uint8
            )
        pixels = torch.from_numpy(np.ascontiguousarray(arr)).permute(2, 0, 1).contiguous()
    elif isinstance(image, torch.Tensor) and image.ndim == 3 and image.shape[0] == 3:
        pixels = image
    else:
        raise TypeError(
            "image: expected a path, PIL image, array or [3, H, W] tensor; got "
            f"{type(image).__name__}"
        )
    return _fit(pixels, reduced_size(tuple(pixels.shape[-2:]), max_pixels))


def _fit(pixels: torch.Tensor, size: tuple[int, int]) -> torch.Tensor:
    """``[3, H, W]`` pixels at ``size`` (bilinear, antialiased: the encoders' resize rule,
    :func:`resireg.models.images.resize_to_patch_grid`), uint8 kept uint8; unchanged at it."""
    if tuple(pixels.shape[-2:]) == tuple(size):
        return pixels
    x = pixels.float()[None]
    x = F.interpolate(x, size=size, mode="bilinear", align_corners=False, antialias=True)[0]
    if pixels.dtype == torch.uint8:
        return x.round_().clamp_(0, 255).to(torch.uint8)
    return x.to(pixels.dtype)


@torch.no_grad()
def segment(
    image: Any,
    labels: str | Sequence[str],
    encoder: Any,
    variant: str = "lite",
    *,
    short_side: int | None = None,
    max_pixels: int | None = MAX_PIXELS,
    temperature: float = 100.0,
    templates: Sequence[Callable[[str], str]] = TEMPLATES,
    device: str | torch.device = "cpu",
    **variant_kwargs: Any,
) -> SegmentationResult:
    """Segment ``image`` into ``labels`` with ``encoder`` and a ReSiReg ``variant``.

    Args:
        image: a path, PIL image, ``[H, W, 3]`` array or uint8 ``[3, H, W]`` tensor.
        labels: class names (a list, or one string separated by commas).
        encoder: see :func:`load_encoder`.
        variant: ``bb`` (the language tokens), ``lite``, ``full`` or ``calib``
            (:func:`resireg.method.variants.build_variant`); ``variant_kwargs`` are its parameters.
        short_side: the model input's shorter side (default: the image's own, rounded to the
            patch size); the results are at the image's size all the same.
        max_pixels: the most pixels of the image: a larger one is resized (aspect kept) to at
            most that many before it becomes the model's input, and the results are at that
            size (a file is decoded with bounded memory:
            :func:`~resireg.deploy.photo.load_photo`). ``short_side`` may not make a model
            input of more (a ``ValueError`` says so). ``None``: no limit.
        temperature: the softmax temperature of the scores (the protocol's 100).
        templates: prompt templates per label (the 80 ImageNet ones).
    """
    names = parse_labels(labels)
    max_pixels = check_max_pixels(max_pixels)
    pixels = _image_tensor(image, max_pixels)  # before the model: a bad image fails at once
    size = tuple(pixels.shape[-2:])
    model = load_encoder(encoder, device)
    if short_side is not None and max_pixels is not None:
        h, w = patch_grid_size(size, short_side, model.input_rule.patch_size)
        if h * w > max_pixels:
            raise ValueError(
                f"short_side={short_side}: makes a {h} x {w} model input ({h * w:,} pixels) of "
                f"the {size[0]} x {size[1]} image, more than max_pixels={max_pixels:,} (a smaller "
                "shorter side, or a larger limit)"
            )
    dense = model.encode_image(pixels, variant, short_side=short_side, **variant_kwargs)
    prototypes = text_prototypes(model.encode_text, names, templates)
    label_map = predict(dense, prototypes, size, temperature)[0]
    similarity = F.interpolate(class_similarity(dense, prototypes), size=size, mode="nearest")[0]
    scores = torch.softmax(temperature * similarity, dim=0)
    return SegmentationResult(
        labels=names,
        label_map=label_map.cpu().numpy(),
        scores=scores.cpu().numpy(),
        similarity=similarity.cpu().numpy(),
        variant=variant,
    )


def _colours(k: int) -> np.ndarray:
    """``[K, 3]`` float RGB in [0, 1]: matplotlib's tab10/tab20, or evenly spaced hues beyond."""
    from matplotlib import colormaps

    if k <= 10:
        return np.asarray(colormaps["tab10"].colors[:k])
    if k <= 20:
        return np.asarray(colormaps["tab20"].colors[:k])
    return colormaps["hsv"](np.linspace(0, 1, k, endpoint=False))[:, :3]


def overlay_figure(image: Any, result: SegmentationResult, alpha: float = 0.5, dpi: int = 100):
    """A matplotlib ``Figure`` of exactly the image's size: the photo blended with the label
    colours (``alpha``) and a legend naming each label with its share of the pixels."""
    from matplotlib.figure import Figure
    from matplotlib.patches import Patch

    h, w = result.size
    # the photo as segmented: the caller's photo, reduced by max_pixels as segment reduced it
    # (read with at most 4 x the segmentation's pixels, so a large file stays cheap)
    pixels = _image_tensor(image, 4 * h * w)
    ph, pw = pixels.shape[-2:]
    if (ph, pw) != (h, w) and ph >= h and pw >= w and abs(ph * w - pw * h) <= 2 * (ph + pw):
        pixels = _fit(pixels, (h, w))  # the same aspect, up to the limit's rounding
    photo = pixels.permute(1, 2, 0).numpy().astype(np.float32) / 255.0
    if photo.shape[:2] != (h, w):
        raise ValueError(f"image size {photo.shape[:2]} is not the segmentation's {(h, w)}")
    colours = _colours(len(result.labels))
    blended = (1 - alpha) * photo + alpha * colours[result.label_map]
    fig = Figure(figsize=(w / dpi, h / dpi), dpi=dpi)
    ax = fig.add_axes((0, 0, 1, 1))
    ax.imshow(np.clip(blended, 0, 1), interpolation="nearest")
    ax.set_axis_off()
    shares = result.shares()
    handles = [Patch(color=colours[i], label=f"{name} ({100 * shares[name]:.0f}%)")
               for i, name in enumerate(result.labels)]  # fmt: skip
    ax.legend(handles=handles, loc="upper right", fontsize=max(6, min(12, h // 40)), framealpha=0.8)
    return fig


def _slug(text: str) -> str:
    return re.sub(r"[^A-Za-z0-9]+", "-", text).strip("-").lower() or "label"


def save_outputs(image: Any, result: SegmentationResult, out: str | os.PathLike) -> dict[str, Any]:
    """Write ``out`` (the label map: a palette PNG whose pixel values are the label indices),
    ``<stem>.overlay.png`` (:func:`overlay_figure`) and ``<stem>.similarity.<i>-<label>.png``
    (each label's cosine similarity, viridis, scaled to the map's own range). Returns
    ``{"label_map", "overlay", "similarity": [...]}`` paths."""
    from matplotlib import colormaps

    out = Path(out)
    out.parent.mkdir(parents=True, exist_ok=True)
    stem = out.with_suffix("")
    label_png = Image.fromarray(result.label_map.astype(np.uint8), mode="P")
    palette = (np.round(_colours(len(result.labels)) * 255).astype(np.uint8)).ravel().tolist()
    label_png.putpalette(palette + [0] * (768 - len(palette)))
    label_png.save(out)
    overlay = Path(f"{stem}.overlay.png")
    overlay_figure(image, result).savefig(overlay, dpi=100)
    maps = []
    viridis = colormaps["viridis"]
    for i, (name, sim) in enumerate(zip(result.labels, result.similarity, strict=True)):
        lo, hi = float(sim.min()), float(sim.max())
        rgb = viridis((sim - lo) / max(hi - lo, 1e-12))[..., :3]
        path = Path(f"{stem}.similarity.{i}-{_slug(name)}.png")
        Image.fromarray(np.round(rgb * 255).astype(np.uint8)).save(path)
        maps.append(path)
    return {"label_map": out, "overlay": overlay, "similarity": maps}
