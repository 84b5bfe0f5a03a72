"""Cityscapes val as downloaded (kind ``cityscapes``; ``dataset=cityscapes``): 19 classes.

``<path>`` is ``cityscapes``: ``leftImg8bit/<split>/<city>/<stem>_leftImg8bit.png`` (500 val
images) and ``gtFine/<split>/<city>/<stem>_gtFine_*.png``. ``labels: converted`` reads
``<stem>_gtFine_labelTrainIds.png`` (cityscapesScripts' ``createTrainIdLabelImgs``, run by mmseg's
``tools/dataset_converters/cityscapes.py``: the 19 train ids, 255 ignored), as mmseg's
``CityscapesDataset`` does; ``labels: raw`` reads the downloaded ``<stem>_gtFine_labelIds.png``
(ids 0..33) and maps each id to its train id (:data:`TRAIN_IDS`, cityscapesScripts
``helpers/labels.py``; every id without one, and any other value, to 255).
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

__all__ = ["LABEL_TRAIN_IDS", "TRAIN_IDS", "check_cityscapes_source", "cityscapes_source"]

#: label id -> train id of cityscapesScripts ``helpers/labels.py`` for the ids with one (road 7
#: -> 0 ... bicycle 33 -> 18); the others (unlabeled, ego vehicle, ..., parking, rail track,
#: guard rail, bridge, tunnel, polegroup, caravan, trailer, license plate) have 255.
TRAIN_IDS: dict[int, int] = {
    7: 0, 8: 1, 11: 2, 12: 3, 13: 4, 17: 5, 19: 6, 20: 7, 21: 8, 22: 9, 23: 10, 24: 11, 25: 12,
    26: 13, 27: 14, 28: 15, 31: 16, 32: 17, 33: 18,
}  # fmt: skip
#: The same as a 256-entry table (``lut[label_id]``), 255 elsewhere.
LABEL_TRAIN_IDS = np.full(256, 255, dtype=np.uint8)
for _id, _train in TRAIN_IDS.items():
    LABEL_TRAIN_IDS[_id] = _train

_CLASSES = 19
_IMAGE = "_leftImg8bit.png"
_LABEL = {"converted": "_gtFine_labelTrainIds.png", "raw": "_gtFine_labelIds.png"}
_LAYOUT = "cityscapes with leftImg8bit/<split>/<city>/ and gtFine/<split>/<city>/"


def _pairs(spec: Mapping[str, Any], key: str) -> list[tuple[Path, Path]]:
    """``(image, label)`` of every ``leftImg8bit/<split>/<city>/*_leftImg8bit.png``, sorted."""
    root = root_of(spec, key, _LAYOUT, "conf/dataset/cityscapes.yaml")
    split = str(spec["split"])
    images = require_folder(root / "leftImg8bit" / split, key, spec,
                            "the images, <city>/<stem>_leftImg8bit.png")  # fmt: skip
    labels = require_folder(root / "gtFine" / split, key, spec,
                            "the fine labels, <city>/<stem>_gtFine_*.png")  # fmt: skip
    files = sorted(images.glob(f"*/*{_IMAGE}"))
    if not files:
        raise FileNotFoundError(f"{key}.path={spec['path']!r}: no <city>/*{_IMAGE} in {images}")
    suffix = _LABEL[str(spec["labels"])]
    pairs = [(f, labels / f.parent.name / f"{f.name.removesuffix(_IMAGE)}{suffix}") for f in files]
    fix = ("run cityscapesScripts' createTrainIdLabelImgs (mmseg's tools/dataset_converters/"
           "cityscapes.py), or set labels=raw (label ids mapped on read)")  # fmt: skip
    missing_files([p[1] for p in pairs], key, spec, f"*{suffix} label maps",
                  fix if spec["labels"] == "converted" else "")  # fmt: skip
    return pairs


def check_cityscapes_source(spec: Mapping[str, Any], key: str = "dataset") -> None:
    """The ``cityscapes`` build's checks that need no model (folders, every image's label
    file, the class-name file's count)."""
    _pairs(spec, key)
    class_names_of(spec, key, _CLASSES, "Cityscapes' train ids")


def cityscapes_source(name: str, spec: Mapping[str, Any], key: str, common: dict) -> Any:
    """The ``cityscapes`` kind (module docstring)."""
    pairs = _pairs(spec, key)
    classes, names = class_names_of(spec, key, _CLASSES, "Cityscapes' train ids")
    read = None
    if str(spec["labels"]) == "raw":

        def read(path: Path) -> np.ndarray:
            with Image.open(path) as image:
                ids = np.asarray(image)
            if ids.ndim != 2:  # left as stored: the set reports it
                return ids
            return LABEL_TRAIN_IDS[np.clip(ids, 0, 255).astype(np.uint8)]

    return benchmark_set(name, pairs, classes, names, common, read_label=read)
