"""The posed RGB-D frames of the 3D benchmarks beside ScanNet (Replica, TartanAir): what their
readers (:mod:`resireg_train.data.replica`, :mod:`resireg_train.data.tartanair`) share, and
what the 3D task (:class:`resireg_train.evaluation.mapping.engine.MappingEngine`) reads of
them: the item of :class:`resireg_train.data.scannet.ScanNetFrames` (``image``, ``depth``,
``intrinsics``, ``gt_label``, ``gt_depth``, ``gt_intrinsics``, ``pose``, ``scene``, ``frame``,
``index``), so one engine scores all of them.

Each reader lists a scene's frames from its trajectory file, one pose per line, as RayFronts'
readers do (``NiceReplicaDataset``, ``SemanticNerfReplicaDataset``, ``TartanAirDataset``):
frame ``f`` is the ``f``-th pose line and its images are named by ``f``; ``frame_skip = s``
keeps frame ``f`` when ``f % (s + 1) == 0``. Colour, depth and labels are resized to
``image_size`` as RayFronts does (colour bilinear and antialiased; depth and labels by the
``resize`` rule, ``torch``: ``F.interpolate(mode="nearest-exact")``; the intrinsics by the
``intrinsics`` rule, ``multiply``: ``K[0] *= W'/W``, ``K[1] *= H'/H``): the ground truth is
lifted at that same resolution (RayFronts' labels at ``rgb_resolution``).

**Bad input never scores silently.** A frame whose pose line is not 7 or 16 finite numbers (as
the format asks), or has no pose line at all, is dropped up front and listed (``dropped``:
the file, the line and what is wrong); a frame whose colour, depth or label file is missing,
truncated, of another size than its colour image, or holds a label id outside the class list,
is skipped when it is loaded and listed with that file and the reason; both are counted in
``results.json`` (``frames_dropped``, ``skipped``, ``skipped_samples``) as the 2D readers'
skipped images are. A missing or empty scene folder, a missing trajectory or class file is a
one-line error naming the file, the download that holds it and the config key to set.
"""

from __future__ import annotations

import abc
import logging
from collections.abc import Callable, Mapping, Sequence
from dataclasses import dataclass
from pathlib import Path
from typing import Any

import numpy as np
import torch

from resireg.models.images import pil_to_tensor, resize_to_patch_grid
from resireg.sources.scannet import FrameFileError, read_image, resize_rgb
from resireg_train.data.scannet import SceneFrames, resize_nearest, scale_camera
from resireg_train.data.segmentation import IGNORE_INDEX, SkippedSample
from resireg_train.data.specs import check_dataset_keys, check_dataset_values

__all__ = [
    "PosedFrame",
    "PosedFrames",
    "PoseLine",
    "class_lookup",
    "pad_poses",
    "read_pose_lines",
    "source_error",
]

log = logging.getLogger(__name__)


def source_error(what: str, path: Path, download: str, key: str) -> FileNotFoundError:
    """The one line of a missing dataset file or folder: what, where, the download holding it
    and the config key that points at it."""
    return FileNotFoundError(f"{key}: no {what} {str(path)!r} (download: {download}); set {key}")


@dataclass(frozen=True)
class PoseLine:
    """One line of a trajectory file: the camera-to-world pose, or why it has none."""

    pose: np.ndarray | None
    where: str
    reason: str = ""


def read_pose_lines(
    path: Path, numbers: int, to_matrix: Callable[[np.ndarray], np.ndarray]
) -> list[PoseLine]:
    """Every line of the trajectory file ``path`` as a :class:`PoseLine`: ``numbers``
    whitespace-separated finite numbers, turned into a ``[4, 4]`` float64 camera-to-world
    matrix by ``to_matrix``; a line with text, another count or a non-finite number holds no
    pose and says why (its frame is dropped and listed, never fused)."""
    lines = []
    for n, text in enumerate(path.read_text().splitlines(), start=1):
        where = f"{path}:{n}"
        try:
            values = np.array([float(v) for v in text.split()], dtype=np.float64)
        except ValueError:
            lines.append(PoseLine(None, where, f"pose line is not numbers: {text.strip()[:60]!r}"))
            continue
        if values.size != numbers:
            lines.append(PoseLine(None, where, f"pose line holds {values.size} numbers, "
                                               f"expected {numbers}"))  # fmt: skip
        elif not np.isfinite(values).all():
            lines.append(PoseLine(None, where, "non-finite pose (NaN or inf)"))
        else:
            lines.append(PoseLine(to_matrix(values), where))
    return lines


def pad_poses(lines: list[PoseLine], images: int, path: Path) -> list[PoseLine]:
    """``lines`` with one pose-less line per image past the last line: the frames of a
    trajectory file that is shorter than the image folder (a missing pose) are dropped and
    listed, not left out unseen."""
    missing = [PoseLine(None, str(path), f"no pose for frame {f}: {path.name} has "
                        f"{len(lines)} lines") for f in range(len(lines), images)]  # fmt: skip
    return [*lines, *missing]


