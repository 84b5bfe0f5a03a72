"""The photo of a segmentation, read without torch (so ``resireg-segment`` reports a bad file
before the models load) and with its memory bounded: :func:`load_photo`, :func:`reduced_size`.

Two limits, one for each cost:

- **decoding**: a file whose declared size exceeds PIL's decompression-bomb limit
  (``PIL.Image.MAX_IMAGE_PIXELS``, 89,478,485 pixels unless changed; PIL refuses files of twice
  that itself, and only warns below) is refused from its header, before a pixel is decoded. A
  JPEG is decoded at the smallest of its 1/2, 1/4, 1/8 scales that still holds the size wanted
  (``Image.draft``), so a large photo never exists in memory at full size; other formats are
  decoded whole (at most ``MAX_IMAGE_PIXELS`` pixels) and reduced at once.
- **the model**: an image of more than ``max_pixels`` pixels (:data:`MAX_PIXELS` by default) is
  resized, its aspect kept, to at most that many (:func:`reduced_size`) before it becomes a
  tensor; the segmentation, its scores and its figures are at that size.
"""

from __future__ import annotations

import math
import os
import warnings

from PIL import Image

from resireg.sources.frames import DECODE_ERRORS

__all__ = ["MAX_PIXELS", "load_photo", "reduce_photo", "reduced_size"]

#: The most pixels an image hands the 25M VLM unless told otherwise: 1024 x 1024, i.e. 4096
#: patches of its 16-pixel grid (the protocol's 576 x 768 inputs are 1728; a 16:9 photo at the
#: protocol's shorter side 576 is 576 x 1024, 2304); with it resireg-segment peaks near 1.2 GiB
#: on the CPU whatever the image's size (docs/benchmarks.md, benchmarks/bench_segment.py).
MAX_PIXELS = 1024 * 1024

#: PIL modes of 16-bit (and 32-bit integer) grey images, resized as 32-bit integers (``I``)
#: so :func:`resireg.models.images.pil_to_tensor` scales them as it does unresized ones.
_WIDE_GREY = ("I;16", "I;16L", "I;16B", "I;16N", "I")


def reduced_size(size: tuple[int, int], max_pixels: int | None) -> tuple[int, int]:
    """``(H, W)`` of an image of ``size`` ``(H, W)`` brought to at most ``max_pixels`` pixels
    (each side scaled by the same factor, rounded down); ``size`` itself when it has no more
    (or ``max_pixels`` is ``None``)."""
    h, w = size
    if max_pixels is None or h * w <= max_pixels:
        return h, w
    scale = math.sqrt(max_pixels / (h * w))
    nh, nw = max(1, math.floor(h * scale)), max(1, math.floor(w * scale))
    while nh * nw > max_pixels:  # a side of 1 (a 1 x N strip) keeps the other at the limit
        nh, nw = (nh - 1, nw) if nh >= nw and nh > 1 else (nh, nw - 1)
    return nh, nw


def check_max_pixels(max_pixels: object, name: str = "max_pixels") -> int | None:
    """``max_pixels`` itself when it is ``None`` or an integer >= 1; else a ``ValueError``
    naming ``name``."""
    if max_pixels is None:
        return None
    if isinstance(max_pixels, bool) or not isinstance(max_pixels, int) or max_pixels < 1:
        raise ValueError(f"{name}={max_pixels!r}: expected a number of pixels >= 1")
    return max_pixels


def reduce_photo(image: Image.Image, max_pixels: int | None = MAX_PIXELS) -> Image.Image:
    """``image`` with at most ``max_pixels`` pixels (:func:`reduced_size`): PIL's resize with
    a bilinear filter widened to the scale (antialiased, as
    :func:`resireg.models.images.resize_to_patch_grid`) after an integer box reduction
    (``reducing_gap``, fast and light); the image itself when it is small enough. Palette and
    other modes become RGB first (a palette resizes by nearest neighbour only), 16-bit grey
    ``I``."""
    w, h = image.size
    nh, nw = reduced_size((h, w), check_max_pixels(max_pixels))
    if (nh, nw) == (h, w):
        return image
    if image.mode in _WIDE_GREY:
        image = image.convert("I") if image.mode != "I" else image
    elif image.mode not in ("RGB", "L"):
        image = image.convert("RGB")
    return image.resize((nw, nh), Image.Resampling.BILINEAR, reducing_gap=2.0)


def load_photo(path: str | os.PathLike, max_pixels: int | None = MAX_PIXELS) -> Image.Image:
    """The image file ``path``, decoded (a JPEG at a reduced scale where that suffices) and
    reduced to at most ``max_pixels`` pixels (:func:`reduce_photo`). A file that is not a
    readable image, or declares more pixels than ``PIL.Image.MAX_IMAGE_PIXELS``, is a
    ``ValueError`` naming it, raised before its pixels are decoded."""
    max_pixels = check_max_pixels(max_pixels)
    try:
        with warnings.catch_warnings():  # the limit is checked below, with the file's name
            warnings.simplefilter("ignore", Image.DecompressionBombWarning)
            with Image.open(path) as im:
                w, h = im.size
                limit = Image.MAX_IMAGE_PIXELS
                if limit is not None and w * h > limit:
                    raise Image.DecompressionBombError(
                        f"it declares {w} x {h} = {w * h:,} pixels, more than PIL's "
                        f"decompression-bomb limit of {limit:,} (PIL.Image.MAX_IMAGE_PIXELS)"
                    )
                nh, nw = reduced_size((h, w), max_pixels)
                im.draft("RGB", (nw, nh))  # JPEG: decode at 1/2, 1/4, 1/8 scale (others: no-op)
                im.load()
                if im.size != (w, h):  # decoded at a reduced scale
                    return _exact(im, nh, nw)
                out = reduce_photo(im, max_pixels)
                return out.copy() if out is im else out  # (im's file closes with the block)
    except Image.DecompressionBombError as err:
        raise ValueError(f"{os.fspath(path)}: refused ({err})") from err
    except DECODE_ERRORS as err:
        raise ValueError(f"{os.fspath(path)}: not a readable image ({err})") from err


def _exact(image: Image.Image, h: int, w: int) -> Image.Image:
    """A JPEG decoded at a reduced scale (``draft``: at least ``(w, h)``), brought to exactly
    :func:`reduced_size`'s size of the full image, so the result does not depend on draft."""
    image = image.convert("RGB") if image.mode != "RGB" else image
    return image if image.size == (w, h) else image.resize((w, h), Image.Resampling.BILINEAR)
