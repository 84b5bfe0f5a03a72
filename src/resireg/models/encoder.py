"""Deprecated: the dense-encoder interface moved to :mod:`resireg.models.interface`. This module re-exports its names, with a
``DeprecationWarning``, for one release."""

from resireg.deprecation import moved

__getattr__ = moved(
    "resireg.models.encoder",
    {
        "InputRule": "resireg.models.interface",
        "DenseOutput": "resireg.models.interface",
        "DenseEncoder": "resireg.models.interface",
        "block_index": "resireg.models.interface",
        "block_indices": "resireg.models.interface",
    },
)
