"""One table per kind of component, without importing torch (docs/design.md section 13).

Each kind has one table, the only place its names, classes and parameter rules are written:

- :data:`VARIANT_SPECS` (:mod:`resireg.specs.variants`): the ReSiReg variants (``bb``,
  ``calib``, ``lite``, ``full``), their classes, parameter rules and report labels;
  defaults in ``conf/resireg/default.yaml``,
- :data:`ENCODER_SPECS` (:mod:`resireg.specs.encoders`): the dense encoders by ``kind``,
  their builders, the ``conf/encoder/`` files of each and the modules they import,
- :data:`PRIOR_SPECS` (:mod:`resireg.specs.priors`): the segmentation priors, their rules;
  defaults in ``conf/prior/``.

The training package keeps two more tables of the same pattern, beside what they describe:
``resireg_train.tasks.TASK_SPECS`` (``resireg-eval``'s tasks) and
``resireg_train.data.specs.DATASET_SPECS`` (the evaluation datasets by ``kind``: builder, keys,
tasks; defaults in ``conf/dataset/``).

An entry names its class lazily (``"resireg.reconstruct:ReSiRegFull"``, loaded by
:func:`load` when something is built), so the config checks (``resireg_train.validation``),
the report and the CLIs read the tables before torch loads. The classes check their keywords
against the same rules (:mod:`resireg.specs.rules`).
"""

from __future__ import annotations

import importlib
from typing import Any

__all__ = ["ENCODER_SPECS", "PRIOR_SPECS", "VARIANT_SPECS", "load"]


def load(target: str) -> Any:
    """The object a ``"package.module:attribute"`` path names (imported now)."""
    module, sep, attribute = target.partition(":")
    if not sep or not module or not attribute:
        raise ValueError(f"{target!r}: expected 'package.module:attribute'")
    return getattr(importlib.import_module(module), attribute)


def __getattr__(name: str) -> Any:  # PEP 562: each table loads with its module
    sources = {"VARIANT_SPECS": "variants", "ENCODER_SPECS": "encoders", "PRIOR_SPECS": "priors"}
    if name in sources:
        return getattr(importlib.import_module(f"resireg.specs.{sources[name]}"), name)
    raise AttributeError(f"module 'resireg.specs' has no attribute {name!r}")
