"""Posed RGB-D recordings for ``resireg-map``: the frame record, timestamp pairing, pose tracks and
windows (docs/design.md section 10.3).

A source (:mod:`.rosbag`, :mod:`.tum`, :func:`resireg_train.data.scannet.scannet_rgbd`) yields, in
time order, :class:`RGBDFrame` records or :class:`SkippedFrame` records (a message or file that
could not be decoded or paired, with the reason); :class:`FrameCounts` tallies them and
:func:`windows` groups consecutive frames of one size into the ``[B, ...]`` tensors
:meth:`resireg.mapping.SemanticMap.add` takes.

**Pairing.** :func:`pair_nearest` gives every anchor stamp (depth) the nearest stamp of another
stream (colour) within a tolerance, ties to the earlier one (``numpy.searchsorted``), as TUM's
``associate.py`` does for one pair (it also makes the pairs one-to-one; a depth stream faster
than colour here reuses a colour image). **Poses.** :class:`PoseTrack` interpolates a stamped
pose stream at a time ``t``, as tf2 does: between the samples just before and after ``t``, the
translation linearly and the rotation by spherical linear interpolation
(``scipy.spatial.transform.Slerp``), provided the two are at most ``max_gap`` seconds apart; a
time before the first or after the last sample takes that sample if it is within ``tolerance``
(tf2 would refuse to extrapolate at all), else has no
pose. These modules import numpy, torch, scipy and PIL only (no Lightning, no Hydra).
"""

from __future__ import annotations

import math
from collections import Counter
from collections.abc import Iterable, Iterator
from dataclasses import dataclass, field

import numpy as np
import torch
from scipy.spatial.transform import Rotation, Slerp

__all__ = [
    "FrameCounts",
    "PoseTrack",
    "RGBDFrame",
    "SkippedFrame",
    "pair_nearest",
    "pose_matrix",
    "windows",
]


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


def pair_nearest(anchors: np.ndarray, stamps: np.ndarray, tolerance: float) -> np.ndarray:
    """For each anchor time the index of the nearest of ``stamps`` (sorted ascending) within
    ``tolerance`` seconds, else -1; of two equally near stamps the earlier wins."""
    anchors = np.asarray(anchors, dtype=np.float64)
    stamps = np.asarray(stamps, dtype=np.float64)
    out = np.full(anchors.shape[0], -1, dtype=np.int64)
    if stamps.size == 0:
        return out
    if np.any(np.diff(stamps) < 0):
        raise ValueError("pair_nearest: stamps must be sorted ascending")
    right = np.searchsorted(stamps, anchors, side="left").clip(0, stamps.size - 1)
    left = (right - 1).clip(0, stamps.size - 1)
    d_left, d_right = np.abs(anchors - stamps[left]), np.abs(stamps[right] - anchors)
    best = np.where(d_left <= d_right, left, right)
    ok = np.minimum(d_left, d_right) <= tolerance
    out[ok] = best[ok]
    return out


def pose_matrix(translation: Iterable[float], quaternion_xyzw: Iterable[float]) -> np.ndarray:
    """``[4, 4]`` float64 from a translation and a unit quaternion ``(x, y, z, w)`` (ROS's and
    TUM's order; scipy's ``Rotation.from_quat`` normalises it)."""
    m = np.eye(4)
    m[:3, :3] = Rotation.from_quat(np.asarray(list(quaternion_xyzw), dtype=np.float64)).as_matrix()
    m[:3, 3] = np.asarray(list(translation), dtype=np.float64)
    return m


class PoseTrack:
    """A stamped pose stream (module docstring): ``at(t)`` -> ``[4, 4]`` or ``None``.

    Args:
        stamps: ``[N]`` seconds (any order; sorted here, a repeated stamp keeps its last pose).
        poses: ``[N, 4, 4]`` rigid transforms.
        tolerance: seconds a time may lie before the first / after the last sample.
        max_gap: the longest interval in seconds between two samples interpolated across.
        static: one pose valid at every time (``/tf_static``).
    """

    def __init__(self, stamps, poses, tolerance: float = 0.02, max_gap: float = 0.5,
                 static: bool = False) -> None:  # fmt: skip
        stamps = np.asarray(stamps, dtype=np.float64).reshape(-1)
        poses = np.asarray(poses, dtype=np.float64).reshape(-1, 4, 4)
        if stamps.shape[0] != poses.shape[0] or stamps.shape[0] == 0:
            raise ValueError(f"PoseTrack: {stamps.shape[0]} stamps for {poses.shape[0]} poses")
        order = np.argsort(stamps, kind="stable")
        stamps, poses = stamps[order], poses[order]
        last = np.append(stamps[1:] != stamps[:-1], True)  # a repeated stamp: its last pose
        self.stamps, self.poses = stamps[last], poses[last]
        self.tolerance, self.max_gap = float(tolerance), float(max_gap)
        self.static = static
        self._slerp = (
            Slerp(self.stamps, Rotation.from_matrix(self.poses[:, :3, :3]))
            if self.stamps.size > 1
            else None
        )

    def __len__(self) -> int:
        return int(self.stamps.size)

    def at(self, t: float) -> np.ndarray | None:
        if self.static:
            return self.poses[-1]
        s = self.stamps
        i = int(np.searchsorted(s, t, side="left"))
        if i < s.size and s[i] == t:
            return self.poses[i]
        if i == 0:
            return self.poses[0] if s[0] - t <= self.tolerance else None
        if i == s.size:
            return self.poses[-1] if t - s[-1] <= self.tolerance else None
        t0, t1 = s[i - 1], s[i]
        if t1 - t0 > self.max_gap:
            return None
        w = (t - t0) / (t1 - t0)
        out = np.eye(4)
        out[:3, :3] = self._slerp([t]).as_matrix()[0]
        out[:3, 3] = (1 - w) * self.poses[i - 1, :3, 3] + w * self.poses[i, :3, 3]
        return out


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
    that many kept frames; ``start`` skips the first kept frames (those a resumed map holds,
    counted as ``in_map``): the first window starts at kept frame ``start`` whatever window
    boundaries an earlier run had. ``max_depth`` (metres): depth pixels beyond it (and
    negative ones) become 0, "no depth", and are counted in ``counts.depth_out_of_range``.
    Skipped records and frames with a non-finite pose are counted in ``counts``; a window ends
    early where the image size changes."""
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
        if limit is not None and position >= limit:
            counts.read -= 1
            break
        if position < start:
            counts.skip(SkippedFrame(frame.name, "held by the resumed map", "in_map"))
            position += 1
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
    if batch:
        yield emit()
