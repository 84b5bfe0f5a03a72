"""The ReSiReg variants: one entry each, in the report order of the paper's Table 1, and the
configuration syntax that names them (``full+prior@n_prototypes:24``).

Every reader takes the names, classes and parameter rules from :data:`VARIANT_SPECS`:
:func:`resireg.method.variants.build_variant` (the class), the classes' ``__init__`` (the rules),
``resireg_train.checks.eval`` (``full.alpha=...`` and ``variants=[...]`` checks), the training
callback and ``resireg-eval`` (which settings are a variant's), the report (labels, order,
the baseline of the deltas) and the playground (titles). Defaults live in
``conf/resireg/default.yaml`` (one block per variant with parameters); the classes' own
keyword defaults equal them (tests/resireg/specs/test_specs.py composes the config and compares).

Adding a variant: a module with the class (``variant(intermediates, language, prior=None) ->
[B, Dl, h, w]``, checking its keywords with :func:`check_variant_kwargs`), one
:class:`VariantSpec` below (its parameter rules), one block of defaults under its name in
``conf/resireg/default.yaml``. The factory (:func:`resireg.method.variants.build_variant`), the config
checks, the report and the playground then know it; ``tests/resireg/specs/test_tables.py`` checks the entry.

The configuration syntax (:func:`parse_variant`) is read by the config checks before torch
loads, so a bad ``variants=`` value is reported in a fraction of a second.
"""

from __future__ import annotations

import ast
import os
from collections.abc import Sequence
from dataclasses import dataclass, field
from typing import Any

from resireg.specs.rules import Rule, integer, interval, is_int, number, one_of, optional_int
from resireg.specs.table import SpecTable

__all__ = [
    "BASELINE",
    "DEFAULTS_FILE",
    "LAYER_KEY",
    "LITE_ATTENTION",
    "PARAM_VARIANTS",
    "PRIOR_SUFFIX",
    "PRIOR_VARIANTS",
    "VARIANTS",
    "VARIANT_SPECS",
    "VariantSpec",
    "build_variant",
    "check_variant_kwargs",
    "parse_variant",
    "takes_prior",
    "variant_layer",
]

#: Where the variants' defaults live (the ``resireg`` config group; key = the variant name).
DEFAULTS_FILE = "conf/resireg/default.yaml"

#: How ReSiReg Lite computes its attention (``lite.attention``, docs/method.md#resireg-lite):
#: ``auto`` (by device: ``sdpa`` on CUDA, ``factorised`` elsewhere), ``sdpa`` (PyTorch's fused
#: attention on the upsampled points) or ``factorised`` (from the coarse grid's Gram matrix).
LITE_ATTENTION: tuple[str, ...] = ("auto", "sdpa", "factorised")


@dataclass(frozen=True)
class VariantSpec:
    """One variant: ``variant(intermediates, language, prior=None) -> [B, Dl, h, w]``.

    Attributes:
        name: the config name (``variants=[..., name]``, the ``<name>.<key>`` settings).
        target: its class, ``"module:Class"`` (loaded on first build).
        label: its name in reports and table columns (``Full``).
        title: its name in the playground (``ReSiReg Full``).
        params: ``keyword -> rule`` of the class (the class checks them with the same rules).
        takes_prior: whether ``<name>+prior`` is scored with a segmentation prior.
    """

    name: str
    target: str
    label: str
    title: str
    params: dict[str, Rule] = field(default_factory=dict)
    takes_prior: bool = False

    @property
    def defaults(self) -> str:
        """Where this variant's defaults live: ``<file>:<key>``."""
        return f"{DEFAULTS_FILE}:{self.name}"

    def load(self) -> Any:
        """The class (imports torch)."""
        from resireg.specs.table import load

        return load(self.target)


_TAU = interval(0, 1)

