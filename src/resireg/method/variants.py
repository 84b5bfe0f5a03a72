"""The ReSiReg variant factory: one name + its keyword arguments -> a module.

Every variant is called the same way, ``variant(intermediates, language, prior=None)``,
and returns unit-norm dense language features ``[B, Dl, h, w]``:

- ``bb``: the backbone's own language tokens, normalised (no reconstruction),
- ``calib``: :class:`~resireg.method.calib.Calib`, SC-CLIP's self-calibration made
  backbone-generic (LOF anomaly resolution, then aggregation with thresholded
  intermediate affinities; ``[B, Dl, Hv, Wv]``, the prior is ignored),
- ``lite``: :class:`~resireg.method.lite.ReSiRegLite`,
- ``full``: :class:`~resireg.method.full.ReSiRegFull`.

:data:`VARIANTS` lists them in the report order of the paper's Table 1 (BB, Calib, Lite,
Full). The evaluation engine, the training callback and ``DenseEncoder.encode_image`` build
variants only through :func:`build_variant`, which takes each class from the variant table
(:data:`resireg.specs.variants.VARIANT_SPECS`): a new variant is one module, one entry there
and its defaults in ``conf/resireg/default.yaml`` (docs/architecture.md#spec-tables).
"""

from __future__ import annotations

from collections.abc import Mapping
from typing import Any

import torch.nn.functional as F
from torch import Tensor, nn

from resireg.errors import ConfigError
from resireg.method.full import FullShared, ReSiRegFull
from resireg.specs.variants import (
    PRIOR_VARIANTS,
    VARIANT_SPECS,
    VARIANTS,
    build_variant,
    parse_variant,
    takes_prior,
)

__all__ = [
    "VARIANTS",
    "BackboneOnly",
    "apply_variant",
    "build_variant",
    "build_variants",
    "parse_variant",
]


class BackboneOnly(nn.Module):
    """The ``bb`` variant: the language tokens as they are, L2-normalised over channels."""

    def forward(
        self, intermediates: Tensor, language: Tensor, prior: Tensor | None = None
    ) -> Tensor:
        return F.normalize(language.float(), dim=1)


def build_variants(
    names: list[str] | tuple[str, ...],
    params: Mapping[str, Mapping[str, Any] | None] | None = None,
) -> dict[str, nn.Module]:
    """``{name: variant}`` for each name, in order: the variant of :func:`parse_variant`'s
    base name built with ``params[base]`` updated by the name's overrides. The evaluation
    scores every configuration on the same encoded batch, so ``["full@n_prototypes:24",
    "full@n_prototypes:36"]`` costs one encoder pass for both.

    Args:
        names: variant names (see :data:`VARIANTS`) or configurations (``full@n_prototypes:24``;
            ``full+prior`` is built as ``full``, the caller passes it the prior).
        params: per-variant keyword arguments, e.g. ``{"full": {"n_prototypes": 36}}``;
            entries for variants not named are ignored.
    """
    if not names:
        raise ConfigError(f"names=[]: name at least one of {list(VARIANTS)}")
    parsed = {n: parse_variant(n) for n in names}
    bad = [n for n, (base, _) in parsed.items() if base not in VARIANT_SPECS]
    if bad:
        raise ConfigError(f"names={list(names)}: unknown {bad}; choose from {list(VARIANTS)}")
    if len(parsed) != len(names):
        raise ConfigError(f"names={list(names)}: a name appears twice")
    bad = [n for n, (base, _) in parsed.items() if takes_prior(n) and base not in PRIOR_VARIANTS]
    if bad:
        raise ConfigError(
            f"names={list(names)}: {bad} cannot take a prior; +prior applies to "
            f"{list(PRIOR_VARIANTS)}"
        )
    params = params or {}
    return {
        n: build_variant(base, **{**dict(params.get(base) or {}), **overrides})
        for n, (base, overrides) in parsed.items()
    }


def apply_variant(
    variant: nn.Module,
    intermediates: Tensor,
    language: Tensor,
    prior: Tensor | None = None,
    shared: dict[Any, Any] | None = None,
) -> Tensor:
    """``variant(intermediates, language, prior)``, reusing what the configurations of one
    batch compute identically.

    ``shared`` is one dict per encoded batch, passed to every configuration scored on it:
    ReSiReg Full configurations with the same ``upscale`` then decompose the covariance
    and resize the language tokens once (:class:`~resireg.method.full.FullShared`), whatever
    their prototype and component counts. Results equal each configuration run alone.
    """
    if shared is not None and isinstance(variant, ReSiRegFull):
        key = (FullShared, variant.upscale)
        if key not in shared:
            shared[key] = FullShared(intermediates, language, variant.upscale)
        return variant(intermediates, language, prior, shared=shared[key])
    return variant(intermediates, language, prior)
