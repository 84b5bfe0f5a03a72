"""Deprecated: the protocol record of a run moved to :mod:`resireg_train.protocol_record`. This module re-exports its names, with a
``DeprecationWarning``, for one release."""

from resireg.deprecation import moved

__getattr__ = moved(
    "resireg_train.protocol",
    {
        "protocol_record": "resireg_train.protocol_record",
        "protocol_text": "resireg_train.protocol_record",
    },
)
