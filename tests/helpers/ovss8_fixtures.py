"""Tiny copies of the eight OVSS benchmarks in their downloaded (and converted) on-disk layouts
and label encodings, written by the tests: VOC's palette PNGs with 255 boundary bands, Pascal
Context's converted 0..59 maps (and a trainval_merged.json they convert from), COCO-Stuff's raw
stuffthingmaps beside mmseg's *_labelTrainIds.png, Cityscapes' label ids beside its train ids,
ADEChallengeData2016. Each writer returns the labels it wrote, as the reader must return them.

The converted files are written here from tables typed from the converters' sources
(mmsegmentation tools/dataset_converters/coco_stuff164k.py and pascal_context.py, SCLIP's
datasets/cvt_coco_object.py, cityscapesScripts helpers/labels.py), entry by entry for the ids
the fixtures use, not from the code under test."""

from __future__ import annotations

import json
from pathlib import Path

import numpy as np
from PIL import Image


def voc_palette() -> list[int]:
    """Pascal VOC's colour map (VOCdevkit's VOClabelcolormap.m: the bits of the index spread
    over R, G, B from the high bit down), 256 colours, flat."""
    palette = []
    for i in range(256):
        r = g = b = 0
        c = i
        for j in range(8):
            r |= ((c >> 0) & 1) << (7 - j)
            g |= ((c >> 1) & 1) << (7 - j)
            b |= ((c >> 2) & 1) << (7 - j)
            c >>= 3
        palette += [r, g, b]
    return palette


def _image(path: Path, size: tuple[int, int], seed: int) -> None:
    rng = np.random.default_rng(seed)
    h, w = size
    pixels = (rng.random((h, w, 3)) * 255).astype(np.uint8)
    path.parent.mkdir(parents=True, exist_ok=True)
    Image.fromarray(pixels).save(path)


def _blocks(size: tuple[int, int], values: list[int]) -> np.ndarray:
    """A label map of ``size``: vertical bands of ``values`` (every value present)."""
    h, w = size
    label = np.zeros((h, w), dtype=np.uint8)
    edges = np.linspace(0, w, len(values) + 1).astype(int)
    for v, (a, b) in zip(values, zip(edges[:-1], edges[1:], strict=True), strict=True):
        label[:, a:b] = v
    return label


def write_voc(
    root: Path, ids=("2007_000032", "2007_000039"), size=(40, 56)
) -> dict[str, np.ndarray]:
    """``VOCdevkit/VOC2012``: palette PNG labels (0 background, 1..20, a 255 boundary band)."""
    labels = {}
    for n, i in enumerate(ids):
        _image(root / "JPEGImages" / f"{i}.jpg", size, n)
        label = _blocks(
            size, [0, 15, 255, 1 + n, 20]
        )  # background, person, boundary, aeroplane (+n), tvmonitor
        png = Image.fromarray(label, mode="P")
        png.putpalette(voc_palette())
        (root / "SegmentationClass").mkdir(parents=True, exist_ok=True)
        png.save(root / "SegmentationClass" / f"{i}.png")
        labels[i] = label
    (root / "ImageSets" / "Segmentation").mkdir(parents=True, exist_ok=True)
    (root / "ImageSets" / "Segmentation" / "val.txt").write_text("".join(f"{i}\n" for i in ids))
    return labels


#: Pascal Context's kept 459-class ids, sorted (mmseg pascal_context.py's _mapping, typed here
#: in its printed order and sorted): label i is the i-th.
CONTEXT_IDS = sorted([
    0, 2, 259, 260, 415, 324, 9, 258, 144, 18, 19, 22, 23, 397, 25, 284, 158, 159, 416, 33, 162,
    420, 454, 295, 296, 427, 44, 45, 46, 308, 59, 440, 445, 31, 232, 65, 354, 424, 68, 326, 72,
    458, 34, 207, 80, 355, 85, 347, 220, 349, 360, 98, 187, 104, 105, 366, 189, 368, 113, 115,
])  # fmt: skip


