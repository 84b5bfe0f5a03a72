"""The ``ade20k`` kind of the dataset table: ADE20K-150 as a
:class:`~resireg_train.data.segmentation.SegmentationSet`.

``path`` is a hub id (conf: ``zhoubolei/scene_parse_150``, config ``scene_parsing``, revision
``refs/convert/parquet``: the hub's script loader does not run with datasets >= 4), a local
folder holding that parquet layout, or a local ``ADEChallengeData2016`` folder
(``images/<split>/*.jpg``, ``annotations/<split>/*.png``). Labels 0..150 with 0 = "other",
scored with ``reduce_zero_label``. :func:`check_ade20k_source` is the table entry's check that
needs no model (:func:`resireg_train.data.segmentation.check_segmentation_source` runs it).
"""

from __future__ import annotations

import os
from collections.abc import Mapping
from pathlib import Path
from typing import Any

import numpy as np
from PIL import Image

from resireg.models.hub import require_online
from resireg.ovss import ADE20K_CLASSES
from resireg_train.data.segmentation import (
    IMAGE_SUFFIXES,
    SegmentationSet,
    header_size,
    open_image,
)
from resireg_train.data.specs import require_keys

__all__ = ["ade20k_source", "check_ade20k_source"]


def ade20k_source(name: str, spec: Mapping[str, Any], key: str, common: dict) -> SegmentationSet:
    """The ``ade20k`` kind (module docstring)."""
    path, split = str(spec["path"]), str(spec["split"])
    common = {**common, "reduce_zero_label": True}
    local = Path(path).expanduser()
    if (local / "images" / split).is_dir():  # ADEChallengeData2016
        return _ade20k_folder(name, local, split, key, path, common)
    table = _load_hub_table(path, spec, split, key, local.is_dir())
    image_col, label_col = spec["image"], spec["label"]
    for role, col in (("image", image_col), ("label", label_col)):
        if col not in table.column_names:
            raise ValueError(
                f"{key}.{role}={col!r}: no such column; columns are {table.column_names}"
            )
    from datasets import Image as HFImage

    table = table.cast_column(image_col, HFImage(decode=False)).cast_column(
        label_col, HFImage(decode=False)
    )

    def stored(value: Mapping[str, Any]) -> bytes | str:  # embedded bytes, or a file path
        return value["bytes"] if value.get("bytes") is not None else value["path"]

    def load(i: int) -> tuple[Image.Image, np.ndarray]:
        row = table[i]
        return open_image(stored(row[image_col])), np.asarray(open_image(stored(row[label_col])))

    def describe(i: int) -> str:
        stored_path = table[i][image_col].get("path")
        return f"{path} [{split}] row {i}" + (f" ({stored_path})" if stored_path else "")

    return SegmentationSet(
        name,
        ADE20K_CLASSES,
        load,
        lambda i: header_size(stored(table[i][image_col])),
        len(table),
        describe=describe,
        **common,
    )


def _ade20k_folder(
    name: str, root: Path, split: str, key: str, path: str, common: dict
) -> SegmentationSet:
    """ADEChallengeData2016: ``images/<split>/<stem>.jpg`` (any image suffix, any case) with
    ``annotations/<split>/<stem>.png``."""
    labels = {
        p.stem: p for p in (root / "annotations" / split).glob("*") if p.suffix.lower() == ".png"
    }
    pairs = []
    for image in sorted((root / "images" / split).iterdir()):
        if image.suffix.lower() not in IMAGE_SUFFIXES:
            continue
        if image.stem not in labels:
            raise FileNotFoundError(
                f"{key}.path={path!r}: {image.name} has no annotations/{split}/{image.stem}.png"
            )
        pairs.append((image, labels[image.stem]))
    return SegmentationSet(
        name,
        ADE20K_CLASSES,
        lambda i: (open_image(pairs[i][0]), np.asarray(open_image(pairs[i][1]))),
        lambda i: header_size(pairs[i][0]),
        len(pairs),
        describe=lambda i: str(pairs[i][0]),
        **common,
    )


def _check_hub_id(path: str, key: str) -> None:
    """``<key>.path`` names no local folder: a FileNotFoundError if it is a path rather than
    a hub id."""
    if path.startswith(("/", ".", "~")):
        raise FileNotFoundError(f"{key}.path={path!r} does not exist")


def check_ade20k_source(spec: Mapping[str, Any], key: str = "dataset") -> None:
    """The ``ade20k`` build's check that needs no model: a ``path`` that is neither a folder
    nor a hub id. A hub dataset's availability is checked when it loads."""
    require_keys(spec, ("path",), key, "conf/dataset/ade20k.yaml")
    path = str(spec["path"])
    if not Path(path).expanduser().is_dir():
        _check_hub_id(path, key)


def _load_hub_table(path: str, spec: Mapping[str, Any], split: str, key: str, local: bool):
    """A map-style ``datasets.Dataset``: a local parquet folder, or the hub (cached or online)."""
    from datasets import load_dataset

    if local:
        return load_dataset(path, split=split)
    _check_hub_id(path, key)
    name, revision = spec["config"], spec["revision"]
    hint = (
        f"Download it where there is a network (e.g. `datasets.load_dataset({path!r}, {name!r}, "
        f"revision={revision!r}, split={split!r})` fills the cache; then set HF_HUB_OFFLINE=1), "
        f"or set {key}.path to a local ADEChallengeData2016 folder."
    )
    if os.environ.get("HF_HUB_OFFLINE", "").strip().lower() not in {"1", "true", "yes", "on"}:
        require_online(f"the hub dataset {path!r} ({key}.path)", "huggingface.co", hint)
    try:
        return load_dataset(path, name, revision=revision, split=split)
    except (ConnectionError, FileNotFoundError, OSError) as err:
        from resireg.models.hub import WeightsUnavailableError

        raise WeightsUnavailableError(
            f"the hub dataset {path!r} ({key}.path) is not in the local cache: {err}. {hint}"
        ) from err
