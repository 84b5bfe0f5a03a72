"""TartanAir v2 / TartanGround for the 3D semantic-mapping task (``resireg-eval
sweep=tartanair3d``), read as RayFronts' ``TartanAirDataset`` reads it
(``rayfronts/datasets/tartanair.py``, ``experiments/semseg_configs/tartanair_*.yaml`` at commit
cfa0e6a; docs/protocol.md, "Replica and TartanAir").

Layout (the front left camera of one trajectory per scene)::

    <path>/seg_rgbs.txt                               the segmentation palette (below)
    <path>/<scene>/seg_label_clean.json               {"name_map": {class name: id or [ids]}}
                                                      (label_file; RayFronts' cleaned labels)
    <path>/<scene>/<data_partition>/<sequence>/pose_lcam_front.txt
        one pose per line: tx ty tz qx qy qz qw, the camera (x forward, y right, z down) in
        the NED world
    .../image_lcam_front/000000_lcam_front.png        RGB
    .../depth_lcam_front/000000_lcam_front_depth.png  RGBA 8-bit: the 4 bytes of a
        little-endian float32 depth in metres, in OpenCV's channel order (B, G, R, A = bytes
        0, 1, 2, 3: RayFronts' ``cv2.imread(..., IMREAD_UNCHANGED).view("<f4")``)
    .../seg_lcam_front/000000_lcam_front_seg.png      uint8 segmentation values

**Poses.** The pose ``[R | t]`` (scipy's scalar-last quaternion) maps the camera's FRD axes
into NED; RayFronts turns both frames into RDF (``P = [[0,1,0],[0,0,1],[1,0,0]]``,
``pose' = P pose P^-1``): the camera gets the OpenCV axes the unprojection uses, the world
becomes (east, down, north), a permutation of NED's axes (the voxels are the same cells).

**Depth.** Decoded from the RGBA bytes; 0 is no depth and depths above ``depth_cutoff``
(100 m: the sky and background spheres) are not mapped, as RayFronts' ``inf``.

**Classes.** ``name_map``'s names in sorted order are the classes (ids 1..K; no
``classes_to_ignore`` in RayFronts' TartanAir configs). The palette ``seg_rgbs.txt`` (comma
separated, one row per segmentation id) gives in its third column the value a segmentation
image holds for that id; RayFronts reads the rows ``1 .. len - 2``. A value of a palette row no
class names is not scored (RayFronts: 0); a value no palette row holds is a label id outside
the class list, and the frame is skipped and named (RayFronts indexes a table as long as the
largest value, so that value and any above it crash it).
"""

from __future__ import annotations

import json
from collections.abc import Mapping, Sequence
from pathlib import Path
from typing import Any

import numpy as np
from scipy.spatial.transform import Rotation

from resireg.sources.scannet import FrameFileError, read_image
from resireg_train.data.posed3d import (
    PosedFrame,
    PosedFrames,
    apply_lookup,
    builder_options,
    class_lookup,
    pad_poses,
    pinhole_90,
    read_gray,
    read_pose_lines,
    source_error,
)
from resireg_train.data.segmentation import IGNORE_INDEX

__all__ = [
    "DOWNLOAD",
    "FRD_TO_RDF",
    "TartanAirFrames",
    "build_tartanair",
    "check_tartanair_spec",
    "decode_depth",
    "ned_pose",
    "read_palette",
]

DOWNLOAD = ("TartanGround (TartanAir v2), tartanair.org/tartanground, with RayFronts' cleaned "
            "labels experiments/tartanground_labels/<scene>_seg_label_clean.json")  # fmt: skip
PALETTE_FILE = "seg_rgbs.txt"
#: RDF axes from FRD axes (RayFronts' ``get_coord_system_transform("frd", "rdf")``).
FRD_TO_RDF = np.array([[0.0, 1.0, 0.0, 0.0], [0.0, 0.0, 1.0, 0.0], [1.0, 0.0, 0.0, 0.0],
                       [0.0, 0.0, 0.0, 1.0]])  # fmt: skip


