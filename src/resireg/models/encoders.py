"""Deprecated: the encoder builder moved to :mod:`resireg.models.factory`. This module re-exports its names, with a
``DeprecationWarning``, for one release."""

from resireg.deprecation import moved

__getattr__ = moved(
    "resireg.models.encoders",
    {
        "ENCODERS": "resireg.models.factory",
        "build_encoder": "resireg.models.factory",
        "count_parameters": "resireg.models.factory",
        "encoder_arguments": "resireg.models.factory",
        "encoder_modules": "resireg.models.factory",
        "load_resireg_vlm": "resireg.models.factory",
    },
)
