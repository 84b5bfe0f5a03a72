"""Posed RGB-D frames of a Nerfstudio folder (``transforms.json``, the Nerfstudio data format),
for ``resireg-map`` (docs/maps.md#robot-maps-semanticmap). OTAS's tooling exports and imports this
format too. The file::

    {"fl_x": 525.0, "fl_y": 525.0, "cx": 319.5, "cy": 239.5, "w": 640, "h": 480,
     "depth_unit_scale_factor": 0.001,
     "frames": [{"file_path": "images/frame_00001.png",
                 "depth_file_path": "depth/frame_00001.png",
                 "transform_matrix": [[...], [...], [...], [0, 0, 0, 1]]}, ...]}

- ``transform_matrix``: camera to world, in the OpenGL / Blender camera axes Nerfstudio uses
  (x right, y up, z back); converted to the project's OpenCV camera axes (x right, y down,
  z forward) by ``T @ diag(1, -1, -1, 1)``. The world frame is kept as it is.
- ``fl_x``, ``fl_y``, ``cx``, ``cy``, ``w``, ``h``: the colour image's pinhole camera, given
  once at the top or per frame (a frame's own values win). They are taken as the pinhole
  matrix ``K`` as written (the half-pixel shift between Nerfstudio's pixel-centre convention
  and OpenCV's is not applied; exporters from ROS or RGB-D apps write ``K`` as it is);
  distortion (``k1``...) is not applied.
- ``depth_file_path`` (OTAS writes ``depth_path``): a single-channel image (16-bit PNG) or a
  ``.npy`` array, in units of ``depth_unit_scale_factor`` metres (the file's top-level value,
  else Nerfstudio's default 0.001, millimetres; the ``depth_unit_scale_factor`` argument
  overrides both). 0 and non-finite depths are "no depth". A depth image of another size than
  the colour image (an iPhone's LiDAR depth) gets ``K`` scaled to its size (pixel centres
  kept: ``c' = (c + 0.5) s - 0.5``).

Frames in the order of their ``file_path`` (Nerfstudio's order), stamped by that position. A
frame without a depth file is ``unpaired``; one whose colour or depth file is missing or
cannot be decoded ``undecodable``; one whose colour image is not of its ``w`` x ``h``
``size_mismatch``; one whose ``transform_matrix`` is not a 4 x 4 (or 3 x 4) matrix of numbers
``no_pose``: each is skipped and counted, named by its file, never fatal. A folder without a
readable ``transforms.json``, or a frame without intrinsics, is an error naming ``path``.
"""

from __future__ import annotations

import json
import math
from collections.abc import Iterator, Mapping
from pathlib import Path
from typing import Any

import numpy as np

from resireg.errors import DataError
from resireg.sources.frames import RGBDFrame, SkippedFrame, SourceNotFoundError
from resireg.sources.scannet import FrameFileError, read_image

__all__ = ["DEFAULT_DEPTH_UNIT", "OPENGL_TO_OPENCV", "NerfstudioSource"]

#: Nerfstudio's default ``depth_unit_scale_factor`` (metres per unit: millimetres).
DEFAULT_DEPTH_UNIT = 1e-3
#: Camera axes OpenGL (x right, y up, z back) -> OpenCV (x right, y down, z forward), applied
#: on the right of a camera-to-world matrix.
OPENGL_TO_OPENCV = np.diag([1.0, -1.0, -1.0, 1.0])
_INTRINSICS = ("fl_x", "fl_y", "cx", "cy")
_DEPTH_KEYS = ("depth_file_path", "depth_path")


def _number(v: Any) -> bool:
    return isinstance(v, (int, float)) and not isinstance(v, bool) and math.isfinite(v)


def _rgb(im: Any) -> np.ndarray:
    return np.asarray(im.convert("RGB"), dtype=np.uint8).copy()