def ned_pose(values: np.ndarray) -> np.ndarray:
    """Camera-to-world ``[4, 4]`` (OpenCV camera, RDF world) of a line ``tx ty tz qx qy qz qw``
    (FRD camera in NED; module docstring)."""
    pose = np.eye(4)
    pose[:3, :3] = Rotation.from_quat(values[3:7]).as_matrix()
    pose[:3, 3] = values[:3]
    return FRD_TO_RDF @ pose @ FRD_TO_RDF.T


def decode_depth(path: Path) -> np.ndarray:
    """Depth in metres ``[H, W]`` float32 from a TartanAir v2 depth PNG (module docstring)."""
    rgba = read_image(path, "depth")
    if rgba.ndim != 3 or rgba.shape[2] != 4 or rgba.dtype != np.uint8:
        raise FrameFileError(path, f"depth has shape {rgba.shape} ({rgba.dtype}): expected "
                             "an 8-bit RGBA image holding float32 bytes")  # fmt: skip
    bgra = np.ascontiguousarray(rgba[..., [2, 1, 0, 3]])
    return bgra.view("<f4")[..., 0]


def read_palette(path: Path, key: str) -> np.ndarray:
    """The third column of ``seg_rgbs.txt``, one value per segmentation id."""
    if not path.is_file():
        raise source_error("palette", path, DOWNLOAD, key)
    try:
        rows = np.loadtxt(path, delimiter=",", dtype=np.int64, ndmin=2)
    except ValueError as err:
        raise ValueError(f"{key}: {str(path)!r} is not comma-separated integer rows: "
                         f"{err}") from None  # fmt: skip
    if rows.shape[1] < 3:
        raise ValueError(f"{key}: {str(path)!r} has {rows.shape[1]} columns, expected 3")
    return rows[:, 2]


