"""Deprecated: the 3D task's metric moved to :mod:`resireg.mapping.metric` (beside the map it
scores; its definitions are the metric table's, :mod:`resireg.specs.metrics`). This module
re-exports its names, with a ``DeprecationWarning``, for one release."""

from __future__ import annotations

import warnings
from typing import Any

_NAMES = ("METRICS", "confusion", "mean_over_scenes", "scores")


def __getattr__(name: str) -> Any:
    if name in _NAMES:
        warnings.warn(f"resireg_train.mapping.metric.{name} moved to resireg.mapping.metric",
                      DeprecationWarning, stacklevel=2)  # fmt: skip
        from resireg.mapping import metric

        return getattr(metric, name)
    raise AttributeError(f"module 'resireg_train.mapping.metric' has no attribute {name!r}")