def class_lookup(ids_to_index: Mapping[int, int], size: int) -> np.ndarray:
    """A ``[size]`` int64 table: a label id -> its class index, ``IGNORE_INDEX`` for the ids
    that are not scored (unlabelled, ignored classes), ``-1`` for ids outside the class list
    (the frame holding one is skipped and named, never scored)."""
    table = np.full(size, -1, dtype=np.int64)
    for label, index in ids_to_index.items():
        if 0 <= label < size:
            table[label] = index
    return table


def apply_lookup(table: np.ndarray, raw: np.ndarray, path: Path, listing: str) -> np.ndarray:
    """``table[raw]`` (class indices, 255 ignored); a :class:`FrameFileError` naming ``path``
    and the first ids outside the class list (``listing``: where that list comes from)."""
    raw = raw.astype(np.int64)
    outside = (raw < 0) | (raw >= len(table))
    out = table[np.clip(raw, 0, len(table) - 1)]
    outside |= out < 0
    if outside.any():
        bad = np.unique(raw[outside])[:5].tolist()
        raise FrameFileError(path, f"label id(s) {bad} outside the class list of {listing}")
    return out


@dataclass(frozen=True)
class PosedFrame:
    """A kept frame: its scene (position in ``scenes``), number, files and pose."""

    scene: int
    number: int
    color: Path
    depth: Path
    label: Path | None
    pose: np.ndarray


class PosedFrames(SceneFrames, abc.ABC):
    """The kept frames of the chosen scenes, scene by scene in frame order (module docstring).

    A reader subclasses it: its ``__init__`` calls this one, then :meth:`add_scene` per scene
    with the scene's pose lines and file names; it defines :meth:`read_depth` (metres, 0 = no
    depth), :meth:`camera` (``K`` of a frame of a given size) and, where it has per-frame
    labels, :meth:`read_label` (class indices, 255 = ignored). A reader whose ground truth is
    a file of labelled points per scene sets ``ground_truth = "external"`` and defines
    :meth:`scene_ground_truth`.

    Attributes:
        scenes: scene names; ``frames_per_scene`` item indices per scene.
        classes: the evaluated class names.
        dropped: frames without a usable pose (:class:`SkippedSample`, file = the pose line).
    """

    #: ``frames``: the ground truth is lifted from the frames' labels; ``external``: read per
    #: scene (:meth:`scene_ground_truth`).
    ground_truth = "frames"
    #: Where the data comes from, for the errors of a missing file.
    download = ""

    def __init__(
        self,
        name: str,
        key: str,
        frame_skip: int,
        image_size: tuple[int, int],
        short_side: int | None,
        patch_size: int,
        limit: int | None,
        resize: str,
        intrinsics: str,
        kind: str,
    ) -> None:
        check_dataset_values(kind, {"resize": resize, "intrinsics": intrinsics}, key)
        self.name, self.key = name, key
        self.ignore_index = IGNORE_INDEX
        self.frame_skip = int(frame_skip)
        self.image_size = (int(image_size[0]), int(image_size[1]))
        self.short_side, self.patch_size, self.limit = short_side, patch_size, limit
        self.resize, self.intrinsics_rule = resize, intrinsics
        self.classes: tuple[str, ...] = ()
        self.scenes: list[str] = []
        self.frames: list[PosedFrame] = []
        self.frames_per_scene: list[list[int]] = []
        self.dropped: list[SkippedSample] = []

    # ------------------------------------------------------------------ listing
    def add_scene(
        self,
        scene: str,
        poses: Sequence[PoseLine],
        files: Callable[[int], tuple[Path, Path, Path | None]],
    ) -> None:
        """List the kept frames of ``scene``: frame ``f`` has pose line ``f`` and the files
        ``files(f)`` (colour, depth, label or ``None``); a frame whose line holds no pose
        (:func:`pad_poses` adds one per image past the last line) is dropped and listed."""
        s = len(self.scenes)
        self.scenes.append(scene)
        items: list[int] = []
        for f, line in enumerate(poses):
            if f % (self.frame_skip + 1) != 0:
                continue
            if self.limit is not None and len(items) >= self.limit:
                break
            color, depth, label = files(f)
            if line.pose is None:
                self.dropped.append(SkippedSample(-1, line.where, line.reason))
                continue
            items.append(len(self.frames))
            self.frames.append(PosedFrame(s, f, color, depth, label, line.pose))
        if not items:
            log.warning("%s: no usable frames in scene %s", self.name, scene)
        self.frames_per_scene.append(items)

    # ------------------------------------------------------------------ reader hooks
    @abc.abstractmethod
    def read_depth(self, path: Path) -> np.ndarray:
        """The depth image at ``path`` in metres (0 = no depth)."""

    @abc.abstractmethod
    def camera(self, frame: PosedFrame, size: tuple[int, int]) -> np.ndarray:
        """``K`` (3 x 3) of ``frame`` at ``size`` ``(H, W)``."""

    def read_label(self, path: Path) -> np.ndarray:
        """Class indices (255 = ignored) of the label image at ``path``: a reader whose frames
        carry label files defines it (:meth:`add_scene` records none for the others)."""
        raise TypeError(f"{type(self).__name__} records no per-frame label files ({path})")

    def scene_ground_truth(self, scene: int) -> tuple[torch.Tensor, torch.Tensor]:
        """``(points [N, 3] float64, class indices [N] int64, 255 = ignored)`` of a scene
        whose ground truth is external (``ground_truth = "external"``)."""
        raise TypeError(f"{type(self).__name__} lifts its ground truth from frames")

    # ------------------------------------------------------------------ dataset
    def _load(self, frame: PosedFrame) -> dict[str, Any]:
        colour = read_image(frame.color, "colour", pil_to_tensor)
        size = tuple(colour.shape[-2:])
        depth_m = self.read_depth(frame.depth)
        if tuple(depth_m.shape) != size:
            raise FrameFileError(
                frame.depth, f"depth is {depth_m.shape[0]} x {depth_m.shape[1]} px, its colour "
                f"image {frame.color.name} is {size[0]} x {size[1]}",
            )  # fmt: skip
        k = torch.from_numpy(self.camera(frame, size))
        depth = torch.from_numpy(depth_m.astype(np.float32))
        rule, scale = self.resize, self.intrinsics_rule
        image = resize_to_patch_grid(resize_rgb(colour, self.image_size), self.short_side,
                                     self.patch_size)  # fmt: skip
        camera = scale_camera(k, size, self.image_size, scale).float()
        resized = resize_nearest(depth, self.image_size, rule)
        item = {"image": image, "depth": resized, "intrinsics": camera,
                "gt_depth": resized, "gt_intrinsics": camera,
                "pose": torch.from_numpy(frame.pose), "scene": frame.scene,
                "frame": frame.number}  # fmt: skip
        if frame.label is not None:
            label = self.read_label(frame.label)
            if tuple(label.shape) != size:
                raise FrameFileError(
                    frame.label, f"label is {label.shape[0]} x {label.shape[1]} px, its colour "
                    f"image {frame.color.name} is {size[0]} x {size[1]}",
                )  # fmt: skip
            item["gt_label"] = resize_nearest(torch.from_numpy(label.astype(np.int64)),
                                              self.image_size, rule)  # fmt: skip
        return item

    def __getitem__(self, index: int) -> dict[str, Any] | SkippedSample:
        frame = self.frames[index]
        try:
            item = self._load(frame)
        except FrameFileError as err:
            return SkippedSample(index, str(err.path), err.reason)
        item["index"] = index
        return item


