"""One image, a few labels, a segmentation: :func:`segment` and its figures (``resireg-segment``).

The prediction is the evaluation protocol's (:mod:`resireg.ovss`, docs/method.md#2d-evaluation-ovss):
one text prototype per label from the 80 ImageNet templates (:func:`~resireg.ovss.text_prototypes`),
cosine similarity with the dense features (:func:`~resireg.ovss.class_similarity`), softmax
with temperature 100 and argmax, brought to the image's size by nearest upsampling
(:func:`~resireg.ovss.predict`). Any encoder of the zoo works: a
:class:`~resireg.models.DenseEncoder`, an export folder or Hub repo id of our VLM, or
``build_encoder`` keywords.

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
from resireg.errors import arguments_under
from resireg.models.images import pil_to_tensor
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
    """A segmentation of one image, everything at the image's size ``(H, W)``.

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


def _image_tensor(image: Any) -> torch.Tensor:
    """uint8 RGB ``[3, H, W]`` of a path, PIL image, ``[H, W, 3]`` / ``[H, W]`` array or tensor."""
    if isinstance(image, (str, os.PathLike)):
        with Image.open(image) as im:
            return pil_to_tensor(im)
    if isinstance(image, Image.Image):
        return pil_to_tensor(image)
    if isinstance(image, np.ndarray):
        arr = image if image.ndim == 3 else np.repeat(image[..., None], 3, axis=2)
        if arr.ndim != 3 or arr.shape[2] != 3:
            raise ValueError(f"image: expected an [H, W, 3] array, got shape {image.shape}")
        if arr.dtype != np.uint8:
            arr = np.clip(np.rint(arr * 255.0 if arr.max() <= 1.0 else arr), 0, 255).astype(
                np.uint8
            )
        return torch.from_numpy(np.ascontiguousarray(arr)).permute(2, 0, 1).contiguous()
    if isinstance(image, torch.Tensor) and image.ndim == 3 and image.shape[0] == 3:
        return image
    raise TypeError(
        f"image: expected a path, PIL image, array or [3, H, W] tensor; got {type(image).__name__}"
    )


@torch.no_grad()
def segment(
    image: Any,
    labels: str | Sequence[str],
    encoder: Any,
    variant: str = "lite",
    *,
    short_side: int | None = None,
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
        temperature: the softmax temperature of the scores (the protocol's 100).
        templates: prompt templates per label (the 80 ImageNet ones).
    """
    names = parse_labels(labels)
    model = load_encoder(encoder, device)
    pixels = _image_tensor(image)
    size = tuple(pixels.shape[-2:])
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

    photo = _image_tensor(image).permute(1, 2, 0).numpy().astype(np.float32) / 255.0
    h, w = result.size
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
