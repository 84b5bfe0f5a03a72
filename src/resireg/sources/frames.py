"""The frame record of a posed RGB-D source, what a source is, and the windows the map takes
(docs/maps.md#robot-maps-semanticmap).

A source (:class:`~resireg.sources.rosbag.BagSource`, :class:`~resireg.sources.tum.TumSource`,
:class:`~resireg.sources.scannet.ScanNetSource`,
:class:`~resireg.sources.nerfstudio.NerfstudioSource`, the live ROS 2 node) is a
:class:`FrameSource`: it yields, in time order, :class:`RGBDFrame` records or
:class:`SkippedFrame` records (a message or file that could not be decoded or paired, with the
reason and its kind); :class:`FrameCounts` tallies them and :func:`windows` groups consecutive
frames of one size into the ``[B, ...]`` tensors :meth:`resireg.mapping.SemanticMap.add` takes.
The timestamp pairing and pose interpolation shared by the sources are in
:mod:`resireg.sources.pairing`, the ROS message decoding in :mod:`resireg.sources.messages`.

This module imports numpy and PIL (torch when :func:`windows` runs): no Lightning, no Hydra.
"""

from __future__ import annotations

import math
from collections import Counter
from collections.abc import Iterable, Iterator, Mapping, Sequence
from dataclasses import dataclass, field
from typing import Protocol, runtime_checkable

import numpy as np
from PIL import Image

from resireg.errors import DataError

__all__ = [
    "DECODE_ERRORS",
    "FrameCounts",
    "FrameSource",
    "MessageSource",
    "RGBDFrame",
    "SkippedFrame",
    "SourceNotFoundError",
    "windows",
]

#: What PIL raises for an undecodable image file (skipped and counted, never fatal).
DECODE_ERRORS = (OSError, ValueError, SyntaxError, Image.DecompressionBombError)


class SourceNotFoundError(DataError, FileNotFoundError):
    """The recording a source is given is not there (no such folder or file, or a file its
    layout needs is missing); the message names the argument (``path='run.bag': ...``)."""


@dataclass
class RGBDFrame:
    """One posed RGB-D frame.

    Attributes:
        image: uint8 RGB ``[H, W, 3]``.
        depth: float32 ``[Hd, Wd]`` metres (0 = no depth); same field of view as ``image``.
        intrinsics: ``[3, 3]`` pinhole matrix of the depth image.
        pose: ``[4, 4]`` camera (OpenCV axes) to world.
        stamp: seconds (the depth image's time).
        name: where it came from (``topic@stamp`` or a file).
    """

    image: np.ndarray
    depth: np.ndarray
    intrinsics: np.ndarray
    pose: np.ndarray
    stamp: float
    name: str


@dataclass(frozen=True)
class SkippedFrame:
    """A candidate frame left out: what (``topic@stamp`` or a file: the message or file at
    fault) and why. Every record stands for one candidate frame (one depth image)."""

    name: str
    reason: str
    # undecodable | unpaired | no_pose | bad_stamp | size_mismatch | non_finite | frame_skip
    # | in_map (held by the map a resumed run continues)
    kind: str = "undecodable"


@dataclass
class FrameCounts:
    """``read`` candidate frames (depth images), ``used`` (fused), ``skipped`` by kind, the
    first skipped records (``examples``, at most 20) with their reasons, the first reason of
    each kind (``reasons``: a run that maps nothing says why per kind), and the depth pixels
    made invalid by ``max_depth`` (``depth_out_of_range`` pixels in ``depth_out_of_range_frames``
    frames)."""

    read: int = 0
    used: int = 0
    skipped: Counter = field(default_factory=Counter)
    examples: list[SkippedFrame] = field(default_factory=list)
    reasons: dict[str, str] = field(default_factory=dict)
    depth_out_of_range: int = 0
    depth_out_of_range_frames: int = 0

    def skip(self, record: SkippedFrame) -> None:
        self.skipped[record.kind] += 1
        self.reasons.setdefault(record.kind, f"{record.name}: {record.reason}")
        if len(self.examples) < 20:
            self.examples.append(record)

    def as_dict(self) -> dict:
        return {
            "read": self.read,
            "used": self.used,
            "skipped": dict(self.skipped),
            "reasons": dict(self.reasons),
            "depth_out_of_range": {
                "pixels": self.depth_out_of_range,
                "frames": self.depth_out_of_range_frames,
            },  # fmt: skip
            "skipped_examples": [
                {"name": s.name, "kind": s.kind, "reason": s.reason} for s in self.examples
            ],
        }

    def line(self) -> str:
        skipped = ", ".join(f"{n} {k}" for k, n in sorted(self.skipped.items())) or "none"
        return f"frames: {self.read} read, {self.used} used, skipped: {skipped}"


