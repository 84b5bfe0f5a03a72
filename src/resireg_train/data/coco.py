"""COCO-Stuff 164k val and COCO-Object val as downloaded and converted (kinds ``coco_stuff``,
``coco_object``; ``dataset=coco_stuff``, ``dataset=coco_object``).

``<path>`` is ``coco_stuff164k``: ``images/<split>/<stem>.jpg`` (``val2017``: 5,000 images) and,
in ``annotations/<split>/``, the raw ``stuffthingmaps`` (``<stem>.png``: COCO's 182 ids minus one,
0..181, 255 unlabelled) beside the converted maps:

- COCO-Stuff (171 classes): mmseg's ``tools/dataset_converters/coco_stuff164k.py`` writes
  ``<stem>_labelTrainIds.png``, the 171 ids COCO uses renumbered 0..170 in order (the 11 ids it
  never assigns, :data:`UNUSED_IDS`, dropped) and 255 kept. ``labels: converted`` reads them;
  ``labels: raw`` maps ``<stem>.png`` the same way on read (:data:`STUFF_TRAIN_IDS`).
- COCO-Object (81 classes: background + the 80 things): the OVSS projects' converter
  (``datasets/cvt_coco_object.py`` of SCLIP, NACLIP, SC-CLIP, ProxyCLIP, after GroupViT and TCL)
  maps the raw maps' thing ids (0..90) to their train id + 1 (1..80), the stuff ids (91..181) and
  255 (unlabelled) to 0 (background), written as ``<stem>_instanceTrainIds.png``. ``labels: raw``
  derives it on read (:data:`OBJECT_IDS`); ``labels: converted`` reads the written files.

An id COCO never assigns (:data:`UNUSED_IDS`) becomes 255 (ignored) in both mappings here; the
converters leave such a pixel's raw value, which no map holds. Images are the split's ``*.jpg``
sorted by name, as mmseg lists them.
"""

from __future__ import annotations

from collections.abc import Mapping
from pathlib import Path
from typing import Any

import numpy as np
from PIL import Image

from resireg_train.data.folders import (
    benchmark_set,
    class_names_of,
    missing_files,
    require_folder,
    root_of,
)

__all__ = [
    "OBJECT_IDS",
    "STUFF_TRAIN_IDS",
    "UNUSED_IDS",
    "check_coco_source",
    "coco_object_source",
    "coco_stuff_source",
]

#: The raw maps' ids (COCO category id - 1) COCO never assigns: 12 street sign, 26 hat, 29 shoe,
#: 30 eye glasses, 45 plate, 66 mirror, 68 window, 69 desk, 71 door, 83 blender, 91 hair brush
#: (COCO ids); the keys mmseg's ``clsID_to_trID`` skips.
UNUSED_IDS: tuple[int, ...] = (11, 25, 28, 29, 44, 65, 67, 68, 70, 82, 90)
#: The raw maps' last thing id: 0..90 are things (80 used), 91..181 stuff (91).
_LAST_THING = 90
_USED = tuple(i for i in range(182) if i not in UNUSED_IDS)


def _table(values: dict[int, int], rest: int) -> np.ndarray:
    lut = np.full(256, rest, dtype=np.uint8)
    for raw, target in values.items():
        lut[raw] = target
    return lut


#: Raw id -> COCO-Stuff train id (``lut[raw]``, 256 entries): the used ids renumbered 0..170 in
#: order, 255 and the unused ids -> 255 (mmseg ``coco_stuff164k.py``'s ``clsID_to_trID``).
STUFF_TRAIN_IDS: np.ndarray = _table({raw: i for i, raw in enumerate(_USED)}, 255)
#: Raw id -> COCO-Object label: a thing's train id + 1 (1..80), stuff and 255 -> 0, unused -> 255
#: (``cvt_coco_object.py``: ``v + 1``, then ``k > 90 -> 0``).
OBJECT_IDS: np.ndarray = _table(
    {**{raw: i + 1 for i, raw in enumerate(_USED) if raw <= _LAST_THING},
     **{raw: 0 for raw in _USED if raw > _LAST_THING}, 255: 0},
    255,
)  # fmt: skip

_LAYOUT = ("coco_stuff164k with images/<split>/*.jpg and annotations/<split>/ (stuffthingmaps "
           "<stem>.png and mmseg's converted <stem>_labelTrainIds.png)")  # fmt: skip
_KINDS = {
    # kind: (converted suffix, raw id table, classes, converter)
    "coco_stuff": ("_labelTrainIds.png", STUFF_TRAIN_IDS, 171,
                   "run mmsegmentation's tools/dataset_converters/coco_stuff164k.py, or set "
                   "labels=raw (the 182 -> 171 mapping on read)"),
    "coco_object": ("_instanceTrainIds.png", OBJECT_IDS, 81,
                    "run the OVSS projects' datasets/cvt_coco_object.py, or set labels=raw "
                    "(derived on read)"),
}  # fmt: skip


def _pairs(spec: Mapping[str, Any], key: str) -> list[tuple[Path, Path]]:
    """``(image, label)`` of every ``images/<split>/*.jpg``, sorted, with its label file."""
    root = root_of(spec, key, _LAYOUT, f"conf/dataset/{spec.get('kind')}.yaml")
    split = str(spec["split"])
    images = require_folder(root / "images" / split, key, spec, f"the {split} images, *.jpg")
    labels = require_folder(root / "annotations" / split, key, spec,
                            f"the {split} label maps")  # fmt: skip
    files = sorted(p for p in images.iterdir() if p.suffix.lower() == ".jpg")
    if not files:
        raise FileNotFoundError(f"{key}.path={spec['path']!r}: no .jpg image in {images}")
    suffix, _, _, fix = _KINDS[str(spec["kind"])]
    converted = str(spec["labels"]) == "converted"
    pairs = [(f, labels / (f"{f.stem}{suffix}" if converted else f"{f.stem}.png")) for f in files]
    what = f"{suffix} label maps" if converted else "raw label maps (<stem>.png)"
    missing_files([p[1] for p in pairs], key, spec, what, fix if converted else "")
    return pairs


def check_coco_source(spec: Mapping[str, Any], key: str = "dataset") -> None:
    """The ``coco_stuff`` / ``coco_object`` build's checks that need no model (the folders,
    every image's label file, the class-name file's count)."""
    _pairs(spec, key)
    count = _KINDS[str(spec["kind"])][2]
    class_names_of(spec, key, count, f"{spec['kind']} labels")


def _source(name: str, spec: Mapping[str, Any], key: str, common: dict) -> Any:
    kind = str(spec["kind"])
    pairs = _pairs(spec, key)
    _, table, count, _ = _KINDS[kind]
    classes, names = class_names_of(spec, key, count, f"{kind} labels")
    read = None
    if str(spec["labels"]) == "raw":

        def read(path: Path) -> np.ndarray:
            with Image.open(path) as image:
                raw = np.asarray(image)
            if raw.ndim != 2:  # left as stored: the set reports it (not a class-id map)
                return raw
            return table[raw.astype(np.uint8, copy=False)]

    return benchmark_set(name, pairs, classes, names, common, read_label=read)


def coco_stuff_source(name: str, spec: Mapping[str, Any], key: str, common: dict) -> Any:
    """The ``coco_stuff`` kind (module docstring)."""
    return _source(name, spec, key, common)


def coco_object_source(name: str, spec: Mapping[str, Any], key: str, common: dict) -> Any:
    """The ``coco_object`` kind (module docstring)."""
    return _source(name, spec, key, common)
