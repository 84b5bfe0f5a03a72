"""A procedural ScanNet-format scene: a room of labelled axis-aligned boxes, written in the
exported ScanNet v2 layout (tests and benchmarks of the 3D task, docs/maps.md#3d-semantic-mapping).

The world is z-up, in metres. The room ``[0, X] x [0, Y] x [0, Z]`` is closed by six slabs
(floor, ceiling, four walls) and holds a few objects (bed, table, chair, sofa, cabinet, a
door on a wall, and a plant, whose NYU40 class ``otherprop`` is not evaluated). A camera
circles inside the room looking across it. Per frame, depth is ray-cast exactly (slab test
per box, nearest hit; the camera's ``z`` is the depth), the label is the hit box's raw
ScanNet id, and the RGB pixel shows the hit box's class. Two worlds (:data:`WORLDS`):

- ``smoke`` (default of the command line): the label map names the boxes' classes with the
  2D synthetic world's vocabulary (:data:`resireg_train.data.synthetic.SYNTHETIC_CLASSES`:
  walls "building", floor "road", ceiling "sky", ...) and every pixel is painted with that
  class's colour, stripes and noise (:func:`resireg_train.data.synthetic.paint`, the training
  data of ``experiment=smoke``), so a smoke-trained model recognises the room's classes and
  scores above chance (the door is not evaluated here: the vocabulary has 8 names);
- ``nyu40``: ScanNet's own names (wall, floor, ..., the plant's otherprop not evaluated) and
  flat colours (:data:`NYU40_COLOURS`, all pairs >= 85 levels apart), so a test encoder can
  read the class back from the colour. A model trained on anything else knows none of these
  words for these flat colours: expect scores near zero.

Written (``write_scene(root, scene)``)::

    <root>/scannetv2-labels.combined.tsv        (real column names; the raw ids used here)
    <root>/<scene>/color/<i>.jpg                 RGB, JPEG quality 100, no chroma subsampling
    <root>/<scene>/depth/<i>.png                 uint16 millimetres, 0 = no depth
    <root>/<scene>/pose/<i>.txt                  4 x 4 camera-to-world (OpenCV camera axes)
    <root>/<scene>/intrinsic/intrinsic_color.txt, intrinsic_depth.txt   4 x 4, K top-left
    <root>/<scene>/label-filt/<i>.png            uint16 raw ScanNet ids, 0 = unlabelled

One frame (``bad_pose_frame``) gets the all ``-inf`` pose that ScanNet writes where tracking
failed, so the reader's drop rule is exercised. ``python -m resireg_train.data.scannet_room
OUT [--world smoke|nyu40]`` writes the default scene (``synthetic0000_00``) under ``OUT``.
"""

from __future__ import annotations

import argparse
import itertools
from dataclasses import dataclass, field
from pathlib import Path

import numpy as np
from PIL import Image

__all__ = [
    "Box",
    "NYU40_COLOURS",
    "RAW_LABELS",
    "SMOKE_LABELS",
    "WORLDS",
    "SyntheticRoom",
    "look_at",
    "ray_cast",
    "write_scene",
]

#: Raw ScanNet label id -> (raw_category, nyu40id, nyu40class): the rows of the
#: ``scannetv2-labels.combined.tsv`` this scene needs (ids and NYU40 ids as in ScanNet's file).
RAW_LABELS: dict[int, tuple[str, int, str]] = {
    1: ("wall", 1, "wall"),
    2: ("chair", 5, "chair"),
    3: ("floor", 2, "floor"),
    4: ("table", 7, "table"),
    5: ("door", 8, "door"),
    6: ("couch", 6, "sofa"),
    7: ("cabinet", 3, "cabinet"),
    11: ("bed", 4, "bed"),
    35: ("plant", 40, "otherprop"),
    36: ("ceiling", 22, "ceiling"),
}

