"""The ReSiReg variant a :class:`~resireg.mapping.SemanticMap` applies: its keyword (``variant=``,
formerly ``configuration=``: :func:`variant_argument`) and the variant it names
(:func:`map_variant`)."""

from __future__ import annotations

import warnings
from collections.abc import Mapping
from typing import Any, NamedTuple

from torch import nn

from resireg.method.variants import build_variants
from resireg.specs.variants import takes_prior, variant_layer

__all__ = ["MapVariant", "map_variant", "variant_argument"]


class MapVariant(NamedTuple):
    """A map's variant: its name (saved as ``settings.configuration``), its module, whether it
    takes a segmentation prior, and whether the module was given built (not by name)."""

    name: str
    module: nn.Module
    takes_prior: bool
    given: bool


def variant_argument(variant: Any, configuration: Any) -> Any:
    """The variant given, by ``variant`` or by the keyword it replaces, ``configuration`` (one
    release: a FutureWarning naming ``variant``); both given are refused naming both."""
    if configuration is None:
        if variant is None:
            raise TypeError("SemanticMap() needs variant= (a variant name or module)")
        return variant
    if variant is not None:
        raise TypeError(f"SemanticMap(): variant={_name(variant)!r} and configuration="
                        f"{_name(configuration)!r} both given: give variant= only")  # fmt: skip
    warnings.warn("SemanticMap(configuration=...) is deprecated and will be removed in the next "
                  "release: use variant=", FutureWarning, stacklevel=3)  # fmt: skip
    return configuration


def map_variant(
    variant: str | nn.Module, params: Mapping[str, Mapping[str, Any] | None] | None,
    prior_input: bool,
) -> MapVariant:  # fmt: skip
    """The variant ``variant`` names (built by :func:`resireg.method.variants.build_variants`
    with ``params``), or the module given (``prior_input``: whether it takes the prior); a
    ValueError for an ``@layer:`` variant (an evaluation sweep setting)."""
    if isinstance(variant, nn.Module):
        return MapVariant(type(variant).__name__, variant, bool(prior_input), True)
    name = str(variant)
    if variant_layer(name) is not None:
        raise ValueError(
            f"variant={name!r}: @layer: is an evaluation sweep setting; a map "
            "runs on the encoder's own intermediates"
        )
    return MapVariant(name, build_variants([name], params or {})[name], takes_prior(name), False)


def _name(variant: Any) -> str:
    return type(variant).__name__ if isinstance(variant, nn.Module) else str(variant)
