"""Deprecated: the model card and the Hub folder moved to :mod:`resireg.models.vlm.card` (beside
the model that publishes them, ``ResiregVLM.push_to_hub``). This module re-exports them, with a
``DeprecationWarning``, for one release."""

from __future__ import annotations

import warnings
from typing import Any

_NAMES = ("hub_folder", "model_card")


def __getattr__(name: str) -> Any:
    if name in _NAMES:
        warnings.warn(f"resireg.deploy.card.{name} moved to resireg.models.vlm.card.{name}",
                      DeprecationWarning, stacklevel=2)  # fmt: skip
        from resireg.models.vlm import card

        return getattr(card, name)
    raise AttributeError(f"module 'resireg.deploy.card' has no attribute {name!r}")