#: The smoke world's rows: raw id -> (raw_category, nyu40id, class name of the 2D synthetic
#: world). The door and the plant are otherprop (not evaluated); their pixels are painted as
#: "building" and "tree".
SMOKE_LABELS: dict[int, tuple[str, int, str]] = {
    1: ("wall", 1, "building"),
    2: ("chair", 5, "person"),
    3: ("floor", 2, "road"),
    4: ("table", 7, "tree"),
    5: ("door", 40, "otherprop"),
    6: ("couch", 6, "water"),
    7: ("cabinet", 3, "grass"),
    11: ("bed", 4, "car"),
    35: ("plant", 40, "otherprop"),
    36: ("ceiling", 22, "sky"),
}
#: The smoke world's painted class of the two unevaluated boxes.
_SMOKE_PAINT = {5: "building", 35: "tree"}
#: The room's label worlds (module docstring).
WORLDS = ("smoke", "nyu40")

#: One RGB colour per NYU40 id (0 = unlabelled): the 64 colours of a 4-level grid, levels
#: 0, 85, 170, 255, so any two colours differ by >= 85 in some channel.
NYU40_COLOURS: np.ndarray = np.array(
    list(itertools.product((0, 85, 170, 255), repeat=3))[:41], dtype=np.uint8
)

_TSV_COLUMNS = ("id", "raw_category", "category", "count", "nyu40id", "nyu40class")


@dataclass(frozen=True)
class Box:
    """An axis-aligned box ``[lo, hi]`` (metres) labelled with a raw ScanNet id."""

    lo: tuple[float, float, float]
    hi: tuple[float, float, float]
    raw_id: int

    @property
    def nyu40(self) -> int:
        return RAW_LABELS[self.raw_id][1]


def _room_boxes(size: tuple[float, float, float], thickness: float = 0.1) -> list[Box]:
    x, y, z = size
    t = thickness
    return [
        Box((-t, -t, -t), (x + t, y + t, 0.0), 3),  # floor
        Box((-t, -t, z), (x + t, y + t, z + t), 36),  # ceiling
        Box((-t, -t, 0.0), (0.0, y + t, z), 1),  # wall x = 0
        Box((x, -t, 0.0), (x + t, y + t, z), 1),  # wall x = X
        Box((0.0, -t, 0.0), (x, 0.0, z), 1),  # wall y = 0
        Box((0.0, y, 0.0), (x, y + t, z), 1),  # wall y = Y
    ]


def _default_objects() -> list[Box]:
    return [
        Box((0.3, 1.7, 0.0), (1.5, 2.8, 0.55), 11),  # bed against wall y = Y
        Box((2.3, 1.1, 0.0), (3.1, 1.7, 0.75), 4),  # table
        Box((2.45, 0.55, 0.0), (2.9, 0.95, 0.9), 2),  # chair
        Box((3.35, 1.6, 0.0), (3.95, 2.9, 0.8), 6),  # sofa against wall x = X
        Box((0.05, 0.1, 0.0), (0.55, 0.9, 1.6), 7),  # cabinet against wall x = 0
        Box((1.6, 2.97, 0.0), (2.5, 3.0, 2.0), 5),  # door on wall y = Y (3 cm proud)
        Box((3.5, 0.2, 0.0), (3.8, 0.5, 1.1), 35),  # plant (otherprop: not evaluated)
    ]