class TartanAirFrames(PosedFrames):
    """The front-left camera frames of one trajectory per scene (module docstring). Args:
    the ``conf/dataset/tartanair.yaml`` keys."""

    download = DOWNLOAD

    def __init__(
        self,
        root: str | Path,
        scenes: Sequence[str],
        data_partition: str,
        sequence: str,
        label_file: str,
        depth_cutoff: float,
        frame_skip: int,
        image_size: tuple[int, int],
        short_side: int | None,
        resize: str,
        intrinsics: str,
        limit: int | None = None,
        patch_size: int = 16,
        name: str = "tartanair",
        key: str = "dataset",
    ) -> None:
        super().__init__(name, key, frame_skip, image_size, short_side, patch_size, limit,
                         resize, intrinsics, "tartanair")  # fmt: skip
        self.root = Path(root).expanduser()
        self.depth_cutoff = float(depth_cutoff)
        if not self.root.is_dir():
            raise source_error("folder", self.root, DOWNLOAD, f"{key}.path")
        palette = read_palette(self.root / PALETTE_FILE, f"{key}.path")
        first: dict[str, list[int]] | None = None
        for scene in scenes:
            folder = self.root / scene
            if not folder.is_dir():
                raise source_error("folder", folder, DOWNLOAD, f"{key}.scenes")
            names = self._name_map(folder / label_file, f"{key}.label_file")
            if first is None:
                first, first_file = names, folder / label_file
            elif sorted(names) != sorted(first):
                raise ValueError(f"{key}.label_file: {str(folder / label_file)!r} names other "
                                 f"classes than {str(first_file)!r}: score those scenes apart")  # fmt: skip
        assert first is not None
        self.classes = tuple(sorted(first))
        self.label_listing = f"{first_file} and {self.root / PALETTE_FILE}"
        self.lookups = {scene: self._lookup(palette, self._name_map(
            self.root / scene / label_file, f"{key}.label_file"), key) for scene in scenes}  # fmt: skip
        for scene in scenes:
            seq = self.root / scene / data_partition / sequence
            if not seq.is_dir():
                raise source_error("trajectory folder", seq, DOWNLOAD,
                                   f"{key}.data_partition / {key}.sequence")  # fmt: skip
            traj = seq / "pose_lcam_front.txt"
            if not traj.is_file():
                raise source_error("pose file", traj, DOWNLOAD, f"{key}.sequence")
            images = len(list((seq / "image_lcam_front").glob("*_lcam_front.png")))
            poses = pad_poses(read_pose_lines(traj, 7, ned_pose), images, traj)
            self.add_scene(scene, poses, lambda f, d=seq: (
                d / "image_lcam_front" / f"{f:06d}_lcam_front.png",
                d / "depth_lcam_front" / f"{f:06d}_lcam_front_depth.png",
                d / "seg_lcam_front" / f"{f:06d}_lcam_front_seg.png"))  # fmt: skip

    @staticmethod
    def _name_map(path: Path, key: str) -> dict[str, list[int]]:
        if not path.is_file():
            raise source_error("label file", path, DOWNLOAD, key)
        try:
            names = json.loads(path.read_text())["name_map"]
            return {str(n): [int(i) for i in (ids if isinstance(ids, list) else [ids])]
                    for n, ids in names.items()}  # fmt: skip
        except (ValueError, KeyError, TypeError, AttributeError) as err:
            raise ValueError(f"{key}: {str(path)!r} has no name_map {{class: id or [ids]}}: "
                             f"{err}") from None  # fmt: skip

    def _lookup(self, palette: np.ndarray, names: Mapping[str, list[int]], key: str) -> np.ndarray:
        """Segmentation value -> class index: 255 for every palette value, then the named ids'
        values (rows 1 .. len - 2, as RayFronts) their class; -1 (outside) for the rest."""
        mapping = {int(v): IGNORE_INDEX for v in palette}
        index = {name: i for i, name in enumerate(self.classes)}
        for name, ids in names.items():
            for i in ids:
                if not 1 <= i <= len(palette) - 2:
                    raise ValueError(f"{key}: class {name!r} names segmentation id {i}, outside "
                                     f"the palette's rows 1..{len(palette) - 2} of "
                                     f"{self.root / PALETTE_FILE}")  # fmt: skip
                mapping[int(palette[i])] = index[name]
        return class_lookup(mapping, 256)

    def read_depth(self, path: Path) -> np.ndarray:
        depth = decode_depth(path).astype(np.float64)
        depth[~np.isfinite(depth) | (depth > self.depth_cutoff)] = 0.0
        return depth

    def read_label(self, path: Path) -> np.ndarray:
        scene = path.relative_to(self.root).parts[0]
        return apply_lookup(self.lookups[scene], read_gray(path, "label"), path,
                            self.label_listing)  # fmt: skip

    def camera(self, frame: PosedFrame, size: tuple[int, int]) -> np.ndarray:
        return pinhole_90(size)


#: The reader keys of a ``conf/dataset/tartanair.yaml`` entry.
TARTANAIR_KEYS = ("data_partition", "sequence", "label_file", "depth_cutoff", "frame_skip",
                  "image_size", "short_side", "resize", "intrinsics", "limit")  # fmt: skip


def build_tartanair(spec: Mapping[str, Any], patch_size: int, key: str = "dataset"
                    ) -> TartanAirFrames:  # fmt: skip
    """:class:`TartanAirFrames` of a ``conf/dataset/tartanair.yaml`` entry."""
    options = builder_options(spec, TARTANAIR_KEYS, key, "tartanair")
    if not spec.get("path"):
        raise ValueError(f"{key}.path={spec.get('path')!r}: set the folder of {DOWNLOAD}")
    scenes = spec.get("scenes")
    if not scenes:
        raise ValueError(f"{key}.scenes={scenes!r}: name at least one scene")
    return TartanAirFrames(str(spec["path"]), [str(s) for s in scenes], patch_size=patch_size,
                           key=key, name=str(spec.get("name") or "tartanair"), **options)  # fmt: skip


def check_tartanair_spec(spec: Mapping[str, Any], key: str = "dataset") -> None:
    """Every folder and file of the entry, before the encoder loads."""
    build_tartanair(spec, 16, key)
