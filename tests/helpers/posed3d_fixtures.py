"""Tiny Replica and TartanAir scenes written exactly as each dataset is downloaded (file names,
image formats, depth encodings, pose files, label encodings), for tests/resireg_train/data/test_posed3d.py.

The scene is the synthetic room of :mod:`resireg_train.data.scannet_room` (labelled boxes,
exact ray-cast depth, known camera-to-world poses with OpenCV camera axes), enlarged so that
the far wall lies beyond 5 m (a NICE-SLAM depth value above 32767 at its scale 6553.5). The
writers here use only numpy, PIL and scipy: nothing of the readers under test. Every pixel is
painted with its class's flat colour (:data:`COLOURS`), so a test encoder can read the class
back from the colour.
"""

from __future__ import annotations

import json
from dataclasses import dataclass
from pathlib import Path

import numpy as np
import torch
from PIL import Image
from scipy.spatial.transform import Rotation

from resireg_train.data.scannet_room import NYU40_COLOURS, SyntheticRoom, ray_cast

#: The room's boxes (their raw ids in scannet_room) -> (Replica class id, name). The plant is
#: an object with no class (Replica id 0, "no label").
REPLICA_OF_RAW = {
    1: (93, "wall"), 3: (40, "floor"), 36: (31, "ceiling"), 5: (37, "door"), 2: (20, "chair"),
    4: (80, "table"), 6: (76, "sofa"), 7: (14, "cabinet"), 11: (7, "bed"), 35: (0, "undefined"),
}  # fmt: skip
#: Replica's class list of the fixture: the room's classes and some absent ones.
REPLICA_CLASSES = {0: "undefined", 3: "basket", 7: "bed", 14: "cabinet", 20: "chair",
                   31: "ceiling", 37: "door", 40: "floor", 76: "sofa", 80: "table", 93: "wall",
                   97: "window", 101: "background"}  # fmt: skip
#: RayFronts' ignored classes of Replica.
REPLICA_IGNORED = ("wall", "floor", "ceiling", "door", "window", "background")
#: The scored classes, in id order.
REPLICA_SCORED = tuple(REPLICA_CLASSES[i] for i in sorted(REPLICA_CLASSES)
                       if i and REPLICA_CLASSES[i] not in REPLICA_IGNORED)  # fmt: skip

#: TartanAir: raw id -> segmentation id (a palette row); the plant's row is named by no class.
TARTAN_ROW_OF_RAW = {1: 1, 3: 2, 36: 3, 5: 4, 2: 5, 4: 6, 6: 7, 7: 8, 11: 9, 35: 10}
#: seg_label_clean.json's name_map: class -> id or [ids] (both spellings of the format).
TARTAN_NAME_MAP = {"wall": [1], "door": 4, "floor": 2, "ceiling": [3], "chair": 5, "table": [6],
                   "sofa": 7, "cabinet": 8, "bed": [9], "rock": [11]}  # fmt: skip
TARTAN_PALETTE_ROWS = 13  # rows 0..12; RayFronts reads rows 1..11
TARTAN_CLASSES = tuple(sorted(TARTAN_NAME_MAP))


def tartan_value(row: int) -> int:
    """The segmentation image's value of palette row ``row`` (the third column)."""
    return 7 + 19 * row


#: One flat colour per class name (4 levels per channel, >= 85 apart).
_NAMES = sorted({n for _, n in REPLICA_OF_RAW.values()} | set(TARTAN_CLASSES))
COLOURS = {n: NYU40_COLOURS[i + 1] for i, n in enumerate(_NAMES)}
NAME_OF_RAW = {raw: name for raw, (_, name) in REPLICA_OF_RAW.items()}


@dataclass
class Scene:
    """The room, its camera and the rendered frames (depth metres, raw ids, poses)."""

    room: SyntheticRoom
    k: np.ndarray
    size: tuple[int, int]
    depth: list[np.ndarray]
    raw: list[np.ndarray]
    poses: list[np.ndarray]

    def colour(self, i: int) -> np.ndarray:
        out = np.zeros((*self.size, 3), dtype=np.uint8)
        for raw, name in NAME_OF_RAW.items():
            out[self.raw[i] == raw] = COLOURS[name]
        return out


