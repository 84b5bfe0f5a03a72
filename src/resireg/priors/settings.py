"""Deprecated: the prior table and its settings moved to :mod:`resireg.specs.priors` (the
torch-free ground floor). This module re-exports them, with a ``DeprecationWarning``, for one
release."""

from __future__ import annotations

import warnings
from typing import Any

_NAMES = ("PRIOR_KINDS", "PRIOR_SPECS", "PriorSpec", "SAM_DEFAULTS", "SAM_MODEL", "SAM_RULES")


def __getattr__(name: str) -> Any:
    if name in _NAMES:
        warnings.warn(f"resireg.priors.settings.{name} moved to resireg.specs.priors.{name}",
                      DeprecationWarning, stacklevel=2)  # fmt: skip
        from resireg.specs import priors

        return getattr(priors, name)
    raise AttributeError(f"module 'resireg.priors.settings' has no attribute {name!r}")
