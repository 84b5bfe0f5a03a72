"""Deprecated: the model card and the Hub folder moved to :mod:`resireg.models.vlm.card` (beside
the model that publishes them, ``ResiregVLM.push_to_hub``). This module re-exports them, with a
``DeprecationWarning``, for one release."""

from resireg.deprecation import moved

__getattr__ = moved(
    "resireg.deploy.card",
    {"hub_folder": "resireg.models.vlm.card", "model_card": "resireg.models.vlm.card"},
)