def render(k: np.ndarray, size=(24, 32), frames: int = 6, room_size=(7.0, 5.0, 2.5)) -> Scene:
    room = SyntheticRoom(size=room_size, image_size=size, frames=frames, bad_pose_frame=None)
    poses = [room.pose(i) for i in range(frames)]
    depth, raw = zip(*(ray_cast(room.boxes, k, p, size) for p in poses), strict=True)
    return Scene(room, k, size, list(depth), list(raw), poses)


def pose_text(pose: np.ndarray) -> str:
    return " ".join(f"{v:.17g}" for v in pose.reshape(-1))


def write_info_semantic(path: Path, classes: dict[int, str] = REPLICA_CLASSES) -> None:
    path.parent.mkdir(parents=True, exist_ok=True)
    info = {"classes": [{"id": i, "name": n} for i, n in classes.items()],
            "objects": [], "id_to_label": []}  # fmt: skip
    path.write_text(json.dumps(info))


# ------------------------------------------------------------------ NICE-SLAM Replica
NICE_SCALE = 6553.5


def nice_k(size=(24, 32)) -> np.ndarray:
    h, w = size
    return np.array([[20.0, 0, (w - 1) / 2], [0, 20.0, (h - 1) / 2], [0, 0, 1]])


def write_nice_replica(root: Path, scene: Scene, name: str = "office0") -> None:
    """``cam_params.json``, ``<name>/traj.txt`` and ``<name>/results/`` (JPEG colour, uint16
    depth at ``NICE_SCALE``), the class list under ``semantic_info/office_0/``."""
    h, w = scene.size
    k = scene.k
    cam = {"camera": {"w": w, "h": h, "fx": k[0, 0], "fy": k[1, 1], "cx": k[0, 2],
                      "cy": k[1, 2], "scale": NICE_SCALE}}  # fmt: skip
    root.mkdir(parents=True, exist_ok=True)
    (root / "cam_params.json").write_text(json.dumps(cam))
    results = root / name / "results"
    results.mkdir(parents=True)
    (root / name / "traj.txt").write_text("".join(pose_text(p) + "\n" for p in scene.poses))
    for i in range(len(scene.poses)):
        Image.fromarray(scene.colour(i)).save(results / f"frame{i:06d}.jpg", quality=100,
                                              subsampling=0)  # fmt: skip
        depth = np.round(scene.depth[i] * NICE_SCALE).astype(np.uint16)
        Image.fromarray(depth).save(results / f"depth{i:06d}.png")
    write_info_semantic(root / "semantic_info" / (name[:-1] + "_" + name[-1]) / "info_semantic.json")


def write_hovsg_gt(path: Path, scene: Scene, step: float = 0.1) -> None:
    """HOV-SG's labelled points of the room as RayFronts reads them: ``semseg_gt_xyz``
    ``[N, 3]`` float64 and ``semseg_gt_label`` ``[N]`` float64 Replica class ids (0: no
    class), points on a grid over every box face (as HOV-SG repeats the mesh's face
    vertices)."""
    xyz, ids = [], []
    for box in scene.room.boxes:
        lo, hi = np.asarray(box.lo), np.asarray(box.hi)
        for axis in range(3):
            for side in (lo[axis], hi[axis]):
                others = [a for a in range(3) if a != axis]
                grids = [np.arange(lo[a], hi[a] + 1e-9, step) for a in others]
                u, v = np.meshgrid(*grids, indexing="ij")
                p = np.zeros((u.size, 3))
                p[:, axis] = side
                p[:, others[0]], p[:, others[1]] = u.ravel(), v.ravel()
                xyz.append(p)
                ids.append(np.full(u.size, REPLICA_OF_RAW[box.raw_id][0], dtype=np.float64))
    path.parent.mkdir(parents=True, exist_ok=True)
    torch.save({"semseg_gt_xyz": torch.from_numpy(np.concatenate(xyz)),
                "semseg_gt_label": torch.from_numpy(np.concatenate(ids))}, path)  # fmt: skip


# ------------------------------------------------------------------ Semantic-NeRF Replica
def semnerf_k(size) -> np.ndarray:
    h, w = size
    return np.array([[w / 2, 0, w / 2], [0, w / 2, h / 2], [0, 0, 1]])


