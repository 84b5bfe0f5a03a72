"""Pascal Context val in the converted layout the OVSS projects read (``dataset=pc60``,
``dataset=pc59``; kind ``pascal_context``), and the conversion that writes it.

``<path>`` is ``VOCdevkit/VOC2010``: ``ImageSets/SegmentationContext/<split>.txt`` lists the ids
(5,105 for val), ``JPEGImages/<id>.jpg`` the images, ``SegmentationClassContext/<id>.png`` the
labels: 0 = background and 1..59 the 59 classes in the converter's order (the 459-class ids of
``trainval_merged.json`` sorted, hence alphabetical: aeroplane, bag, bed, ..., wood), as mmseg's
``PascalContextDataset`` and the peers' ``PascalContext60Dataset`` / ``PascalContext59Dataset``
read them. PC60 scores the 60 classes; PC59 (``reduce_zero_label: true``) ignores background.

The conversion (mmsegmentation ``tools/dataset_converters/pascal_context.py``, which uses the
PASCAL in Detail API): for every image of a phase of ``trainval_merged.json``, start from zeros
and paint each of its segmentation annotations (COCO run-length masks, in the file's order) with
its category id, then map the 60 ids the benchmark keeps (0 and 59 category ids) to 0..59 by
their sorted order; a pixel of any other id is an error, as mmseg's assertion. This module runs it
with pycocotools' RLE decoder (the Detail API's is the same code, forked from the COCO API)::

    python -m resireg_train.data.context VOCdevkit            # reads VOC2010/trainval_merged.json
    python -m resireg_train.data.context VOCdevkit --json trainval_merged.json --phases val

It writes ``VOC2010/SegmentationClassContext/<id>.png`` and
``VOC2010/ImageSets/SegmentationContext/<phase>.txt`` (ids sorted), what mmseg's script writes.
"""

from __future__ import annotations

import argparse
import json
import sys
from collections.abc import Mapping, Sequence
from pathlib import Path
from typing import Any

import numpy as np
from PIL import Image

from resireg_train.data.folders import benchmark_set, class_names_of, listed_pairs, root_of

__all__ = [
    "CONTEXT_CATEGORY_IDS",
    "check_context_source",
    "context_label",
    "context_source",
    "convert_context",
    "main",
]

#: The 459-class ids Pascal Context's 60-class benchmark keeps (0 = background first), sorted:
#: label ``i`` is the ``i``-th (mmsegmentation ``tools/dataset_converters/pascal_context.py``
#: ``_mapping``, the same 60 ids).
CONTEXT_CATEGORY_IDS: tuple[int, ...] = tuple(sorted((
    0, 2, 259, 260, 415, 324, 9, 258, 144, 18, 19, 22, 23, 397, 25, 284, 158, 159, 416, 33, 162,
    420, 454, 295, 296, 427, 44, 45, 46, 308, 59, 440, 445, 31, 232, 65, 354, 424, 68, 326, 72,
    458, 34, 207, 80, 355, 85, 347, 220, 349, 360, 98, 187, 104, 105, 366, 189, 368, 113, 115,
)))  # fmt: skip
_LAYOUT = ("VOCdevkit/VOC2010 with JPEGImages/, SegmentationClassContext/ and "
           "ImageSets/SegmentationContext/ (python -m resireg_train.data.context writes the last "
           "two from trainval_merged.json)")  # fmt: skip
_SOURCE = "conf/dataset/pc60.yaml"


def _pairs(spec: Mapping[str, Any], key: str) -> list[tuple[Path, Path]]:
    root = root_of(spec, key, _LAYOUT, _SOURCE)
    return listed_pairs(root, spec, key, "ImageSets/SegmentationContext", "JPEGImages",
                        "SegmentationClassContext")  # fmt: skip


def _count(spec: Mapping[str, Any]) -> tuple[int, str]:
    reduce = bool(spec["reduce_zero_label"])
    return len(CONTEXT_CATEGORY_IDS) - reduce, f"Context labels with reduce_zero_label={reduce}"


def check_context_source(spec: Mapping[str, Any], key: str = "dataset") -> None:
    """The ``pascal_context`` build's checks that need no model (the folder, list, label folder,
    every listed file, the class-name file's count)."""
    _pairs(spec, key)
    class_names_of(spec, key, *_count(spec))


def context_source(name: str, spec: Mapping[str, Any], key: str, common: dict) -> Any:
    """The ``pascal_context`` kind (module docstring)."""
    pairs = _pairs(spec, key)
    classes, names = class_names_of(spec, key, *_count(spec))
    return benchmark_set(name, pairs, classes, names, common,
                         reduce_zero_label=bool(spec["reduce_zero_label"]))  # fmt: skip