class NerfstudioSource:
    """The frames of a Nerfstudio folder (module docstring); a
    :class:`~resireg.sources.frames.FrameSource`. ``transforms.json`` is read and checked when
    it is made.

    Args:
        path: the folder holding ``transforms.json``, or that file.
        depth_unit_scale_factor: metres per depth unit; ``None``: the file's value, else 0.001.
    """

    def __init__(self, path: str | Path, depth_unit_scale_factor: float | None = None) -> None:
        given = Path(path).expanduser()
        self.file = given if given.suffix == ".json" else given / "transforms.json"
        self.root = self.file.parent
        if not self.file.is_file():
            where = "no such folder" if not self.root.is_dir() else f"no {self.file.name} in it"
            raise SourceNotFoundError(f"path={str(path)!r}: {where} (a Nerfstudio folder)")
        try:
            meta = json.loads(self.file.read_text())
        except (OSError, UnicodeDecodeError, json.JSONDecodeError) as err:
            raise DataError(
                f"path={str(path)!r}: {self.file.name} is not readable JSON: {err}"
            ) from None
        frames = meta.get("frames") if isinstance(meta, dict) else None
        if not isinstance(frames, list) or not all(isinstance(f, dict) for f in frames):
            raise DataError(f"path={str(path)!r}: {self.file.name} holds no 'frames' list")
        scale = depth_unit_scale_factor
        if scale is None:
            scale = meta.get("depth_unit_scale_factor", DEFAULT_DEPTH_UNIT)
            what = f"path={str(path)!r}: {self.file.name}'s depth_unit_scale_factor={scale!r}"
        else:
            what = f"depth_unit_scale_factor={scale!r}"
        if not _number(scale) or scale <= 0:
            raise DataError(f"{what}: expected metres per depth unit > 0")
        self.depth_unit = float(scale)
        for i, frame in enumerate(frames):
            if not isinstance(frame.get("file_path"), str):
                raise DataError(f"path={str(path)!r}: frames[{i}] has no file_path")
            missing = [k for k in _INTRINSICS if not _number(frame.get(k, meta.get(k)))]
            if missing:
                raise DataError(
                    f"path={str(path)!r}: frames[{i}] ({frame['file_path']}) has no {missing} "
                    "(neither its own nor the file's): the camera's fl_x, fl_y, cx, cy"
                )
        self.meta: Mapping[str, Any] = meta
        self.frames = sorted(frames, key=lambda f: f["file_path"])  # Nerfstudio's order
        self.unpaired_colour = 0  # frames without depth are counted as unpaired candidates

    def __len__(self) -> int:
        return len(self.frames)

    def _value(self, frame: Mapping[str, Any], key: str) -> Any:
        return frame.get(key, self.meta.get(key))

    def __iter__(self) -> Iterator[RGBDFrame | SkippedFrame]:
        for i, frame in enumerate(self.frames):
            colour_file = self.root / frame["file_path"]
            name = str(colour_file)
            depth_name = next((frame[k] for k in _DEPTH_KEYS if isinstance(frame.get(k), str)),
                              None)  # fmt: skip
            if depth_name is None:
                yield SkippedFrame(name, "no depth_file_path for this frame", "unpaired")
                continue
            try:
                pose = np.asarray(frame.get("transform_matrix"), dtype=np.float64)
            except (TypeError, ValueError) as err:
                yield SkippedFrame(name, f"transform_matrix is not a matrix: {err}", "no_pose")
                continue
            if pose.shape == (3, 4):
                pose = np.vstack([pose, [0.0, 0.0, 0.0, 1.0]])
            if pose.shape != (4, 4):
                yield SkippedFrame(name, f"transform_matrix has shape {pose.shape}: expected "
                                   "4 x 4", "no_pose")  # fmt: skip
                continue
            try:
                image = read_image(colour_file, "colour", _rgb)
                depth = self._depth(self.root / depth_name)
            except FrameFileError as err:
                yield SkippedFrame(str(err.path), err.reason, "undecodable")
                continue
            w, h = self._value(frame, "w"), self._value(frame, "h")
            if _number(w) and _number(h) and image.shape[:2] != (int(h), int(w)):
                yield SkippedFrame(name, f"colour image {image.shape[1]}x{image.shape[0]} but "
                                   f"its camera is for {int(w)}x{int(h)}", "size_mismatch")  # fmt: skip
                continue
            fx, fy, cx, cy = (float(self._value(frame, k)) for k in _INTRINSICS)
            if depth.shape != image.shape[:2]:  # K of the depth image, pixel centres kept
                sx, sy = depth.shape[1] / image.shape[1], depth.shape[0] / image.shape[0]
                fx, fy, cx, cy = fx * sx, fy * sy, (cx + 0.5) * sx - 0.5, (cy + 0.5) * sy - 0.5
            k = np.array([[fx, 0.0, cx], [0.0, fy, cy], [0.0, 0.0, 1.0]])
            yield RGBDFrame(image, depth, k, pose @ OPENGL_TO_OPENCV, float(i), name)

    def _depth(self, path: Path) -> np.ndarray:
        """float32 metres of a depth file (0 for no depth); :class:`FrameFileError` naming it."""
        if path.suffix == ".npy":
            try:
                units = np.load(path, allow_pickle=False)
            except FileNotFoundError:
                raise FrameFileError(path, "missing depth file") from None
            except (OSError, ValueError) as err:
                raise FrameFileError(path, f"unreadable depth: {err}") from None
        else:
            units = read_image(path, "depth")
        units = np.asarray(units)
        if units.ndim == 3 and units.shape[-1] == 1:
            units = units[..., 0]
        if units.ndim != 2 or not (np.issubdtype(units.dtype, np.number)):
            raise FrameFileError(path, f"depth has shape {units.shape} ({units.dtype}): expected "
                                 "one channel of numbers")  # fmt: skip
        metres = units.astype(np.float32) * np.float32(self.depth_unit)
        return np.where(np.isfinite(metres) & (metres > 0), metres, np.float32(0)).astype(
            np.float32
        )
