"""The ReSiReg variant names and the configuration syntax, without importing torch.

The config checks (``resireg_train.validation``) need them before anything heavy is loaded,
so a bad ``variants=`` value is reported in a fraction of a second; the factories live in
:mod:`resireg.variants`.
"""

from __future__ import annotations

import ast
from typing import Any

__all__ = ["VARIANTS", "parse_variant"]

#: Names of :func:`resireg.variants.build_variant`, in the report order of the paper's Table 1.
VARIANTS: tuple[str, ...] = ("bb", "calib", "lite", "full")


def parse_variant(name: str) -> tuple[str, dict[str, Any]]:
    """``"full@n_prototypes:24@alpha:5.0"`` -> ``("full", {"n_prototypes": 24, "alpha": 5.0})``.

    A *configuration* is a variant name with parameter overrides after ``@`` (``key:value``,
    repeated; values are Python literals, else strings such as ``auto``). The syntax passes
    through Hydra's command line (``variants=[bb,full@n_prototypes:24]``) and YAML unquoted.
    """
    base, *items = str(name).split("@")
    overrides: dict[str, Any] = {}
    for item in items:
        key, sep, text = item.partition(":")
        if not sep or not key:
            raise ValueError(f"{name!r}: expected <variant>@<key>:<value>[@<key>:<value>...]")
        try:
            overrides[key] = ast.literal_eval(text)
        except (ValueError, SyntaxError):
            overrides[key] = text
    return base, overrides
