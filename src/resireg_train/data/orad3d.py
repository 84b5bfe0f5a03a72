"""The ``orad3d`` kind of the dataset table: ORAD-3D's off-road images as a
:class:`~resireg_train.data.segmentation.SegmentationSet`.

A local ORAD-3D folder ``<path>/<split>/<sequence>/{image_data, gt_image,
gt_image_multi_seg}``; :func:`orad3d_label` says how a label map is built from the
``gt_image`` colours and the polygons drawn over them. :func:`check_orad3d_source` is the
table entry's check that needs no model (a missing ``<path>/<split>`` folder).
"""

from __future__ import annotations

import json
import os
from collections.abc import Mapping, Sequence
from pathlib import Path
from typing import Any

import numpy as np
from PIL import Image, ImageDraw

from resireg.ovss import ORAD3D_CLASSES
from resireg_train.data.segmentation import (
    IGNORE_INDEX,
    IMAGE_SUFFIXES,
    SegmentationSet,
    header_size,
    open_image,
)
from resireg_train.data.specs import require_keys

__all__ = ["check_orad3d_source", "orad3d_label", "orad3d_source"]


def _orad3d_root(spec: Mapping[str, Any], key: str) -> Path:
    """``<path>/<split>``, the folder of the ORAD-3D sequences; an error naming ``<key>.path``
    unless it exists."""
    require_keys(spec, ("path", "split"), key, "conf/dataset/orad3d.yaml")
    root = Path(str(spec["path"])).expanduser() / str(spec["split"])
    if not root.is_dir():
        raise FileNotFoundError(
            f"{key}.path={spec['path']!r}: no {root} folder (expected <path>/<split>/<sequence>/"
            "{image_data,gt_image,gt_image_multi_seg})"
        )
    return root


def check_orad3d_source(spec: Mapping[str, Any], key: str = "dataset") -> None:
    """The ``orad3d`` build's check that needs no model: a missing ``<path>/<split>`` folder."""
    _orad3d_root(spec, key)


def orad3d_label(
    gt_image: str | os.PathLike,
    polygons: str | os.PathLike | None,
    polygon_tags: Mapping[str, str],
    gt_image_classes: Mapping[str, str],
    key: str = "orad3d",
) -> np.ndarray:
    """ORAD-3D label map ``[H, W]`` (uint8 class ids of ``ORAD3D_CLASSES``, 255 = ignore).

    The base layer is ``gt_image`` (road / non-road / sky colours, ``gt_image_classes``;
    other colours are ignored). The ``gt_image_multi_seg`` polygons (a LabelMe-style JSON:
    ``{"shapes": [{"label": tag, "points": [[x, y], ...]}, ...]}``) are drawn over it in
    file order, each tag mapped to a class by ``polygon_tags``. Both mappings are the dataset
    entry's (``conf/dataset/orad3d.yaml`` holds ORAD-3D's; ``dataset_conf("orad3d")`` reads them
    outside Hydra).
    """
    index = {c: i for i, c in enumerate(ORAD3D_CLASSES)}
    for table, table_key in (
        (polygon_tags, "polygon_tags"),
        (gt_image_classes, "gt_image_classes"),
    ):
        bad = sorted(set(table.values()) - set(index))
        if bad:
            raise ValueError(f"{key}.{table_key}: {bad} are not ORAD-3D classes {ORAD3D_CLASSES}")
    rgb = np.asarray(open_image(gt_image).convert("RGB"))
    label = np.full(rgb.shape[:2], IGNORE_INDEX, dtype=np.uint8)
    for colour, cls in gt_image_classes.items():
        r, g, b = (int(v) for v in str(colour).split(","))
        label[(rgb[..., 0] == r) & (rgb[..., 1] == g) & (rgb[..., 2] == b)] = index[cls]
    if polygons is None:
        return label
    canvas = Image.fromarray(label)
    draw = ImageDraw.Draw(canvas)
    for cls, points in _polygons(polygons, polygon_tags, key):
        if len(points) >= 3:
            draw.polygon(points, fill=index[cls])
    return np.asarray(canvas)


def _polygons(
    path: str | os.PathLike, polygon_tags: Mapping[str, str], key: str
) -> list[tuple[str, list[tuple[float, float]]]]:
    """``(class, points)`` of every polygon of a LabelMe-style JSON, in file order; a tag
    without a class is an error naming ``<key>.polygon_tags``."""
    shapes = []
    for shape in json.loads(Path(path).read_text()).get("shapes", []):
        tag = str(shape.get("label", "")).strip()
        if tag not in polygon_tags:
            raise ValueError(
                f"{path}: polygon tag {tag!r} has no class; add it to "
                f"{key}.polygon_tags (known: {sorted(polygon_tags)})"
            )
        shapes.append((polygon_tags[tag], [tuple(map(float, p)) for p in shape.get("points", [])]))
    return shapes


def _match(folder: Path, stem: str, suffixes: Sequence[str]) -> Path | None:
    """The file of ``folder`` named ``<stem><suffix>`` or ``<stem>_<anything><suffix>`` (the
    ORFD-style ``_fillcolor``); never another stem that merely starts alike (``10`` for ``1``)."""
    if not folder.is_dir():
        return None
    hits = sorted(
        p
        for p in folder.iterdir()
        if p.suffix.lower() in suffixes and (p.stem == stem or p.stem.startswith(f"{stem}_"))
    )
    return hits[0] if hits else None


def orad3d_source(name: str, spec: Mapping[str, Any], key: str, common: dict) -> SegmentationSet:
    """The ``orad3d`` kind (module docstring; labels: :func:`orad3d_label`)."""
    root = _orad3d_root(spec, key)
    tags, colours = dict(spec["polygon_tags"]), dict(spec["gt_image_classes"])
    items: list[tuple[Path, Path, Path | None]] = []
    for sequence in sorted(p for p in root.iterdir() if p.is_dir()):
        images = sorted(
            p for p in (sequence / "image_data").glob("*") if p.suffix.lower() in IMAGE_SUFFIXES
        )
        for image in images:
            gt = _match(sequence / "gt_image", image.stem, (".png",))
            if gt is None:
                continue  # not annotated
            items.append(
                (image, gt, _match(sequence / "gt_image_multi_seg", image.stem, (".json",)))
            )
    if not items:
        raise FileNotFoundError(f"{key}.path={spec['path']!r}: no annotated images under {root}")
    # Tags are checked up front: a decoding error skips an image, a missing tag must not.
    for _, _, polygons in items:
        if polygons is not None:
            _polygons(polygons, tags, key)

    def load(i: int) -> tuple[Image.Image, np.ndarray]:
        image, gt, polygons = items[i]
        return open_image(image), orad3d_label(gt, polygons, tags, colours, key)

    return SegmentationSet(
        name,
        ORAD3D_CLASSES,
        load,
        lambda i: header_size(items[i][0]),
        len(items),
        describe=lambda i: str(items[i][0]),
        **common,
    )
