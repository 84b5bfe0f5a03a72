"""The 3D protocol's choices side by side (docs/protocol.md section 4): mIoU / f-mIoU of one set
of predictions on the synthetic ScanNet-format rooms under the default protocol
(``conf/dataset/scannet.yaml``, RayFronts' ``scripts/semseg_eval.py``), each alternative alone,
RayFronts' configs' settings together, and this project's earlier protocol
(``conf/dataset/scannet_legacy.yaml``), in one run.

Setting. Two rooms (``resireg_train.data.scannet_room``, ``--world nyu40``: ScanNet's class
names, flat colours), 160 x 212 frames rendered and resized to 212 x 282 (the 4/3 of ScanNet's 480 x
640 -> 640 x 864), frame skip 0, voxel 0.1 m (the rooms are 4 m across). The encoder, unless
``--model-path`` names an export of ours: a colour oracle on a coarse grid (8 x 8-pixel patches:
each patch's mean colour, nearest class colour, one-hot features; the class names as one-hot
text), so the predictions are right inside objects and wrong along their edges, as a real model's
coarse features are; a model-free, deterministic input, enough to show what each choice changes.
Scores are of ``bb`` (the encoder's own features).

    python benchmarks/protocol_3d.py [--model-path EXPORT] [--world nyu40|smoke]
"""

from __future__ import annotations

import argparse
import tempfile
import time
from collections.abc import Sequence
from pathlib import Path
from typing import Any

import torch
import torch.nn.functional as F
import yaml

from resireg.method.variants import build_variants
from resireg.models.interface import DenseEncoder, DenseOutput, InputRule
from resireg.ovss import NYU40_CLASSES
from resireg_train.data.scannet import READER_KEYS, ScanNetFrames
from resireg_train.data.scannet_room import NYU40_COLOURS, Box, SyntheticRoom, write_scene
from resireg_train.evaluation.mapping.engine import TASK_KEYS, MappingEngine, MappingSettings

CONF = Path(__file__).resolve().parents[1] / "conf" / "dataset"
SCENES = ("synthetic0000_00", "synthetic0001_00")
RENDER, IMAGE, VOXEL = (160, 212), (212, 282), 0.1

#: (row label, overrides of the default protocol); "legacy": scannet_legacy.yaml's keys.
ROWS: tuple[tuple[str, dict[str, Any]], ...] = (
    ("default (rayfronts_semseg_eval)", {}),
    ("metric: union", {"metric": "union"}),
    ("gt_unlabelled: vote", {"gt_unlabelled": "vote"}),
    ("gt_unlabelled: drop", {"gt_unlabelled": "drop"}),
    ("points: pixel", {"points": "pixel"}),
    ("lattice: floor", {"lattice": "floor"}),
    ("resize: exact", {"resize": "exact"}),
    ("intrinsics: half_pixel", {"intrinsics": "half_pixel"}),
    ("gt_resolution: label", {"gt_resolution": "label"}),
    ("knn: 5", {"knn": 5}),
    ("knn: 0 (same voxel)", {"knn": 0}),
    ("prediction_threshold: 0.1", {"prediction_threshold": 0.1}),
    ("RayFronts' configs: knn 5, threshold 0.1, denoising 0.5",
     {"knn": 5, "prediction_threshold": 0.1, "prompt_denoising": 0.5}),
    ("classes_to_ignore: RayFronts' default (32 classes)",
     {"classes_to_ignore": ["otherprop", "otherstructure", "otherfurniture", "wall", "floor",
                            "ceiling", "door", "window"]}),
    ("class_names: nyu40", {"class_names": "nyu40"}),
    ("this project's earlier protocol (scannet_legacy)", "legacy"),  # type: ignore[arg-type]
)  # fmt: skip


