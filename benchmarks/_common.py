"""What the benchmark scripts share: the 25M architecture with random weights, ReSiReg's
defaults from ``conf/``, and a median timer. (A script run as ``python benchmarks/x.py`` finds
this module next to it; the tests that import a benchmark put ``benchmarks/`` on the path.)"""

from __future__ import annotations

import statistics
import time
from collections.abc import Callable
from pathlib import Path
from typing import Any

import yaml

CONF = Path(__file__).resolve().parents[1] / "conf"


def load_yaml(path: Path) -> dict[str, Any]:
    with open(path) as f:
        return yaml.safe_load(f)


#: The tiny model of ``experiment=smoke`` (random init, same architectures), read from conf/.
TINY_BACKBONE = load_yaml(CONF / "model" / "backbone" / "tiny.yaml")
TINY_HEAD = load_yaml(CONF / "model" / "tiny.yaml")["head"]  # over vlm25m's head
TINY_TEXT = load_yaml(CONF / "model" / "text" / "tiny.yaml")


def resireg_defaults() -> dict[str, Any]:
    """``conf/resireg/default.yaml``: ReSiReg's parameters (``lite``, ``full``, ...)."""
    return load_yaml(CONF / "resireg" / "default.yaml")


def build_model(tiny: bool = False):
    """The 25M VLM with random weights: EUPE ViT-S/16 of ``conf/model/backbone/eupe_vit_s16.yaml``
    (``weights: null``) and the head of ``conf/model/vlm25m.yaml``; or the tests' tiny one. The
    text tower takes no part in an image pass, so the tiny one is built to save time.

    torch and the models are imported here, not at the top, so a process that imports this
    module for its helpers (e.g. the map's memory probe) loads only what it uses."""
    from resireg.models import ResiregVLM

    if tiny:
        return ResiregVLM.build(TINY_BACKBONE, TINY_HEAD, TINY_TEXT).eval()
    backbone = {**load_yaml(CONF / "model" / "backbone" / "eupe_vit_s16.yaml"), "weights": None}
    head = dict(load_yaml(CONF / "model" / "vlm25m.yaml")["head"])
    return ResiregVLM.build(backbone, head, TINY_TEXT).eval()


def generated_spec(
    images: int, short_side: int, image_size: list[int] | None = None
) -> dict[str, Any]:
    """The dataset entry of ``images`` generated scenes (3:4, ``short_side`` x 4/3 unless
    ``image_size``) at the protocol's ``short_side``: the benchmarks' stand-in for ADE20K."""
    size = image_size or [short_side, short_side * 4 // 3]
    from resireg_train.data.specs import dataset_conf

    return dataset_conf("synthetic", size=images, short_side=short_side, image_size=size)


def encode_generated(model: Any, images: int, short_side: int) -> Any:
    """``model.encode`` of the :func:`generated_spec` images, one batch, no gradients."""
    import torch

    from resireg_train.data.segmentation import build_segmentation_set

    data = build_segmentation_set(generated_spec(images, short_side), model.input_rule.patch_size)
    pixels = torch.stack([data[i]["image"] for i in range(images)])
    with torch.no_grad():
        return model.encode(model.input_rule.normalize(pixels))


def median_seconds(fn: Callable[[], Any], repeats: int, warmup: int = 1) -> float:
    """Median wall seconds of ``repeats`` calls of ``fn`` after ``warmup`` untimed ones."""
    for _ in range(warmup):
        fn()
    times = []
    for _ in range(repeats):
        start = time.perf_counter()
        fn()
        times.append(time.perf_counter() - start)
    return statistics.median(times)


def positive_int(text: str) -> int:
    """An ``argparse`` type: an integer >= 1 (argparse names the flag and the value otherwise)."""
    import argparse

    try:
        value = int(text)
    except ValueError:
        raise argparse.ArgumentTypeError(f"{text!r}: expected an integer >= 1") from None
    if value < 1:
        raise argparse.ArgumentTypeError(f"{text!r}: expected an integer >= 1")
    return value
