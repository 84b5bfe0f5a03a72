"""Segmentation priors for ReSiReg: instance-id maps ``[B, H, W]`` (0 = none) from images.

A prior provider is any callable ``images -> LongTensor [B, H, W]``; ReSiReg Full and Lite
take its output as ``prior`` (docs/design.md sections 4.2, 4.3, 4.3c) and
``DenseEncoder.encode_image(..., prior=provider)`` calls it on the images it encodes.

- :class:`SamPrior`: SAM 2.1 automatic masks through Hugging Face ``transformers``
  (``Sam2Model`` + the ``mask-generation`` pipeline),
- :func:`build_prior`: a provider from a config entry (``conf/prior/sam2.yaml``),
- :func:`masks_to_instances`: overlapping binary masks -> one instance-id map (the
  smaller mask wins; see its docstring).

Imports torch only; ``transformers`` loads when a :class:`SamPrior` is built.
"""

from __future__ import annotations

from resireg.priors.sam import PRIOR_KINDS, SAM_DEFAULTS, SamPrior, build_prior, masks_to_instances

__all__ = ["PRIOR_KINDS", "SAM_DEFAULTS", "SamPrior", "build_prior", "masks_to_instances"]
