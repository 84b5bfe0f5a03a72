"""Replica for the 3D semantic-mapping task (``resireg-eval sweep=replica3d``), read as RayFronts
reads it (``rayfronts/datasets/replica.py`` and ``experiments/semseg_configs/replica_*.yaml``
at commit cfa0e6a; docs/protocol.md, "Replica and TartanAir").

Two layouts, two dataset kinds:

``replica`` (RayFronts' ``NiceReplicaDataset``, the paper's: the NICE-SLAM renders, scored
against HOV-SG's ground-truth points)::

    <path>/cam_params.json                       {"camera": {w, h, fx, fy, cx, cy, scale}}
    <path>/<scene>/traj.txt                      one 4 x 4 camera-to-world per line (16 numbers)
    <path>/<scene>/results/frame000000.jpg       RGB
    <path>/<scene>/results/depth000000.png       uint16, metres = value / scale (6553.5)
    <semantic_info>/<office_0>/info_semantic.json   the class list (from Semantic-NeRF's Replica)
    <gt_path>/<scene>/external_semseg_gt.pt      HOV-SG's labelled points (below)

``replica_semnerf`` (RayFronts' ``SemanticNerfReplicaDataset``: Semantic-NeRF's renders with
per-frame labels; the ground truth is lifted from them like ScanNet's)::

    <path>/<office_0>/Sequence_1/traj_w_c.txt    one 4 x 4 camera-to-world per line
    <path>/<office_0>/Sequence_1/rgb/rgb_0.png, depth/depth_0.png (uint16 mm),
        semantic_class/semantic_class_0.png      (class ids of info_semantic.json)
    <path>/semantic_info/<office_0>/info_semantic.json

**Classes** (RayFronts' ``SemSegDataset._init_semseg_mappings``): the ``classes`` of the
scene's ``info_semantic.json`` in id order, id 0 being "no label", without
``classes_to_ignore`` (RayFronts' Replica configs: wall, floor, ceiling, door, window,
background). A label id of no class in the list is not scored silently (RayFronts maps it to
"no label", or crashes past the largest id): the frame (or the ground-truth file) is named.

**Ground truth of ``replica``.** RayFronts' ``semseg_eval.py load_externel_semseg_gt`` reads
``semseg_gt_xyz`` ``[N, 3]`` and ``semseg_gt_label`` ``[N]`` (Replica class ids; negative ->
0), maps ids to class indices (ignored classes and 0 -> "no label"), sums one-hot votes per
voxel (``pointcloud_to_sparse_voxels(aggregation="sum")``, ``round(p / v)``) and takes the
argmax with "no label" first (ties go to it, then to the smaller class). The file is written
by RayFronts' HOV-SG patch (``experiments/patches/hovsg.patch``,
``application/eval/evaluate_sem_seg.py``): HOV-SG's ``read_ply_and_assign_colors_replica``
reads Replica's ``habitat/mesh_semantic.ply``, repeats every face's vertices with the face's
``object_id``, maps objects to ``class_id`` through ``info_semantic.json``'s ``objects`` (0
where none), and saves the points and ids (float64) as ``semseg_gt.pt``; RayFronts reads it
as ``external_semseg_gt.pt`` (their upload, experiments/README.md). This reader reads that
file the same way; it does not rebuild it from the mesh (the mesh needs the full Replica
download and a PLY reader the project does not carry: fetch RayFronts' upload or run the
patched HOV-SG script).
"""

from __future__ import annotations

import json
import logging
from collections.abc import Mapping, Sequence
from pathlib import Path
from typing import Any

import numpy as np
import torch

from resireg.sources.scannet import FrameFileError
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
    "NICE_DOWNLOAD",
    "SEMNERF_DOWNLOAD",
    "NiceReplicaFrames",
    "SemanticNerfReplicaFrames",
    "build_replica",
    "build_replica_semnerf",
    "check_replica_spec",
    "check_replica_semnerf_spec",
    "read_semantic_info",
    "replica_classes",
]

log = logging.getLogger(__name__)

NICE_DOWNLOAD = "NICE-SLAM's Replica, github.com/cvg/nice-slam scripts/download_replica.sh"
SEMNERF_DOWNLOAD = "Semantic-NeRF's Replica renders, github.com/Harry-Zhi/semantic_nerf"
GT_DOWNLOAD = ("HOV-SG's Replica ground truth as RayFronts uploaded it (RayFronts "
               "experiments/README.md), one <scene>/external_semseg_gt.pt per scene")  # fmt: skip
GT_FILE = "external_semseg_gt.pt"
INFO_FILE = "info_semantic.json"


