"""Segmentation priors for ReSiReg: instance-id maps ``[B, H, W]`` (0 = none) from images.

A prior provider is any callable ``images -> LongTensor [B, H, W]``; ReSiReg Full and Lite
take its output as ``prior`` (docs/method.md#resireg-full) and
``DenseEncoder.encode_image(..., prior=provider)`` calls it on the images it encodes.

- :class:`SamPrior`: SAM 2.1 automatic masks through Hugging Face ``transformers``
  (``Sam2Model`` + the ``mask-generation`` pipeline),
- :func:`build_prior`: a provider from a config entry (``conf/prior/sam2.yaml``),
- :func:`masks_to_instances`: overlapping binary masks -> one instance-id map (the
  smaller mask wins; see its docstring).

The names load on first use (PEP 562): :mod:`resireg.specs.priors` (the settings and
their rules) imports no torch; the rest imports torch, and ``transformers`` loads when a
:class:`SamPrior` is built.

Imports ``resireg.models`` and ``resireg.specs``. May be imported by ``resireg.mapping``,
``deploy``, ``ros2`` and ``resireg_train`` (their kinds: :data:`resireg.specs.priors.PRIOR_SPECS`).
"""

from __future__ import annotations

from resireg import lazy_names

__all__ = [
    "PRIOR_KINDS",
    "SAM_DEFAULTS",
    "SAM_MODEL",
    "SAM_RULES",
    "SamPrior",
    "build_prior",
    "check_sam_source",
    "masks_to_instances",
]

_SOURCES = {
    "PRIOR_KINDS": "resireg.specs.priors",
    "SAM_DEFAULTS": "resireg.specs.priors",
    "SAM_MODEL": "resireg.specs.priors",
    "SAM_RULES": "resireg.specs.priors",
    "SamPrior": "resireg.priors.sam",
    "build_prior": "resireg.priors.sam",
    "check_sam_source": "resireg.priors.sam",
    "masks_to_instances": "resireg.priors.sam",
}

__getattr__ = lazy_names("resireg.priors", _SOURCES)