# ------------------------------------------------------------------------------ conversion
def _decode(rle: Mapping[str, Any]) -> np.ndarray:
    """A COCO run-length mask (compressed, or uncompressed ``counts`` list) -> ``[H, W]``."""
    from pycocotools import mask as coco_mask

    if isinstance(rle.get("counts"), list):  # uncompressed: frPyObjects compresses it
        h, w = rle["size"]
        rle = coco_mask.frPyObjects(dict(rle), h, w)
    elif isinstance(rle.get("counts"), str):
        rle = {**rle, "counts": rle["counts"].encode("ascii")}
    return coco_mask.decode(rle)


def context_label(image: Mapping[str, Any], annotations: Sequence[Mapping[str, Any]]) -> np.ndarray:
    """The 60-class label map (uint8, 0..59) of one ``trainval_merged.json`` image: its
    ``annotations`` (``annos_segmentation`` entries of the image, in the file's order) painted
    with their category ids over zeros (Detail's ``getMask``), then each kept id replaced by its
    rank in :data:`CONTEXT_CATEGORY_IDS` (mmseg's ``np.digitize(..., right=True)``); a ValueError
    names the image and any id the benchmark does not keep."""
    mask = np.zeros((int(image["height"]), int(image["width"])), dtype=np.int64)
    for ann in annotations:
        mask[_decode(ann["segmentation"]) != 0] = int(ann["category_id"])
    ids = np.asarray(CONTEXT_CATEGORY_IDS)
    index = np.searchsorted(ids, mask)  # == np.digitize(mask, ids, right=True)
    bad = np.unique(mask[(index >= len(ids)) | (ids[np.minimum(index, len(ids) - 1)] != mask)])
    if bad.size:
        raise ValueError(f"{image.get('file_name')}: category ids {bad.tolist()[:5]} are not "
                         "among the 60 Pascal Context keeps")  # fmt: skip
    return index.astype(np.uint8)


def convert_context(
    devkit: str | Path,
    json_path: str | Path | None = None,
    phases: Sequence[str] = ("train", "val"),
) -> dict[str, int]:
    """Write ``VOC2010/SegmentationClassContext/<id>.png`` and
    ``VOC2010/ImageSets/SegmentationContext/<phase>.txt`` under ``devkit`` (``VOCdevkit``) from
    ``json_path`` (default ``VOC2010/trainval_merged.json``); returns the images per phase."""
    root = Path(devkit).expanduser() / "VOC2010"
    source = Path(json_path).expanduser() if json_path else root / "trainval_merged.json"
    if not source.is_file():
        raise FileNotFoundError(f"no {source} (Pascal Context's trainval_merged.json; pass --json)")
    data = json.loads(source.read_text())
    by_image: dict[Any, list[Mapping[str, Any]]] = {}
    for ann in data["annos_segmentation"]:
        by_image.setdefault(ann["image_id"], []).append(ann)
    out = root / "SegmentationClassContext"
    lists = root / "ImageSets" / "SegmentationContext"
    out.mkdir(parents=True, exist_ok=True)
    lists.mkdir(parents=True, exist_ok=True)
    counts = {}
    for phase in phases:
        written = []
        for image in data["images"]:
            if image.get("phase") != phase:
                continue
            stem = Path(image["file_name"]).stem
            label = context_label(image, by_image.get(image["image_id"], []))
            Image.fromarray(label).save(out / f"{stem}.png")
            written.append(stem)
        (lists / f"{phase}.txt").write_text("".join(f"{s}\n" for s in sorted(written)))
        counts[phase] = len(written)
    return counts


def main(argv: Sequence[str] | None = None) -> int:
    parser = argparse.ArgumentParser(
        prog="python -m resireg_train.data.context",
        description="Convert Pascal Context's trainval_merged.json to the 60-class label maps the "
        "OVSS benchmarks read (VOC2010/SegmentationClassContext, ImageSets/SegmentationContext).",
    )
    parser.add_argument("devkit", help="the VOCdevkit folder (holding VOC2010/)")
    parser.add_argument(
        "--json", default=None, help="default: VOCdevkit/VOC2010/trainval_merged.json"
    )
    parser.add_argument("--phases", nargs="+", default=["train", "val"])
    args = parser.parse_args(argv)
    try:
        counts = convert_context(args.devkit, args.json, args.phases)
    except (FileNotFoundError, ValueError, KeyError) as err:
        print(f"error: {err}", file=sys.stderr)
        return 2
    print(", ".join(f"{phase}: {n} images" for phase, n in counts.items()))
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
