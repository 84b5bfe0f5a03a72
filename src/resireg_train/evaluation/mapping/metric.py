"""Deprecated: the 3D task's metric moved to :mod:`resireg.mapping.metric` (beside the map it
scores; its definitions are the metric table's, :mod:`resireg.specs.metrics`). This module
re-exports its names, with a ``DeprecationWarning``, for one release."""

from resireg.deprecation import moved

__getattr__ = moved(
    "resireg_train.evaluation.mapping.metric",
    {
        "METRICS": "resireg.mapping.metric",
        "confusion": "resireg.mapping.metric",
        "mean_over_scenes": "resireg.mapping.metric",
        "scores": "resireg.mapping.metric",
    },
)