def write_context(
    root: Path, ids=("2008_000002", "2008_000003"), size=(40, 56)
) -> dict[str, np.ndarray]:
    """``VOCdevkit/VOC2010`` in the converted layout (``SegmentationClassContext``, grey 0..59),
    and a ``trainval_merged.json`` whose conversion gives the same maps (the first image's
    annotations overlap: the later one wins, as Detail's getMask paints them in order)."""
    from pycocotools import mask as coco_mask

    labels, images, annos = {}, [], []
    for n, i in enumerate(ids):
        _image(root / "JPEGImages" / f"{i}.jpg", size, 10 + n)
        h, w = size
        raw = np.zeros(size, dtype=np.int64)  # 459-class ids
        first = np.zeros(size, dtype=np.uint8)
        first[:, : w // 2] = 1
        second = np.zeros(size, dtype=np.uint8)
        second[h // 2 :, w // 4 :] = 1
        cats = (CONTEXT_IDS[5 + n], CONTEXT_IDS[59])  # e.g. bicycle, wood
        for k, (m, cat) in enumerate(((first, cats[0]), (second, cats[1]))):
            raw[m != 0] = cat
            rle = coco_mask.encode(np.asfortranarray(m))
            rle["counts"] = rle["counts"].decode("ascii")
            annos.append({"id": 100 * n + k, "image_id": 2008000002 + n, "category_id": cat,
                          "segmentation": rle})  # fmt: skip
        label = np.searchsorted(CONTEXT_IDS, raw).astype(np.uint8)
        (root / "SegmentationClassContext").mkdir(parents=True, exist_ok=True)
        Image.fromarray(label).save(root / "SegmentationClassContext" / f"{i}.png")
        images.append({"image_id": 2008000002 + n, "file_name": f"{i}.jpg", "height": h,
                       "width": w, "phase": "val"})  # fmt: skip
        labels[i] = label
    (root / "ImageSets" / "SegmentationContext").mkdir(parents=True, exist_ok=True)
    (root / "ImageSets" / "SegmentationContext" / "val.txt").write_text(
        "".join(f"{i}\n" for i in ids)
    )
    (root / "trainval_merged.json").write_text(json.dumps(
        {"images": images, "annos_segmentation": annos, "categories": []}
    ))  # fmt: skip
    return labels


#: COCO-Stuff raw id -> (mmseg train id, COCO-Object label) for the ids the fixtures use, typed
#: from mmseg coco_stuff164k.py's clsID_to_trID and SCLIP's cvt_coco_object.py.
COCO_IDS = {0: (0, 1), 12: (11, 12), 26: (24, 25), 90: None, 91: (80, 0), 150: (139, 0), 151: (140, 0),
            181: (170, 0), 255: (255, 0)}  # fmt: skip


def write_coco(root: Path, stems=("000000000139", "000000000285"), size=(40, 56)) -> dict:
    """``coco_stuff164k``: images/val2017, annotations/val2017 with the raw maps, mmseg's
    ``_labelTrainIds.png`` and the OVSS converter's ``_instanceTrainIds.png``. Returns
    ``{stem: (raw, stuff train ids, object labels)}``."""
    out = {}
    for n, s in enumerate(stems):
        _image(root / "images" / "val2017" / f"{s}.jpg", size, 20 + n)
        raw = _blocks(size, [0, 12, 26, 91, 150 + n, 181, 255])
        stuff = np.vectorize(lambda v: COCO_IDS[v][0])(raw).astype(np.uint8)
        obj = np.vectorize(lambda v: COCO_IDS[v][1])(raw).astype(np.uint8)
        folder = root / "annotations" / "val2017"
        folder.mkdir(parents=True, exist_ok=True)
        Image.fromarray(raw).save(folder / f"{s}.png")
        Image.fromarray(stuff).save(folder / f"{s}_labelTrainIds.png")
        Image.fromarray(obj).save(folder / f"{s}_instanceTrainIds.png")
        out[s] = (raw, stuff, obj)
    return out


#: Cityscapes label id -> train id (cityscapesScripts helpers/labels.py) for the fixtures' ids.
CITY_IDS = {0: 255, 7: 0, 8: 1, 9: 255, 26: 13, 33: 18}


def write_cityscapes(root: Path, stems=("frankfurt_000000_000294", "lindau_000000_000019"),
                     size=(32, 64)) -> dict:  # fmt: skip
    """``cityscapes``: leftImg8bit/val/<city>/ and gtFine/val/<city>/ with labelIds and
    labelTrainIds. Returns ``{stem: (label ids, train ids)}``."""
    out = {}
    for n, stem in enumerate(stems):
        city = stem.split("_")[0]
        _image(root / "leftImg8bit" / "val" / city / f"{stem}_leftImg8bit.png", size, 30 + n)
        ids = _blocks(size, [0, 7, 8, 9, 26, 33])
        train = np.vectorize(CITY_IDS.get)(ids).astype(np.uint8)
        folder = root / "gtFine" / "val" / city
        folder.mkdir(parents=True, exist_ok=True)
        Image.fromarray(ids).save(folder / f"{stem}_gtFine_labelIds.png")
        Image.fromarray(train).save(folder / f"{stem}_gtFine_labelTrainIds.png")
        out[stem] = (ids, train)
    return out


def write_ade(root: Path, stems=("ADE_val_00000001", "ADE_val_00000002"), size=(40, 56)) -> dict:
    """``ADEChallengeData2016``: images/validation/*.jpg, annotations/validation/*.png (0..150)."""
    out = {}
    for n, stem in enumerate(stems):
        _image(root / "images" / "validation" / f"{stem}.jpg", size, 40 + n)
        label = _blocks(size, [0, 1, 13, 150])
        (root / "annotations" / "validation").mkdir(parents=True, exist_ok=True)
        Image.fromarray(label).save(root / "annotations" / "validation" / f"{stem}.png")
        out[stem] = label
    return out


def write_all(data_dir: Path) -> None:
    """The eight benchmarks under ``data_dir`` as ``paths.data_dir`` expects them."""
    write_voc(data_dir / "VOCdevkit" / "VOC2012")
    write_context(data_dir / "VOCdevkit" / "VOC2010")
    write_coco(data_dir / "coco_stuff164k")
    write_cityscapes(data_dir / "cityscapes")
    write_ade(data_dir / "ADEChallengeData2016")