@dataclass
class SyntheticRoom:
    """The room, its camera intrinsics and trajectory.

    Args:
        size: room extent ``(X, Y, Z)`` in metres.
        image_size: ``(H, W)`` of every image (colour, depth and labels share it).
        focal: focal length in pixels (``fx = fy``); the principal point is the image
            centre ``((W - 1) / 2, (H - 1) / 2)`` (pixel centres at integer coordinates).
        frames: number of frames of the trajectory.
        bad_pose_frame: frame written with an all ``-inf`` pose (``None``: none).
        objects: the boxes inside the room (default: the furniture of the module docstring).
    """

    size: tuple[float, float, float] = (4.0, 3.0, 2.5)
    image_size: tuple[int, int] = (48, 64)
    focal: float = 40.0
    frames: int = 10
    bad_pose_frame: int | None = 2
    objects: list[Box] = field(default_factory=_default_objects)

    @property
    def boxes(self) -> list[Box]:
        """Every labelled box: the room's six slabs, then the objects."""
        return _room_boxes(self.size) + list(self.objects)

    @property
    def intrinsics(self) -> np.ndarray:
        """``K`` ``[3, 3]`` of the images."""
        h, w = self.image_size
        return np.array(
            [[self.focal, 0.0, (w - 1) / 2], [0.0, self.focal, (h - 1) / 2], [0.0, 0.0, 1.0]]
        )

    def pose(self, i: int) -> np.ndarray:
        """Camera-to-world ``[4, 4]`` of frame ``i``: on an ellipse 1.4 m high, looking at a
        point across the room, 0.6 m above the floor."""
        x, y, _ = self.size
        a = 2 * np.pi * i / self.frames + 0.3
        eye = np.array([x / 2 + 0.28 * x * np.cos(a), y / 2 + 0.28 * y * np.sin(a), 1.4])
        target = np.array([x / 2 - 0.3 * x * np.cos(a), y / 2 - 0.3 * y * np.sin(a), 0.6])
        return look_at(eye, target)

    def render(self, i: int) -> tuple[np.ndarray, np.ndarray]:
        """``(depth [H, W] metres, raw label ids [H, W])`` of frame ``i`` (exact ray cast)."""
        return ray_cast(self.boxes, self.intrinsics, self.pose(i), self.image_size)


def look_at(eye: np.ndarray, target: np.ndarray, up: tuple[float, float, float] = (0, 0, 1)):
    """Camera-to-world ``[4, 4]`` with OpenCV camera axes (x right, y down, z forward)."""
    forward = (target - eye) / np.linalg.norm(target - eye)
    right = np.cross(forward, np.asarray(up, dtype=float))
    right /= np.linalg.norm(right)
    down = np.cross(forward, right)
    pose = np.eye(4)
    pose[:3, :3] = np.stack([right, down, forward], axis=1)
    pose[:3, 3] = eye
    return pose


def ray_cast(
    boxes: list[Box], intrinsics: np.ndarray, pose: np.ndarray, image_size: tuple[int, int]
) -> tuple[np.ndarray, np.ndarray]:
    """Depth ``[H, W]`` (metres; 0 where no box is hit) and the hit box's raw id ``[H, W]``.

    The ray of pixel ``(u, v)`` (pixel centres at integer coordinates) has camera direction
    ``((u - cx) / fx, (v - cy) / fy, 1)``, so its parameter at a hit is the depth. Each box
    is intersected with the slab test; the nearest hit in front of the camera wins.
    """
    h, w = image_size
    v, u = np.mgrid[0:h, 0:w].astype(np.float64)
    k = intrinsics
    d_cam = np.stack([(u - k[0, 2]) / k[0, 0], (v - k[1, 2]) / k[1, 1], np.ones_like(u)], -1)
    d = d_cam.reshape(-1, 3) @ pose[:3, :3].T
    o = pose[:3, 3]
    depth = np.full(h * w, np.inf)
    raw = np.zeros(h * w, dtype=np.int64)
    with np.errstate(divide="ignore", invalid="ignore"):
        inv = 1.0 / d
        for box in boxes:
            t1 = (np.asarray(box.lo) - o) * inv
            t2 = (np.asarray(box.hi) - o) * inv
            near = np.nanmax(np.minimum(t1, t2), axis=1)
            far = np.nanmin(np.maximum(t1, t2), axis=1)
            hit = (far >= near) & (near > 0) & (near < depth)
            depth[hit] = near[hit]
            raw[hit] = box.raw_id
    depth[~np.isfinite(depth)] = 0.0
    return depth.reshape(h, w), raw.reshape(h, w)


def _matrix_text(m: np.ndarray) -> str:
    return "\n".join(" ".join(f"{v:.9g}" for v in row) for row in m) + "\n"


def _rows(world: str) -> dict[int, tuple[str, int, str]]:
    if world not in WORLDS:
        raise ValueError(f"world={world!r}: expected one of {WORLDS}")
    return SMOKE_LABELS if world == "smoke" else RAW_LABELS


