"""Images -> patch-grid tensors: the resize rule every dense encoder's input follows.

The shorter side is scaled to ``short_side`` (aspect kept; ``None`` keeps the size), then
each side is rounded to a multiple of the patch size; bilinear with antialiasing. The
evaluation datasets resize in DataLoader workers with these same functions, so a model's
own preprocessing and the evaluation agree pixel for pixel (docs/method.md#the-dense-encoder-interface).
"""

from __future__ import annotations

import numpy as np
import torch
import torch.nn.functional as F
from PIL import Image
from torch import Tensor

__all__ = [
    "WIDE_GREY",
    "pil_to_tensor",
    "patch_grid_size",
    "resize_to_patch_grid",
    "resize_square",
    "tokens_to_grid",
]


#: PIL modes of 16-bit (and 32-bit integer) single-channel images, e.g. 16-bit PNGs.
WIDE_GREY = ("I;16", "I;16L", "I;16B", "I;16N", "I")


def pil_to_tensor(image: Image.Image) -> Tensor:
    """A PIL image -> uint8 RGB ``[3, H, W]``.

    16-bit grey images are scaled (``v / 257``, so 65535 -> 255): PIL's ``convert("RGB")``
    clips them at 255 instead, turning almost every pixel white. Mode ``I`` (32-bit int)
    is read as 16-bit, what PNG decoders give it.
    """
    if image.mode in WIDE_GREY:
        wide = np.asarray(image).astype(np.float64)
        grey = np.clip(np.rint(wide / 257.0), 0, 255).astype(np.uint8)
        return torch.from_numpy(grey).expand(3, *grey.shape).contiguous()
    array = np.asarray(image.convert("RGB"), dtype=np.uint8).copy()
    return torch.from_numpy(array).permute(2, 0, 1)


def patch_grid_size(
    size: tuple[int, int], short_side: int | None, patch_size: int
) -> tuple[int, int]:
    """``(H, W)`` after :func:`resize_to_patch_grid` (no pixels needed)."""
    h, w = size
    scale = short_side / min(h, w) if short_side else 1.0
    p = patch_size
    return (max(p, round(h * scale / p) * p), max(p, round(w * scale / p) * p))


def resize_to_patch_grid(image: Tensor, short_side: int | None, patch_size: int) -> Tensor:
    """An RGB image ``[3, H, W]`` (uint8, or float in [0, 1]) -> float ``[3, h, w]`` in [0, 1]."""
    if image.ndim != 3 or image.shape[0] != 3:
        raise ValueError(f"images must be RGB [3, H, W], got shape {tuple(image.shape)}")
    image = image.float() / 255.0 if not image.is_floating_point() else image.float()
    size = patch_grid_size(tuple(image.shape[-2:]), short_side, patch_size)
    if size == tuple(image.shape[-2:]):
        return image
    return F.interpolate(
        image[None], size=size, mode="bilinear", align_corners=False, antialias=True
    )[0]


def resize_square(images: Tensor, size: int | None) -> Tensor:
    """A normalised batch ``[B, 3, H, W]`` -> ``[B, 3, size, size]`` (bilinear), the input of an
    encoder with a fixed square resolution (dino.txt's 518, TIPSv2's 574); ``None`` keeps it."""
    if size is None:
        return images
    return F.interpolate(images, size=(size, size), mode="bilinear", align_corners=False)


def tokens_to_grid(tokens: Tensor, size: tuple[int, int], grid: tuple[int, int]) -> Tensor:
    """Patch tokens ``[B, N, D]`` of a ``size`` patch grid (row-major) -> float ``[B, D, *grid]``,
    bilinearly resized when ``grid`` differs: how an encoder with a fixed native input brings
    its dense maps to the evaluation canvas's grid."""
    b, _, d = tokens.shape
    x = tokens.float().transpose(1, 2).reshape(b, d, *size)
    if tuple(size) != tuple(grid):
        x = F.interpolate(x, size=tuple(grid), mode="bilinear", align_corners=False)
    return x
