"""The ground floor: one table per kind of component, and the rules of their settings, without
importing torch (docs/architecture.md).

Every table is a :class:`~resireg.specs.table.SpecTable` (``names()``, ``get(name)`` answering
an unknown name with the closest ones, lazy ``"module:Class"`` targets, ``configs(name)``: the
``conf/<group>/`` files of an entry, found by scanning):

- :data:`VARIANT_SPECS` (:mod:`resireg.specs.variants`): the ReSiReg variants (``bb``,
  ``calib``, ``lite``, ``full``) and the configuration syntax (``full+prior@n_prototypes:24``);
  defaults in ``conf/resireg/default.yaml``,
- :data:`ENCODER_SPECS` (:mod:`resireg.specs.encoders`): the dense encoders by ``kind``;
  ``conf/encoder/``; installed packages add kinds through entry points,
- :data:`PRIOR_SPECS` (:mod:`resireg.specs.priors`): the segmentation priors; ``conf/prior/``,
- :data:`METRIC_SPECS` (:mod:`resireg.specs.metrics`): the scores, their keys and direction,
- :data:`SOURCE_SPECS` (:mod:`resireg.specs.sources`): the map's frame sources;
  ``conf/source/``,
- :data:`TEXT_SPECS` (:mod:`resireg.specs.text`): the 25M VLM's frozen text towers;
  ``conf/model/text/``.

The training package keeps four more tables of the same type beside what they describe:
``resireg_train.evaluation.specs.TASK_SPECS``, ``resireg_train.data.specs.DATASET_SPECS``,
``resireg_train.training.specs.TEACHER_SPECS`` and
``resireg_train.report.specs.SECTION_SPECS``. Each table module's docstring holds its
"adding a ..." recipe.

This package imports nothing of ``resireg`` above it (:mod:`resireg.errors` only; the import
contracts in ``pyproject.toml`` check it).

May be imported by every module of both packages (it is the ground floor).
"""

from __future__ import annotations

import importlib
from typing import Any

from resireg.specs.table import SpecTable, UnknownNameError, conf_dir, load

__all__ = [
    "ENCODER_SPECS",
    "METRIC_SPECS",
    "PRIOR_SPECS",
    "SOURCE_SPECS",
    "TEXT_SPECS",
    "VARIANT_SPECS",
    "SpecTable",
    "UnknownNameError",
    "conf_dir",
    "load",
]

_TABLES = {
    "VARIANT_SPECS": "variants",
    "ENCODER_SPECS": "encoders",
    "PRIOR_SPECS": "priors",
    "METRIC_SPECS": "metrics",
    "SOURCE_SPECS": "sources",
    "TEXT_SPECS": "text",
}


def __getattr__(name: str) -> Any:  # PEP 562: each table loads with its module
    if name in _TABLES:
        return getattr(importlib.import_module(f"resireg.specs.{_TABLES[name]}"), name)
    raise AttributeError(f"module 'resireg.specs' has no attribute {name!r}")