def write_label_map(root: str | Path, world: str = "nyu40") -> Path:
    """``<root>/scannetv2-labels.combined.tsv`` with the rows of the ``world``
    (:data:`RAW_LABELS` or :data:`SMOKE_LABELS`)."""
    path = Path(root) / "scannetv2-labels.combined.tsv"
    path.parent.mkdir(parents=True, exist_ok=True)
    lines = ["\t".join(_TSV_COLUMNS)]
    for raw, (name, nyu, nyu_name) in _rows(world).items():
        lines.append("\t".join(map(str, (raw, name, name, 1, nyu, nyu_name))))
    path.write_text("\n".join(lines) + "\n")
    return path


def _painter(world: str, seed: int):
    """``raw ids [H, W] -> uint8 RGB [H, W, 3]`` of the ``world`` (module docstring)."""
    if world == "nyu40":
        nyu_of_raw = np.zeros(max(RAW_LABELS) + 1, dtype=np.int64)
        for raw, (_, nyu, _) in RAW_LABELS.items():
            nyu_of_raw[raw] = nyu
        return lambda raw, i: NYU40_COLOURS[nyu_of_raw[raw]]
    from resireg_train.data.synthetic import SYNTHETIC_CLASSES, paint

    cls_of_raw = np.zeros(max(SMOKE_LABELS) + 1, dtype=np.int64)
    for raw, (_, _, name) in SMOKE_LABELS.items():
        cls_of_raw[raw] = SYNTHETIC_CLASSES.index(_SMOKE_PAINT.get(raw, name))
    noise = 12.0  # conf/data/synthetic.yaml's training scenes use SyntheticScenes' default
    return lambda raw, i: paint(cls_of_raw[raw], np.random.default_rng([seed, i]), noise)


def write_scene(
    root: str | Path,
    scene: str = "synthetic0000_00",
    room: SyntheticRoom | None = None,
    world: str = "nyu40",
    seed: int = 0,
) -> Path:
    """Write ``room`` (default :class:`SyntheticRoom`) as ScanNet scene ``scene`` under
    ``root`` (and the label map of ``world`` at ``root``); ``seed`` seeds the smoke world's
    pixel noise. Returns the scene folder."""
    room = room or SyntheticRoom()
    folder = Path(root) / scene
    for sub in ("color", "depth", "pose", "intrinsic", "label-filt"):
        (folder / sub).mkdir(parents=True, exist_ok=True)
    write_label_map(root, world)
    painter = _painter(world, seed)
    k4 = np.eye(4)
    k4[:3, :3] = room.intrinsics
    for name in ("intrinsic_color.txt", "intrinsic_depth.txt"):
        (folder / "intrinsic" / name).write_text(_matrix_text(k4))
    for i in range(room.frames):
        depth, raw = room.render(i)
        colour = painter(raw, i)
        Image.fromarray(colour).save(folder / "color" / f"{i}.jpg", quality=100, subsampling=0)
        mm = np.clip(np.rint(depth * 1000.0), 0, 65535).astype(np.uint16)
        Image.fromarray(mm).save(folder / "depth" / f"{i}.png")
        Image.fromarray(raw.astype(np.uint16)).save(folder / "label-filt" / f"{i}.png")
        pose = room.pose(i)
        if i == room.bad_pose_frame:
            pose = np.full((4, 4), -np.inf)
        (folder / "pose" / f"{i}.txt").write_text(_matrix_text(pose))
    return folder


def main(argv: list[str] | None = None) -> None:
    parser = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    parser.add_argument("root", help="dataset root to write (the scene folder goes inside)")
    parser.add_argument("--scene", default="synthetic0000_00")
    parser.add_argument("--frames", type=int, default=SyntheticRoom.frames)
    parser.add_argument("--height", type=int, default=SyntheticRoom.image_size[0])
    parser.add_argument("--width", type=int, default=SyntheticRoom.image_size[1])
    parser.add_argument("--focal", type=float, default=SyntheticRoom.focal)
    parser.add_argument("--world", choices=WORLDS, default="smoke",
                        help="smoke: the classes and textures experiment=smoke learns; nyu40: "
                             "ScanNet's names, flat colours (module docstring)")  # fmt: skip
    args = parser.parse_args(argv)
    room = SyntheticRoom(image_size=(args.height, args.width), focal=args.focal, frames=args.frames)
    print(write_scene(args.root, args.scene, room, world=args.world))


if __name__ == "__main__":
    main()
