"""The tiny model parts of the tests (random init, same architectures): read from the configs of
``experiment=smoke`` (``conf/model/backbone/tiny.yaml``, ``conf/model/tiny.yaml``'s head block,
``conf/model/text/tiny.yaml``), so the tests build the smoke run's model and no copy of its
values exists (they were once library constants, ``resireg.models.TINY_*``)."""

import yaml

from helpers.paths import ROOT

_MODEL = ROOT / "conf" / "model"


def _load(path):
    with open(_MODEL / path) as f:
        return yaml.safe_load(f)


TINY_BACKBONE = _load("backbone/tiny.yaml")
TINY_HEAD = _load("tiny.yaml")["head"]  # what model=tiny sets over vlm25m's head
TINY_TEXT = _load("text/tiny.yaml")