def semantic_scene(scene: str) -> str:
    """The Semantic-NeRF / Replica folder of a NICE-SLAM scene: ``office0`` -> ``office_0``
    (RayFronts: ``scene[:-1] + "_" + scene[-1]``)."""
    return scene[:-1] + "_" + scene[-1]


def read_semantic_info(path: Path, key: str, download: str) -> dict[int, str]:
    """``{class id: name}`` of an ``info_semantic.json`` (its ``classes``: ``id``, ``name``)."""
    if not path.is_file():
        raise source_error("class file", path, download, key)
    try:
        info = json.loads(path.read_text())
        return {int(c["id"]): str(c["name"]) for c in info["classes"]}
    except (ValueError, KeyError, TypeError) as err:
        raise ValueError(f"{key}: {str(path)!r} is not an info_semantic.json with classes "
                         f"(id, name): {err}") from None  # fmt: skip


def replica_classes(
    names: Mapping[int, str], ignore: Sequence[str]
) -> tuple[tuple[int, ...], tuple[str, ...], dict[int, int]]:
    """``(class ids, names, {id: class index or 255})``: the ids other than 0 whose name is
    not in ``ignore``, in id order (RayFronts' black list); 0 and the ignored ids map to 255."""
    ids = tuple(i for i in sorted(names) if i != 0 and names[i] not in set(ignore))
    index = {i: n for n, i in enumerate(ids)}
    mapping = {i: index.get(i, IGNORE_INDEX) for i in names}
    mapping[0] = IGNORE_INDEX
    return ids, tuple(names[i] for i in ids), mapping


def _require_folder(folder: Path, key: str, download: str) -> None:
    if not folder.is_dir():
        raise source_error("folder", folder, download, key)


class _ReplicaClasses:
    """The class list shared by a reader's scenes (one list: the scores name one class set)."""

    def _set_classes(self, files: Sequence[Path], ignore: Sequence[str], key: str,
                     download: str) -> None:  # fmt: skip
        first: dict[int, str] | None = None
        for path in files:
            names = read_semantic_info(path, key, download)
            if first is None:
                first, first_path = names, path
            elif names != first:
                raise ValueError(f"{key}: {str(path)!r} lists other classes than "
                                 f"{str(first_path)!r}: score those scenes apart")  # fmt: skip
        assert first is not None
        unknown = sorted(set(ignore) - set(first.values()))
        if unknown:
            log.info("classes_to_ignore names no class of %s: %s", files[0], unknown)
        self.class_ids, self.classes, mapping = replica_classes(first, ignore)
        self.lookup = class_lookup(mapping, max(first) + 1)
        self.class_file = str(files[0])
        if not self.classes:
            raise ValueError(f"{key}: classes_to_ignore leaves no class of {files[0]} to score")


