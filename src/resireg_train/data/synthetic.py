"""Procedural scenes with captions and matching segmentation masks (tests, smoke runs).

Each scene is a background class with one to three foreground shapes (rectangles or
ellipses) of other classes. Every class has its own colour and texture (stripe period
and orientation), so a small model can learn the image-text correspondence; the caption
names the classes present, and the mask holds each pixel's class index. Scene ``i`` of a
given ``seed`` is always the same, so map-style access needs no storage.
"""

from __future__ import annotations

from collections.abc import Iterator

import numpy as np
from PIL import Image

__all__ = ["SYNTHETIC_CLASSES", "SyntheticScenes", "paint"]

#: Classes of the synthetic world (label ids in this order).
SYNTHETIC_CLASSES: tuple[str, ...] = (
    "sky",
    "grass",
    "road",
    "water",
    "car",
    "person",
    "tree",
    "building",
)

_COLOURS = np.array(
    [
        [110, 170, 240],
        [60, 170, 60],
        [90, 90, 90],
        [30, 80, 200],
        [220, 30, 30],
        [240, 200, 150],
        [20, 110, 30],
        [170, 120, 80],
    ],
    dtype=np.float32,
)
_BACKGROUNDS = (0, 1, 2, 3, 7)  # classes that can fill a scene
_TEMPLATES = ("a photo of {}.", "a picture showing {}.", "{} in a scene.", "an image of {}.")


def paint(mask: np.ndarray, rng: np.random.Generator, noise: float) -> np.ndarray:
    """The pixels of a class map ``mask`` ``[H, W]`` (class ids): each class's colour and
    texture (stripes whose period and direction depend on the class, in image coordinates),
    plus Gaussian noise of std ``noise`` drawn from ``rng``; uint8 RGB ``[H, W, 3]``. The 3D
    synthetic room paints its boxes with it too (``resireg_train.data.scannet_room``)."""
    yy, xx = np.mgrid[0 : mask.shape[0], 0 : mask.shape[1]]
    image = _COLOURS[mask].copy()
    period = 4.0 + 2.0 * mask
    phase = np.where(mask % 2 == 0, yy, xx) / period
    image += 25.0 * np.sin(2 * np.pi * phase)[..., None]
    image += rng.normal(0.0, noise, size=image.shape)
    return np.clip(image, 0, 255).astype(np.uint8)


class SyntheticScenes:
    """A deterministic, indexable set of synthetic scenes.

    Args:
        size: number of scenes.
        image_size: ``(H, W)`` of every image.
        seed: base seed; scene ``i`` uses ``seed * 1_000_003 + i``.
        noise: standard deviation of per-pixel colour noise (0..255 scale).
    """

    classes = SYNTHETIC_CLASSES

    def __init__(
        self,
        size: int = 256,
        image_size: tuple[int, int] = (128, 128),
        seed: int = 0,
        noise: float = 12.0,
    ) -> None:
        if size < 1:
            raise ValueError(f"size must be >= 1, got {size}")
        self.size = size
        self.image_size = tuple(image_size)
        self.seed = seed
        self.noise = noise

    def __len__(self) -> int:
        return self.size

    def __iter__(self) -> Iterator[dict]:
        for i in range(self.size):
            yield self[i]

    def __getitem__(self, index: int) -> dict:
        """``{"image": PIL RGB, "caption": str, "mask": uint8 [H, W] class ids}``."""
        if not 0 <= index < self.size:
            raise IndexError(f"scene index {index} out of range for {self.size} scenes")
        rng = np.random.default_rng(self.seed * 1_000_003 + index)
        h, w = self.image_size
        background = int(rng.choice(_BACKGROUNDS))
        mask = np.full((h, w), background, dtype=np.uint8)
        others = [c for c in range(len(SYNTHETIC_CLASSES)) if c != background]
        yy, xx = np.mgrid[0:h, 0:w]
        for cls in rng.choice(others, size=int(rng.integers(1, 4)), replace=False):
            ch, cw = int(rng.integers(h // 4, h // 2 + 1)), int(rng.integers(w // 4, w // 2 + 1))
            y0, x0 = int(rng.integers(0, h - ch + 1)), int(rng.integers(0, w - cw + 1))
            if rng.random() < 0.5:
                shape = (yy >= y0) & (yy < y0 + ch) & (xx >= x0) & (xx < x0 + cw)
            else:
                cy, cx = y0 + ch / 2, x0 + cw / 2
                shape = ((yy - cy) / (ch / 2)) ** 2 + ((xx - cx) / (cw / 2)) ** 2 <= 1.0
            mask[shape] = cls
        image = paint(mask, rng, self.noise)
        present = [SYNTHETIC_CLASSES[c] for c in np.unique(mask)]
        rng.shuffle(present)
        names = ", ".join(present[:-1]) + f" and {present[-1]}" if len(present) > 1 else present[0]
        caption = str(rng.choice(_TEMPLATES)).format(names)
        return {
            "image": Image.fromarray(image),
            "caption": caption,
            "mask": mask,
        }
