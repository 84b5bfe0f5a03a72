"""Posed RGB-D frames of one ScanNet scene folder, as ScanNet's ``SensReader`` exports it, for
``resireg-map`` (docs/maps.md#robot-maps-semanticmap); and the file readers the ScanNet *evaluation*
dataset (``resireg_train.data.scannet``) shares with it. Layout (no labels needed)::

    <path>/color/<i>.jpg                    RGB
    <path>/depth/<i>.png                    uint16 millimetres (0 = no depth)
    <path>/pose/<i>.txt                     4 x 4 camera-to-world (OpenCV camera axes)
    <path>/intrinsic/intrinsic_depth.txt    4 x 4, top-left 3 x 3 = K of the depth image

Frames in index order; colour is resized to the depth image's size (bilinear, antialiased:
ScanNet's colour and depth share the field of view, about 58 degrees horizontally). A frame
whose colour or depth file is missing or undecodable is skipped as ``undecodable``, one whose
pose file is unreadable as ``no_pose``, each naming the file; the ``-inf`` pose ScanNet writes
where tracking was lost is passed on (:func:`~resireg.sources.frames.windows` drops it as
``no_pose``).
"""

from __future__ import annotations

import re
from collections.abc import Callable, Iterator
from pathlib import Path
from typing import Any

import numpy as np
from PIL import Image

from resireg.errors import DataError
from resireg.sources.frames import DECODE_ERRORS, RGBDFrame, SkippedFrame, SourceNotFoundError

__all__ = [
    "FrameFileError",
    "ScanNetSource",
    "read_image",
    "read_matrix",
    "resize_rgb",
    "scannet_rgbd",
]


def read_matrix(path: Path, shape: tuple[int, int]) -> np.ndarray:
    """The float64 matrix of a whitespace-separated text file (``pose/<i>.txt``,
    ``intrinsic_depth.txt``); ``ValueError`` unless it is of ``shape``."""
    m = np.loadtxt(path, dtype=np.float64, ndmin=2)
    if m.shape != shape:
        raise ValueError(f"{path}: expected a {shape[0]} x {shape[1]} matrix, got {m.shape}")
    return m


class FrameFileError(DataError):
    """A frame file that could not be read: the file and why (a skipped frame or sample)."""

    def __init__(self, path: Path, reason: str) -> None:
        super().__init__(f"{path}: {reason}")
        self.path, self.reason = path, reason


def read_image(path: Path, what: str, decode: Callable[[Image.Image], Any] = np.asarray) -> Any:
    """``decode`` of the image at ``path`` (its pixels as an array by default); a missing or
    undecodable file is a :class:`FrameFileError` naming that file (PIL decodes lazily: a
    truncated PNG fails in ``np.asarray``, after ``Image.open`` succeeded)."""
    try:
        with Image.open(path) as im:
            return decode(im)
    except FileNotFoundError:
        raise FrameFileError(path, f"missing {what} file") from None
    except (*DECODE_ERRORS, RuntimeError) as err:
        raise FrameFileError(path, f"unreadable {what}: {err}") from None


def resize_rgb(image: Any, size: tuple[int, int]) -> Any:
    """uint8 RGB tensor ``[3, H, W]`` -> float ``[3, *size]`` in [0, 1] (bilinear,
    antialiased)."""
    import torch

    x = image.float() / 255.0
    if tuple(x.shape[-2:]) == tuple(size):
        return x
    return torch.nn.functional.interpolate(
        x[None], size=tuple(size), mode="bilinear", align_corners=False, antialias=True
    )[0].clamp_(0, 1)


class ScanNetSource:
    """The frames of one ScanNet scene export folder (module docstring); a
    :class:`~resireg.sources.frames.FrameSource`. The folder is checked when it is made.

    Args:
        path: the scene folder (``color/``, ``depth/``, ``pose/``, ``intrinsic/``).
    """

    def __init__(self, path: str | Path) -> None:
        self.root = Path(path).expanduser()
        for sub in ("color", "depth", "pose"):
            if not (self.root / sub).is_dir():
                raise SourceNotFoundError(
                    f"path={str(path)!r}: no {sub}/ folder (a ScanNet scene export: color/, "
                    "depth/, pose/, intrinsic/)"
                )
        k_path = self.root / "intrinsic" / "intrinsic_depth.txt"
        if not k_path.is_file():
            raise SourceNotFoundError(f"path={str(path)!r}: no intrinsic/intrinsic_depth.txt")
        self.intrinsics = read_matrix(k_path, (4, 4))[:3, :3]
        self.unpaired_colour = 0  # colour and depth come in pairs

    def __iter__(self) -> Iterator[RGBDFrame | SkippedFrame]:
        import torch

        from resireg.models.images import pil_to_tensor

        folder = self.root
        stems = {int(p.stem): p.stem for p in (folder / "color").glob("*.jpg")
                 if re.fullmatch(r"\d+", p.stem)}  # fmt: skip
        for i in sorted(stems):
            stem = stems[i]
            try:
                pose = read_matrix(folder / "pose" / f"{stem}.txt", (4, 4))
            except (OSError, ValueError) as err:
                yield SkippedFrame(str(folder / "pose" / f"{stem}.txt"),
                                   f"unreadable pose: {err}", "no_pose")  # fmt: skip
                continue
            try:
                colour = read_image(folder / "color" / f"{stem}.jpg", "colour", pil_to_tensor)
                depth = read_image(folder / "depth" / f"{stem}.png", "depth").astype(np.float32)
            except FrameFileError as err:
                yield SkippedFrame(str(err.path), err.reason, "undecodable")
                continue
            if depth.ndim != 2:
                yield SkippedFrame(str(folder / "depth" / f"{stem}.png"),
                                   f"depth has shape {depth.shape}: expected one channel",
                                   "undecodable")  # fmt: skip
                continue
            rgb = resize_rgb(colour, depth.shape)
            image = (rgb * 255).round().to(torch.uint8).permute(1, 2, 0).numpy()
            yield RGBDFrame(image, depth / 1000.0, self.intrinsics, pose, float(i),
                            str(folder / "color" / f"{stem}.jpg"))  # fmt: skip


def scannet_rgbd(folder: str | Path) -> Iterator[RGBDFrame | SkippedFrame]:
    """The records of :class:`ScanNetSource` ``(folder)`` (the folder checked now)."""
    return iter(ScanNetSource(folder))