class NiceReplicaFrames(_ReplicaClasses, PosedFrames):
    """NICE-SLAM's Replica renders, scored against HOV-SG's ground-truth points (module
    docstring). Args: the ``conf/dataset/replica.yaml`` keys."""

    ground_truth = "external"
    download = NICE_DOWNLOAD

    def __init__(
        self,
        root: str | Path,
        scenes: Sequence[str],
        semantic_info: str | Path | None,
        gt_path: str | Path,
        classes_to_ignore: Sequence[str],
        frame_skip: int,
        image_size: tuple[int, int],
        short_side: int | None,
        resize: str,
        intrinsics: str,
        limit: int | None = None,
        patch_size: int = 16,
        name: str = "replica",
        key: str = "dataset",
    ) -> None:
        super().__init__(name, key, frame_skip, image_size, short_side, patch_size, limit,
                         resize, intrinsics, "replica")  # fmt: skip
        self.root = Path(root).expanduser()
        _require_folder(self.root, f"{key}.path", NICE_DOWNLOAD)
        info = Path(semantic_info).expanduser() if semantic_info else self.root / "semantic_info"
        self.gt_path = Path(gt_path).expanduser()
        for scene in scenes:  # a wrong scene name first, before its class file
            _require_folder(self.root / scene, f"{key}.scenes", NICE_DOWNLOAD)
        self._set_classes([info / semantic_scene(s) / INFO_FILE for s in scenes],
                          classes_to_ignore, f"{key}.semantic_info", SEMNERF_DOWNLOAD)  # fmt: skip
        params = self.root / "cam_params.json"
        if not params.is_file():
            raise source_error("camera file", params, NICE_DOWNLOAD, f"{key}.path")
        try:
            cam = json.loads(params.read_text())["camera"]
            self.camera_size = (int(cam["h"]), int(cam["w"]))
            self.k = np.array([[cam["fx"], 0, cam["cx"]], [0, cam["fy"], cam["cy"]], [0, 0, 1]],
                              dtype=np.float64)  # fmt: skip
            self.depth_scale = float(cam["scale"])
        except (ValueError, KeyError, TypeError) as err:
            raise ValueError(f"{key}.path: {str(params)!r} has no camera "
                             f"{{w, h, fx, fy, cx, cy, scale}}: {err}") from None  # fmt: skip
        for scene in scenes:
            folder = self.root / scene
            _require_folder(folder, f"{key}.scenes", NICE_DOWNLOAD)
            traj = folder / "traj.txt"
            if not traj.is_file():
                raise source_error("trajectory", traj, NICE_DOWNLOAD, f"{key}.path")
            results = folder / "results"
            _require_folder(results, f"{key}.path", NICE_DOWNLOAD)
            images = len(list(results.glob("frame*.jpg")))
            poses = pad_poses(read_pose_lines(traj, 16, lambda v: v.reshape(4, 4)), images, traj)
            self.add_scene(scene, poses, lambda f, r=results: (
                r / f"frame{f:06d}.jpg", r / f"depth{f:06d}.png", None))  # fmt: skip
            gt = self.gt_path / scene / GT_FILE
            if not gt.is_file():
                raise source_error("ground truth", gt, GT_DOWNLOAD, f"{key}.gt_path")

    def read_depth(self, path: Path) -> np.ndarray:
        return read_gray(path, "depth").astype(np.float64) / self.depth_scale

    def camera(self, frame: PosedFrame, size: tuple[int, int]) -> np.ndarray:
        if size != self.camera_size:
            raise FrameFileError(frame.color, f"colour is {size[0]} x {size[1]} px, "
                                 f"cam_params.json is for {self.camera_size[0]} x "
                                 f"{self.camera_size[1]}")  # fmt: skip
        return self.k

    def scene_ground_truth(self, scene: int) -> tuple[torch.Tensor, torch.Tensor]:
        """HOV-SG's points and class indices of scene ``scene`` (module docstring); an id of
        no class in the list, a non-integer id or a malformed file is an error naming it."""
        path = self.gt_path / self.scenes[scene] / GT_FILE
        try:
            data = torch.load(path, map_location="cpu", weights_only=True)
            xyz, ids = data["semseg_gt_xyz"], data["semseg_gt_label"]
        except (OSError, RuntimeError, KeyError, TypeError, EOFError) as err:
            raise ValueError(f"{self.key}.gt_path: {str(path)!r} is not a tensor file with "
                             f"semseg_gt_xyz and semseg_gt_label: {err}") from None  # fmt: skip
        ids = ids.reshape(-1)
        if xyz.ndim != 2 or xyz.shape[1] != 3 or xyz.shape[0] != ids.shape[0]:
            raise ValueError(f"{self.key}.gt_path: {str(path)!r}: semseg_gt_xyz "
                             f"{tuple(xyz.shape)} and semseg_gt_label {tuple(ids.shape)} do not "
                             "pair as [N, 3] and [N]")  # fmt: skip
        if ids.is_floating_point() and not bool((ids == ids.round()).all()):
            raise ValueError(f"{self.key}.gt_path: {str(path)!r}: semseg_gt_label holds "
                             "non-integer ids")  # fmt: skip
        if not bool(torch.isfinite(xyz).all()):
            raise ValueError(f"{self.key}.gt_path: {str(path)!r}: semseg_gt_xyz holds "
                             "non-finite points")  # fmt: skip
        raw = ids.long().clamp(min=0).numpy()  # RayFronts: negative ids are "no label"
        try:
            labels = apply_lookup(self.lookup, raw, path, self.class_file)
        except FrameFileError as err:
            raise ValueError(f"{self.key}.gt_path: {err}") from None
        return xyz.double(), torch.from_numpy(labels)