def read_gray(path: Path, what: str) -> np.ndarray:
    """A one-channel image as an unsigned integer array (16-bit PNGs stay unsigned: values
    above 32767 are kept, never read as negative); a :class:`FrameFileError` naming the file
    when it is missing, truncated or has channels."""
    array = read_image(path, what)
    if array.ndim != 2:
        raise FrameFileError(path, f"{what} has shape {array.shape}: expected one channel")
    if array.dtype.kind == "i" and array.dtype.itemsize == 2:
        array = array.view(np.uint16)
    elif array.dtype.kind == "i":  # PIL's mode I (32-bit) of a 16-bit PNG
        if array.min() < 0:
            raise FrameFileError(path, f"{what} holds negative values")
    return array


def builder_options(spec: Mapping[str, Any], reader_keys: Sequence[str], key: str,
                    kind: str) -> dict[str, Any]:  # fmt: skip
    """The reader's keywords of a ``conf/dataset/`` entry of ``kind`` (every key checked
    against the dataset table; lists of sizes as tuples)."""
    if spec.get("kind") != kind:
        raise ValueError(f"{key}.kind={spec.get('kind')!r}: expected {kind!r}")
    check_dataset_keys(spec, key)
    options = {k: spec[k] for k in reader_keys}
    if isinstance(options.get("image_size"), (list, tuple)):
        options["image_size"] = tuple(int(v) for v in options["image_size"])
    return options


def pinhole_90(size: tuple[int, int]) -> np.ndarray:
    """``K`` of a 90-degree horizontal field of view at ``size = (H, W)``: ``fx = fy = W / 2``,
    ``cx = W / 2``, ``cy = H / 2`` (RayFronts' constants of the Semantic-NeRF Replica renders,
    320 at 480 x 640, and of TartanAir v2, 320 at 640 x 640)."""
    h, w = size
    f = w / 2
    return np.array([[f, 0.0, w / 2], [0.0, f, h / 2], [0.0, 0.0, 1.0]], dtype=np.float64)