VARIANT_SPECS: SpecTable[VariantSpec] = SpecTable(
    "ReSiReg variant",
    (
        VariantSpec("bb", "resireg.method.variants:BackboneOnly", "BB", "BB (language tokens)"),
        VariantSpec(
            "calib",
            "resireg.method.calib:Calib",
            "Calib",
            "Calib (SC-CLIP self-calibration)",
            {"n_neighbors": integer(1), "contamination": interval(0, 0.5), "threshold": _TAU},
        ),
        VariantSpec(
            "lite",
            "resireg.method.lite:ReSiRegLite",
            "Lite",
            "ReSiReg Lite",
            {
                "alpha": number(0, strict=True, finite=True),
                "tau": _TAU,
                "upscale": integer(1),
                "attention": one_of(LITE_ATTENTION),
            },
            takes_prior=True,
        ),
        VariantSpec(
            "full",
            "resireg.method.full:ReSiRegFull",
            "Full",
            "ReSiReg Full",
            {
                "n_prototypes": (
                    (lambda v: v in ("auto", "elbo") or (is_int(v) and v >= 1)),
                    "an integer >= 1, 'auto' (the fitted heuristic) or 'elbo' (chosen per batch)",
                ),
                "elbo_candidates": (
                    (
                        lambda v: (
                            v is None
                            or (
                                isinstance(v, Sequence)
                                and not isinstance(v, str)
                                and len(v) > 0
                                and all(is_int(c) and c >= 1 for c in v)
                            )
                        )
                    ),
                    "null or a non-empty list of integers >= 1",
                ),  # fmt: skip
                "n_components": optional_int(1),
                "heuristic": (
                    (lambda v: v is None or isinstance(v, (str, os.PathLike)) or callable(v)),
                    "null, a prototype_heuristic.json path or a callable",
                ),
                "alpha": number(0, strict=True, finite=True),
                "tau": _TAU,
                "upscale": integer(1),
                "seed": (is_int, "an integer"),
                "max_iter": integer(1),
                "tol": number(0, finite=True),
                "elbo_max_points": integer(1),
                "elbo_stop_after": optional_int(1),
                "elbo_tol": number(0, strict=True, finite=True),
            },
            takes_prior=True,
        ),
    ),
    where="resireg.specs.variants",
)

#: Variant names, in the report order of the paper's Table 1 (BB, Calib, Lite, Full).
VARIANTS: tuple[str, ...] = tuple(VARIANT_SPECS)
#: Variants that take parameters (``calib``, ``lite``, ``full``): each has a block of them in
#: :data:`DEFAULTS_FILE` under its name (``resireg-map``'s ``params``, the callback's settings).
PARAM_VARIANTS: tuple[str, ...] = tuple(n for n, s in VARIANT_SPECS.items() if s.params)
#: Variants that take a segmentation prior (``full+prior``).
PRIOR_VARIANTS: tuple[str, ...] = tuple(n for n, s in VARIANT_SPECS.items() if s.takes_prior)
#: The variant the report's deltas are measured against (the backbone alone).
BASELINE = "bb"


def build_variant(name: str, **kwargs: Any) -> Any:
    """The variant ``name`` (a torch module) built with ``kwargs`` (``bb`` takes none); its
    class is imported now, from the table's ``target``. The encoder interface
    (:meth:`resireg.models.DenseEncoder.encode_image`) builds named variants through this, so it
    depends on the table, not on the method's modules."""
    if name not in VARIANT_SPECS:
        raise ValueError(f"unknown ReSiReg variant {name!r}; choose from {list(VARIANTS)}")
    spec = VARIANT_SPECS[name]
    if not spec.params and kwargs:
        raise ValueError(f"variant {name!r} takes no parameters, got {sorted(kwargs)}")
    return spec.load()(**kwargs)


def check_variant_kwargs(name: str, values: dict[str, Any]) -> None:
    """The rules of variant ``name`` on a class's keywords (``ValueError`` naming the first
    bad one: ``alpha must be a number > 0 (finite), got -1.0``)."""
    from resireg.specs.rules import check_kwargs

    check_kwargs(VARIANT_SPECS[name].params, values)


#: ``<variant>+prior``: the configuration is called with the segmentation prior
#: (``full+prior``, ``lite+prior@alpha:5.0``); only the variants that use one take it
#: (:data:`PRIOR_VARIANTS`).
PRIOR_SUFFIX = "+prior"

#: ``<variant>@layer:<block>``: the configuration runs on that encoder block's intermediates
#: (``lite@layer:5``; the CLIP layer sweep). It is an instruction to the evaluation, not a
#: parameter of the variant: :func:`parse_variant` leaves it out.
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
