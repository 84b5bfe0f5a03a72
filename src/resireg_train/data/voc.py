"""Pascal VOC 2012 val as downloaded (``dataset=voc21``, ``dataset=voc20``; kind ``voc``).

``<path>`` is ``VOCdevkit/VOC2012``: ``ImageSets/Segmentation/<split>.txt`` lists the ids,
``JPEGImages/<id>.jpg`` the images, ``SegmentationClass/<id>.png`` the labels: palette PNGs whose
indices are the classes (0 = background, 1..20 aeroplane .. tvmonitor) and 255 the boundary
band (ignored), read as indices, never as colours (mmseg's ``PascalVOCDataset`` with
``LoadAnnotations``). VOC21 scores the 21 classes; VOC20 (``reduce_zero_label: true``, mmseg's
``PascalVOC20Dataset`` of SCLIP and NACLIP) ignores the background: ``0 -> 255``, ``c -> c - 1``.
"""

from __future__ import annotations

from collections.abc import Mapping
from pathlib import Path
from typing import Any

from resireg_train.data.folders import benchmark_set, class_names_of, listed_pairs, root_of

__all__ = ["VOC_CLASSES", "check_voc_source", "voc_source"]

#: Pascal VOC's label ids: 0 = background and the 20 object classes (label 255: boundary).
VOC_CLASSES = 21
_LAYOUT = "VOCdevkit/VOC2012 with JPEGImages/, SegmentationClass/, ImageSets/Segmentation/"
_SOURCE = "conf/dataset/voc21.yaml"


def _pairs(spec: Mapping[str, Any], key: str) -> list[tuple[Path, Path]]:
    root = root_of(spec, key, _LAYOUT, _SOURCE)
    return listed_pairs(root, spec, key, "ImageSets/Segmentation", "JPEGImages",
                        "SegmentationClass")  # fmt: skip


def check_voc_source(spec: Mapping[str, Any], key: str = "dataset") -> None:
    """The ``voc`` build's checks that need no model: the folder, the split's list, the image
    and label folders, every listed file, and the class-name file's class count."""
    _pairs(spec, key)
    class_names_of(spec, key, VOC_CLASSES - bool(spec["reduce_zero_label"]),
                   f"VOC labels with reduce_zero_label={spec['reduce_zero_label']}")  # fmt: skip


def voc_source(name: str, spec: Mapping[str, Any], key: str, common: dict) -> Any:
    """The ``voc`` kind (module docstring)."""
    reduce = bool(spec["reduce_zero_label"])
    pairs = _pairs(spec, key)
    classes, names = class_names_of(spec, key, VOC_CLASSES - reduce,
                                    f"VOC labels with reduce_zero_label={reduce}")  # fmt: skip
    return benchmark_set(name, pairs, classes, names, common, reduce_zero_label=reduce)