def write_semnerf_replica(root: Path, scene: Scene, name: str = "office_0") -> None:
    """``<name>/Sequence_1/`` (traj_w_c.txt, rgb/rgb_i.png, depth/depth_i.png uint16 mm,
    semantic_class/semantic_class_i.png uint8 class ids) and ``semantic_info/<name>/``."""
    seq = root / name / "Sequence_1"
    for sub in ("rgb", "depth", "semantic_class"):
        (seq / sub).mkdir(parents=True)
    (seq / "traj_w_c.txt").write_text("".join(pose_text(p) + "\n" for p in scene.poses))
    lut = np.zeros(64, dtype=np.uint8)
    for raw, (cid, _) in REPLICA_OF_RAW.items():
        lut[raw] = cid
    for i in range(len(scene.poses)):
        Image.fromarray(scene.colour(i)).save(seq / "rgb" / f"rgb_{i}.png")
        depth = np.round(scene.depth[i] * 1000).astype(np.uint16)
        Image.fromarray(depth).save(seq / "depth" / f"depth_{i}.png")
        Image.fromarray(lut[scene.raw[i]]).save(seq / "semantic_class" / f"semantic_class_{i}.png")
    write_info_semantic(root / "semantic_info" / name / "info_semantic.json")


# ------------------------------------------------------------------ TartanAir v2
#: FRD camera axes -> RDF (OpenCV) axes, written independently of the reader's constant.
_P = np.zeros((4, 4))
_P[0, 1] = _P[1, 2] = _P[2, 0] = _P[3, 3] = 1.0


def ned_line(pose: np.ndarray) -> str:
    """The ``tx ty tz qx qy qz qw`` line whose reading is ``pose`` (OpenCV camera in the world
    taken as RDF): the FRD camera in the NED world is ``P^T pose P``."""
    ned = _P.T @ pose @ _P
    q = Rotation.from_matrix(ned[:3, :3]).as_quat()  # x, y, z, w
    return " ".join(f"{v:.17g}" for v in (*ned[:3, 3], *q))


def float_depth_png(depth: np.ndarray, path: Path) -> None:
    """TartanAir's depth PNG: the float32 bytes as 8-bit RGBA, in OpenCV's BGRA memory order
    (what ``cv2.imwrite`` of ``depth.view(uint8)`` writes: PNG R = byte 2, B = byte 0)."""
    b = depth.astype("<f4").view(np.uint8).reshape(*depth.shape, 4)
    Image.fromarray(np.ascontiguousarray(b[..., [2, 1, 0, 3]]), "RGBA").save(path)


def write_tartanair(root: Path, scene: Scene, name: str = "Factory", sky: bool = True) -> None:
    """``seg_rgbs.txt``, ``<name>/seg_label_clean.json`` and ``<name>/Data_ground/P0000/``."""
    root.mkdir(parents=True, exist_ok=True)
    if not (root / "seg_rgbs.txt").exists():
        rows = [f"{(3 * r) % 256},{(5 * r) % 256},{tartan_value(r)}"
                for r in range(TARTAN_PALETTE_ROWS)]  # fmt: skip
        (root / "seg_rgbs.txt").write_text("\n".join(rows) + "\n")
    (root / name).mkdir()
    (root / name / "seg_label_clean.json").write_text(json.dumps({"name_map": TARTAN_NAME_MAP}))
    seq = root / name / "Data_ground" / "P0000"
    for sub in ("image_lcam_front", "depth_lcam_front", "seg_lcam_front"):
        (seq / sub).mkdir(parents=True)
    (seq / "pose_lcam_front.txt").write_text("".join(ned_line(p) + "\n" for p in scene.poses))
    lut = np.zeros(64, dtype=np.uint8)
    for raw, row in TARTAN_ROW_OF_RAW.items():
        lut[raw] = tartan_value(row)
    for i in range(len(scene.poses)):
        Image.fromarray(scene.colour(i)).save(seq / "image_lcam_front" / f"{i:06d}_lcam_front.png")
        depth = scene.depth[i].astype(np.float32)
        if sky and i == 0:  # a "sky" pixel beyond the 100 m cutoff
            depth = depth.copy()
            depth[0, 0] = 500.0
        float_depth_png(depth, seq / "depth_lcam_front" / f"{i:06d}_lcam_front_depth.png")
        Image.fromarray(lut[scene.raw[i]]).save(seq / "seg_lcam_front" / f"{i:06d}_lcam_front_seg.png")
