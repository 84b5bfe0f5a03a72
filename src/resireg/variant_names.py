"""The ReSiReg configuration syntax (``full+prior@n_prototypes:24``), without importing torch.

The config checks (``resireg_train.validation``) need it before anything heavy is loaded,
so a bad ``variants=`` value is reported in a fraction of a second. The variants themselves
(names, classes, parameter rules) are one table, :mod:`resireg.specs.variants`; the factory
is :mod:`resireg.variants`.
"""

from __future__ import annotations

import ast
from typing import Any

from resireg.specs.variants import LITE_ATTENTION, PRIOR_VARIANTS, VARIANTS

__all__ = [
    "LAYER_KEY",
    "LITE_ATTENTION",
    "PRIOR_SUFFIX",
    "PRIOR_VARIANTS",
    "VARIANTS",
    "parse_variant",
    "takes_prior",
    "variant_layer",
]

#: ``<variant>+prior``: the configuration is called with the segmentation prior
#: (``full+prior``, ``lite+prior@alpha:5.0``); only the variants that use one take it
#: (:data:`PRIOR_VARIANTS`). The names, :data:`VARIANTS`, :data:`PRIOR_VARIANTS` and
#: :data:`LITE_ATTENTION` come from the variant table, :mod:`resireg.specs.variants`.
PRIOR_SUFFIX = "+prior"


#: ``<variant>@layer:<block>``: the configuration runs on that encoder block's intermediates
#: (``lite@layer:5``; the CLIP layer sweep, docs/design.md section 5). It is an instruction to
#: the evaluation, not a parameter of the variant: :func:`parse_variant` leaves it out.
LAYER_KEY = "layer"


def takes_prior(name: str) -> bool:
    """Whether configuration ``name`` is scored with the segmentation prior (``full+prior``,
    ``full+prior@n_prototypes:24``)."""
    return str(name).split("@")[0].endswith(PRIOR_SUFFIX)


def parse_variant(name: str) -> tuple[str, dict[str, Any]]:
    """``"full@n_prototypes:24@alpha:5.0"`` -> ``("full", {"n_prototypes": 24, "alpha": 5.0})``.

    A *configuration* is a variant name with parameter overrides after ``@`` (``key:value``,
    repeated; values are Python literals, else strings such as ``auto``). The syntax passes
    through Hydra's command line (``variants=[bb,full@n_prototypes:24]``) and YAML unquoted.
    A ``+prior`` suffix on the name (``full+prior@n_prototypes:24``) is not part of the base
    (``"full"``); :func:`takes_prior` reads it. Nor is ``@layer:<block>`` one of the
    overrides; :func:`variant_layer` reads it.
    """
    base, *items = str(name).split("@")
    base = base.removesuffix(PRIOR_SUFFIX)
    overrides: dict[str, Any] = {}
    for item in items:
        key, sep, text = item.partition(":")
        if not sep or not key:
            raise ValueError(f"{name!r}: expected <variant>@<key>:<value>[@<key>:<value>...]")
        try:
            overrides[key] = ast.literal_eval(text)
        except (ValueError, SyntaxError):
            overrides[key] = text
    overrides.pop(LAYER_KEY, None)
    return base, overrides


def variant_layer(name: str) -> int | None:
    """The encoder block of ``@layer:<block>`` in configuration ``name`` (``"lite@layer:5"`` ->
    5, negative counts from the end), or ``None`` (the encoder's own intermediates). A value
    that is not an integer is a ValueError naming the configuration."""
    layer = None
    for item in str(name).split("@")[1:]:
        key, _, text = item.partition(":")
        if key == LAYER_KEY:
            try:
                layer = ast.literal_eval(text)
            except (ValueError, SyntaxError):
                layer = text
            if isinstance(layer, bool) or not isinstance(layer, int):
                raise ValueError(f"{name!r}: @{LAYER_KEY}: takes a block index, got {text!r}")
    return layer