@runtime_checkable
class FrameSource(Protocol):
    """What ``resireg-map`` (and any caller of :func:`windows`) takes as a source: an iterable of
    :class:`RGBDFrame` and :class:`SkippedFrame` records in time order, one record per
    candidate frame (a skip counted and named), and ``unpaired_colour``, the colour images no
    depth image took (0 for a source of ready-made pairs). A source checks what it is given
    when it is made (a missing folder or topic fails there, before a model loads)."""

    unpaired_colour: int

    def __iter__(self) -> Iterator[RGBDFrame | SkippedFrame]: ...


@runtime_checkable
class MessageSource(FrameSource, Protocol):
    """A :class:`FrameSource` of timestamped messages (a bag, a live ROS 2 node), whose faults
    beyond the frames ``resireg-map`` records in ``results.json``: messages that could not be
    deserialised by topic (``corrupt``) with the first of them (``corrupt_examples``), colour
    images left out for their header stamps (``colour_stamp_faults``), and what stopped a
    damaged recording's read (``damage``, or ``None``)."""

    corrupt: Mapping[str, int]
    corrupt_examples: Sequence[str]
    colour_stamp_faults: Sequence[str]
    damage: str | None


def windows(
    frames: Iterable[RGBDFrame | SkippedFrame],
    size: int,
    counts: FrameCounts,
    frame_skip: int = 0,
    limit: int | None = None,
    start: int = 0,
    max_depth: float | None = None,
) -> Iterator[dict]:
    """Windows of up to ``size`` consecutive kept frames of one image and depth size, as tensors:
    ``image`` uint8 ``[B, 3, H, W]``, ``depth`` float32 ``[B, Hd, Wd]``, ``intrinsics``
    ``[B, 3, 3]``, ``pose`` float64 ``[B, 4, 4]``, ``stamp`` and ``name`` lists, ``first``
    (the position of the window's first frame among the kept frames).

    ``frame_skip = s`` keeps every ``(s + 1)``-th frame (ScanNet's rule); ``limit`` stops after
    that many kept frames, without asking for the next one (a live stream ends at once);
    ``start`` skips the first kept frames (those a resumed map holds, counted as ``in_map``):
    the first window starts at kept frame ``start`` whatever window boundaries an earlier run
    had. ``max_depth`` (metres): depth pixels beyond it (and
    negative ones) become 0, "no depth", and are counted in ``counts.depth_out_of_range``.
    Skipped records and frames with a non-finite pose are counted in ``counts``; a window ends
    early where the image size changes."""
    import torch

    if size < 1:
        raise ValueError(f"window={size!r}: expected an integer >= 1")
    if max_depth is not None and not (0 < float(max_depth) < math.inf):
        raise ValueError(f"max_depth={max_depth!r}: expected a finite number of metres > 0")
    batch: list[RGBDFrame] = []
    position, first, seen = 0, 0, 0

    def emit() -> dict:
        return {
            "image": torch.from_numpy(np.stack([f.image for f in batch])).permute(0, 3, 1, 2),
            "depth": torch.from_numpy(np.stack([f.depth for f in batch]).astype(np.float32)),
            "intrinsics": torch.from_numpy(np.stack([f.intrinsics for f in batch])).float(),
            "pose": torch.from_numpy(np.stack([f.pose for f in batch])).double(),
            "stamp": [f.stamp for f in batch],
            "name": [f.name for f in batch],
            "first": first,
        }

    for frame in frames:
        if isinstance(frame, SkippedFrame):
            counts.read += 1
            counts.skip(frame)
            continue
        counts.read += 1
        keep = seen % (frame_skip + 1) == 0
        seen += 1
        if not keep:
            counts.skip(SkippedFrame(frame.name, f"frame_skip={frame_skip}", "frame_skip"))
            continue
        if not np.isfinite(frame.pose).all():
            counts.skip(SkippedFrame(frame.name, "non-finite pose", "no_pose"))
            continue
        if position < start:
            counts.skip(SkippedFrame(frame.name, "held by the resumed map", "in_map"))
            position += 1
            if limit is not None and position >= limit:
                break
            continue
        if max_depth is not None:
            out = ~(frame.depth <= max_depth) & (frame.depth != 0)  # NaN, > max, negative
            out |= frame.depth < 0
            n_out = int(out.sum())
            if n_out:
                frame.depth = np.where(out, np.float32(0), frame.depth).astype(np.float32)
                counts.depth_out_of_range += n_out
                counts.depth_out_of_range_frames += 1
        same = not batch or (
            frame.image.shape == batch[0].image.shape and frame.depth.shape == batch[0].depth.shape
        )
        if batch and (len(batch) == size or not same):
            yield emit()
            batch = []
        if not batch:
            first = position
        batch.append(frame)
        position += 1
        if limit is not None and position >= limit:
            break  # before asking for another frame: a live stream may never send one
    if batch:
        yield emit()