class SemanticNerfReplicaFrames(_ReplicaClasses, PosedFrames):
    """Semantic-NeRF's Replica renders with per-frame labels (module docstring). A scene is
    ``office_0/Sequence_1`` (one sequence) or ``office_0`` (its sequences in name order, one
    frame numbering, as RayFronts plays them)."""

    download = SEMNERF_DOWNLOAD

    def __init__(
        self,
        root: str | Path,
        scenes: Sequence[str],
        classes_to_ignore: Sequence[str],
        frame_skip: int,
        image_size: tuple[int, int],
        short_side: int | None,
        resize: str,
        intrinsics: str,
        limit: int | None = None,
        patch_size: int = 16,
        name: str = "replica_semnerf",
        key: str = "dataset",
    ) -> None:
        super().__init__(name, key, frame_skip, image_size, short_side, patch_size, limit,
                         resize, intrinsics, "replica_semnerf")  # fmt: skip
        self.root = Path(root).expanduser()
        _require_folder(self.root, f"{key}.path", SEMNERF_DOWNLOAD)
        info = self.root / "semantic_info"
        for scene in scenes:
            _require_folder(self.root / scene, f"{key}.scenes", SEMNERF_DOWNLOAD)
        self._set_classes([info / s.split("/")[0] / INFO_FILE for s in scenes],
                          classes_to_ignore, f"{key}.path", SEMNERF_DOWNLOAD)  # fmt: skip
        for scene in scenes:
            folder = self.root / scene
            _require_folder(folder, f"{key}.scenes", SEMNERF_DOWNLOAD)
            sequences = [folder] if "/" in scene else sorted(
                p for p in folder.iterdir() if p.is_dir())  # fmt: skip
            if not sequences:
                raise source_error("sequence folder", folder / "Sequence_1", SEMNERF_DOWNLOAD,
                                   f"{key}.scenes")  # fmt: skip
            poses, files = [], []
            for seq in sequences:
                traj = seq / "traj_w_c.txt"
                if not traj.is_file():
                    raise source_error("trajectory", traj, SEMNERF_DOWNLOAD, f"{key}.path")
                images = len(list((seq / "rgb").glob("rgb_*.png")))
                lines = pad_poses(read_pose_lines(traj, 16, lambda v: v.reshape(4, 4)), images,
                                  traj)  # fmt: skip
                poses += lines
                files += [(seq / "rgb" / f"rgb_{f}.png", seq / "depth" / f"depth_{f}.png",
                           seq / "semantic_class" / f"semantic_class_{f}.png")
                          for f in range(len(lines))]  # fmt: skip
            self.add_scene(scene, poses, files.__getitem__)

    def read_depth(self, path: Path) -> np.ndarray:
        return read_gray(path, "depth").astype(np.float64) / 1000.0

    def read_label(self, path: Path) -> np.ndarray:
        return apply_lookup(self.lookup, read_gray(path, "label"), path, self.class_file)

    def camera(self, frame: PosedFrame, size: tuple[int, int]) -> np.ndarray:
        return pinhole_90(size)


#: The reader keys of each kind's ``conf/dataset/`` entry (beside name, kind, path, scenes,
#: protocol and the 3D task's keys).
REPLICA_KEYS = ("semantic_info", "gt_path", "classes_to_ignore", "frame_skip", "image_size",
                "short_side", "resize", "intrinsics", "limit")  # fmt: skip
SEMNERF_KEYS = ("classes_to_ignore", "frame_skip", "image_size", "short_side", "resize",
                "intrinsics", "limit")  # fmt: skip


def _source(spec: Mapping[str, Any], key: str, download: str) -> tuple[str, list[str]]:
    if not spec.get("path"):
        raise ValueError(f"{key}.path={spec.get('path')!r}: set the folder of {download}")
    scenes = spec.get("scenes")
    if not scenes:
        raise ValueError(f"{key}.scenes={scenes!r}: name at least one scene")
    return str(spec["path"]), [str(s) for s in scenes]


def build_replica(spec: Mapping[str, Any], patch_size: int, key: str = "dataset"
                  ) -> NiceReplicaFrames:  # fmt: skip
    """:class:`NiceReplicaFrames` of a ``conf/dataset/replica.yaml`` entry."""
    options = builder_options(spec, REPLICA_KEYS, key, "replica")
    root, scenes = _source(spec, key, NICE_DOWNLOAD)
    return NiceReplicaFrames(root, scenes, patch_size=patch_size, key=key,
                             name=str(spec.get("name") or "replica"), **options)  # fmt: skip


def build_replica_semnerf(spec: Mapping[str, Any], patch_size: int, key: str = "dataset"
                          ) -> SemanticNerfReplicaFrames:  # fmt: skip
    """:class:`SemanticNerfReplicaFrames` of a ``conf/dataset/replica_semnerf.yaml`` entry."""
    options = builder_options(spec, SEMNERF_KEYS, key, "replica_semnerf")
    root, scenes = _source(spec, key, SEMNERF_DOWNLOAD)
    return SemanticNerfReplicaFrames(root, scenes, patch_size=patch_size, key=key,
                                     name=str(spec.get("name") or "replica_semnerf"),
                                     **options)  # fmt: skip


def check_replica_spec(spec: Mapping[str, Any], key: str = "dataset") -> None:
    """Every folder and file of the entry, before the encoder loads (the reader's own checks:
    listing the frames reads only the text files)."""
    build_replica(spec, 16, key)


def check_replica_semnerf_spec(spec: Mapping[str, Any], key: str = "dataset") -> None:
    """Every folder and file of the entry, before the encoder loads."""
    build_replica_semnerf(spec, 16, key)
