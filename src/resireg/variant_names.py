"""Deprecated: the configuration syntax moved to :mod:`resireg.specs.variants` (beside the variant
table it reads). This module re-exports its names, with a ``DeprecationWarning``, for one
release."""

from __future__ import annotations

import warnings
from typing import Any

_NAMES = ("LAYER_KEY", "LITE_ATTENTION", "PRIOR_SUFFIX", "PRIOR_VARIANTS", "VARIANTS",
          "parse_variant", "takes_prior", "variant_layer")  # fmt: skip


def __getattr__(name: str) -> Any:
    if name in _NAMES:
        warnings.warn(
            f"resireg.variant_names.{name} moved to resireg.specs.variants.{name}",
            DeprecationWarning,
            stacklevel=2,
        )
        from resireg.specs import variants

        return getattr(variants, name)
    raise AttributeError(f"module 'resireg.variant_names' has no attribute {name!r}")