class CoarseColourOracle(DenseEncoder):
    """Per 8 x 8 patch: the class whose colour (:data:`NYU40_COLOURS`) is nearest to the patch's
    mean colour, as one-hot features over NYU40's 40 names; text: the one-hot of the NYU40 name
    a prompt holds (the longest that matches)."""

    def __init__(self) -> None:
        super().__init__()
        self.anchor = torch.nn.Parameter(torch.zeros(1))
        self.register_buffer("palette", torch.tensor(NYU40_COLOURS[1:41], dtype=torch.float32))

    @property
    def input_rule(self) -> InputRule:
        return InputRule(8, (0.0, 0.0, 0.0), (1.0, 1.0, 1.0))

    def encode(self, images):
        b, _, h, w = images.shape
        mean = F.avg_pool2d(images * 255, 8).permute(0, 2, 3, 1)  # [B, h/8, w/8, 3]
        cls = torch.cdist(mean.reshape(-1, 3), self.palette).argmin(1).reshape(b, h // 8, w // 8)
        onehot = F.one_hot(cls, 40).float().permute(0, 3, 1, 2)
        return DenseOutput(onehot, onehot, None)

    def encode_text(self, texts):
        out = torch.zeros(len(texts), 40)
        for i, text in enumerate(texts):
            hits = [c for c in NYU40_CLASSES if c in text]
            out[i, NYU40_CLASSES.index(max(hits, key=len))] = 1.0
        return out


def write_rooms(root: Path, world: str) -> None:
    """The two rooms of the module docstring."""
    room = SyntheticRoom(image_size=RENDER, focal=100.0, frames=16, bad_pose_frame=None)
    write_scene(root, SCENES[0], room, world=world)
    other = SyntheticRoom(size=(3.6, 3.4, 2.6), image_size=RENDER, focal=100.0, frames=12,
                          bad_pose_frame=None, objects=[
        Box((0.4, 2.0, 0.0), (1.8, 3.2, 0.5), 11), Box((2.2, 0.3, 0.0), (3.0, 0.9, 0.8), 4),
        Box((2.4, 1.0, 0.0), (2.8, 1.4, 0.9), 2), Box((0.1, 0.2, 0.0), (0.6, 1.0, 1.8), 7),
        Box((2.7, 2.2, 0.0), (3.3, 2.8, 1.0), 35), Box((1.2, 3.37, 0.0), (2.1, 3.4, 2.0), 5),
    ])  # fmt: skip
    write_scene(root, SCENES[1], other, world=world)


def settings_of(row: dict[str, Any] | str) -> dict[str, Any]:
    """The dataset keys of a row: scannet.yaml with the row's overrides (or the legacy file's)."""
    spec = yaml.safe_load((CONF / "scannet.yaml").read_text())
    if row == "legacy":
        legacy = yaml.safe_load((CONF / "scannet_legacy.yaml").read_text())
        return {**spec, **{k: v for k, v in legacy.items() if k != "defaults"}}
    return {**spec, **row}


def score(root: Path, spec: dict[str, Any], encoder: DenseEncoder) -> dict[str, float]:
    reader = {k: spec[k] for k in READER_KEYS if k in spec and k not in ("label_map", "limit")}
    reader.update(frame_skip=0, image_size=IMAGE, short_side=None)
    if isinstance(reader.get("gt_resolution"), list):
        reader["gt_resolution"] = tuple(reader["gt_resolution"])
    frames = ScanNetFrames(root, SCENES, patch_size=encoder.input_rule.patch_size, **reader)
    protocol = MappingSettings.from_spec({**{k: spec[k] for k in TASK_KEYS}, "voxel_size": VOXEL})
    result = MappingEngine(frames, batch_size=4, protocol=protocol).run(
        encoder, build_variants(["bb"])
    )
    s = result.scores()
    p = "val/scannet3d/scannet"
    per_scene = result.per_scene()
    return {
        "miou": s[f"{p}/miou_bb"], "fmiou": s[f"{p}/fmiou_bb"],
        "pooled_miou": s[f"{p}/pooled_miou_bb"], "pooled_fmiou": s[f"{p}/pooled_fmiou_bb"],
        "gt_voxels": sum(v["gt_voxels"] for v in per_scene.values()),
        "feature_voxels": sum(v["scores"]["bb"]["voxels"] for v in per_scene.values()),
        "classes": len(frames.classes),
    }  # fmt: skip


def main(argv: Sequence[str] | None = None) -> list[tuple[str, dict[str, float]]]:
    parser = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    parser.add_argument("--model-path", default=None, help="an export of ours (default: oracle)")
    parser.add_argument("--world", choices=("nyu40", "smoke"), default=None,
                        help="the rooms' world (default: nyu40 for the oracle, smoke for a model)")  # fmt: skip
    args = parser.parse_args(argv)
    torch.manual_seed(0)
    if args.model_path:
        from resireg.models import ResiregVLM

        encoder: DenseEncoder = ResiregVLM.from_pretrained(args.model_path)
    else:
        encoder = CoarseColourOracle()
    world = args.world or ("smoke" if args.model_path else "nyu40")
    rows = []
    with tempfile.TemporaryDirectory() as tmp:
        write_rooms(Path(tmp), world)
        start = time.perf_counter()
        for label, row in ROWS:
            rows.append((label, score(Path(tmp), settings_of(row), encoder)))
        seconds = time.perf_counter() - start
    name = args.model_path or "coarse colour oracle (8 px patches)"
    print(f"3D protocol choices: {name}, world {world}, rooms {', '.join(SCENES)} "
          f"({RENDER[0]}x{RENDER[1]} -> {IMAGE[0]}x{IMAGE[1]}), voxel {VOXEL} m; x100; "
          f"mIoU / f-mIoU = mean over the 2 scenes, pooled = one confusion over both ({seconds:.0f} s)")  # fmt: skip
    print()
    print(
        "| protocol | mIoU | f-mIoU | pooled mIoU | pooled f-mIoU | GT voxels | feature voxels | classes |"
    )
    print("|---|---:|---:|---:|---:|---:|---:|---:|")
    for label, r in rows:
        print(f"| {label} | {100 * r['miou']:.1f} | {100 * r['fmiou']:.1f} | "
              f"{100 * r['pooled_miou']:.1f} | {100 * r['pooled_fmiou']:.1f} | "
              f"{r['gt_voxels']:,} | {r['feature_voxels']:,} | {r['classes']} |")  # fmt: skip
    return rows


if __name__ == "__main__":
    main()
