"""Deprecated: the protocol record of a run moved to :mod:`resireg_train.evaluation.protocol`. This module re-exports its names, with a
``DeprecationWarning``, for one release."""

from resireg.deprecation import moved

__getattr__ = moved(
    "resireg_train.protocol",
    {
        "protocol_record": "resireg_train.evaluation.protocol",
        "protocol_text": "resireg_train.evaluation.protocol",
    },
)
