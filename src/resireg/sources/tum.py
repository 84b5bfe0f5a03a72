"""Posed RGB-D frames from a sequence in the TUM RGB-D benchmark's layout, for ``resireg-map``
(docs/maps.md#robot-maps-semanticmap). The layout (https://cvg.cit.tum.de/data/datasets/rgbd-dataset/file_formats)::

    <path>/rgb.txt            "timestamp filename" per line (# comments), e.g. 1305031102.175304 rgb/1305031102.175304.png
    <path>/depth.txt          the same for depth/*.png: uint16, 5000 units per metre (0 = none)
    <path>/groundtruth.txt    "timestamp tx ty tz qx qy qz qw": the colour camera's optical
                              centre in the world (quaternion x, y, z, w; camera axes x right,
                              y down, z forward)

Every depth image is a candidate frame: the colour image of the nearest timestamp within
``tolerance`` (TUM's ``associate.py`` pairs with ``max_difference`` 0.02 s) and the ground-truth
pose interpolated at the depth image's timestamp (:class:`~resireg.sources.pairing.PoseTrack`;
the motion capture runs at 100 Hz). The depth images are registered to the colour images, so
the colour camera's intrinsics serve both: ``camera`` picks TUM's published values
(:data:`CAMERAS`; ``ros_default`` is what the depth registration used) or ``intrinsics``
``[fx, fy, cx, cy]`` sets them. The images are not undistorted (TUM's fr1 / fr2 have small
radial distortion, which the map ignores).
"""

from __future__ import annotations

from collections.abc import Iterator, Sequence
from pathlib import Path

import numpy as np
from PIL import Image

from resireg.errors import DataError
from resireg.sources.frames import DECODE_ERRORS, RGBDFrame, SkippedFrame, SourceNotFoundError
from resireg.sources.pairing import PoseTrack, pair_nearest, pose_matrix
from resireg.specs.sources import TUM_CAMERAS

__all__ = ["CAMERAS", "DEPTH_SCALE", "TumSource", "read_list", "read_trajectory"]

#: TUM's depth PNGs: 5000 units per metre.
DEPTH_SCALE = 5000.0
#: ``[fx, fy, cx, cy]`` of TUM's cameras (file_formats page, "Intrinsic Camera Calibration"; the
#: source table's, :data:`resireg.specs.sources.TUM_CAMERAS`).
CAMERAS = TUM_CAMERAS


def _lines(path: Path) -> list[list[str]]:
    if not path.is_file():
        raise SourceNotFoundError(
            f"path={str(path.parent)!r}: no {path.name} in it (TUM RGB-D layout)"
        )
    out = []
    for line in path.read_text().splitlines():
        line = line.strip()
        if line and not line.startswith("#"):
            out.append(line.replace(",", " ").split())
    return out


def read_list(path: Path) -> tuple[np.ndarray, list[str]]:
    """``rgb.txt`` / ``depth.txt``: timestamps ``[N]`` (sorted) and file names."""
    rows = sorted((float(r[0]), r[1]) for r in _lines(path) if len(r) >= 2)
    return np.array([t for t, _ in rows]), [f for _, f in rows]


def read_trajectory(path: Path) -> PoseTrack:
    """``groundtruth.txt`` -> a :class:`PoseTrack` (tolerance set by the caller)."""
    rows = [r for r in _lines(path) if len(r) >= 8]
    if not rows:
        raise DataError(
            f"path={str(path.parent)!r}: {path.name} holds no 'timestamp tx ty tz qx qy qz qw' line"
        )
    values = np.array([[float(v) for v in r[:8]] for r in rows])
    poses = np.stack([pose_matrix(v[1:4], v[4:8]) for v in values])
    return PoseTrack(values[:, 0], poses)


class TumSource:
    """The frames of a TUM RGB-D sequence folder (module docstring).

    Args:
        path: the sequence folder.
        tolerance: seconds from a depth image to its colour image and pose neighbours.
        camera: a key of :data:`CAMERAS`, used unless ``intrinsics`` is given.
        intrinsics: ``[fx, fy, cx, cy]`` or ``None``.
        depth_scale: depth units per metre.
        max_pose_gap: the longest interval between two ground-truth samples interpolated across.
    """

    def __init__(
        self,
        path: str | Path,
        tolerance: float = 0.02,
        camera: str = "ros_default",
        intrinsics: Sequence[float] | None = None,
        depth_scale: float = DEPTH_SCALE,
        max_pose_gap: float = 0.5,
    ) -> None:
        self.root = Path(path).expanduser()
        if not self.root.is_dir():
            raise SourceNotFoundError(f"path={str(path)!r}: no such folder")
        if intrinsics is None:
            if camera not in CAMERAS:
                raise DataError(f"camera={camera!r}: expected one of {sorted(CAMERAS)}")
            intrinsics = CAMERAS[camera]
        if len(intrinsics) != 4:
            raise DataError(f"intrinsics={list(intrinsics)!r}: expected [fx, fy, cx, cy]")
        fx, fy, cx, cy = (float(v) for v in intrinsics)
        self.intrinsics = np.array([[fx, 0, cx], [0, fy, cy], [0, 0, 1.0]])
        self.tolerance, self.depth_scale = float(tolerance), float(depth_scale)
        self.rgb_times, self.rgb_files = read_list(self.root / "rgb.txt")
        self.depth_times, self.depth_files = read_list(self.root / "depth.txt")
        self.trajectory = read_trajectory(self.root / "groundtruth.txt")
        self.trajectory.tolerance = self.tolerance
        self.trajectory.max_gap = float(max_pose_gap)
        self.unpaired_colour = 0

    def __iter__(self) -> Iterator[RGBDFrame | SkippedFrame]:
        match = pair_nearest(self.depth_times, self.rgb_times, self.tolerance)
        self.unpaired_colour = int(len(self.rgb_times) - np.unique(match[match >= 0]).size)
        for t, file, m in zip(self.depth_times, self.depth_files, match, strict=True):
            name = str(self.root / file)
            if m < 0:
                yield SkippedFrame(name, f"no rgb.txt image within {self.tolerance} s", "unpaired")
                continue
            pose = self.trajectory.at(float(t))
            if pose is None:
                yield SkippedFrame(name, f"no groundtruth.txt pose at {t:.6f} (gap or end)",
                                   "no_pose")  # fmt: skip
                continue
            colour_file = self.root / self.rgb_files[m]
            try:
                with Image.open(self.root / file) as im:
                    units = np.asarray(im)
                if units.ndim != 2:
                    raise ValueError(f"depth has shape {units.shape}: expected one channel")
                with Image.open(colour_file) as im:
                    image = np.asarray(im.convert("RGB"), dtype=np.uint8).copy()
            except FileNotFoundError as err:
                yield SkippedFrame(str(err.filename), "missing file", "undecodable")
                continue
            except (*DECODE_ERRORS, ValueError) as err:
                yield SkippedFrame(name, f"unreadable: {err}", "undecodable")
                continue
            depth = units.astype(np.float32) / np.float32(self.depth_scale)
            yield RGBDFrame(image, depth, self.intrinsics, pose, float(t), name)
