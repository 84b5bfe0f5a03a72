"""The 25M dense VLM and its parts: the frozen EUPE ViT-S/16 backbone (``eupe``), the trained
language head (``head``), the frozen SigLIP 2 text tower and its trained projection (``text``),
assembled by :class:`ResiregVLM` (``model``).

May be imported by the rest of :mod:`resireg.models` (the encoder builder, by the encoder
table's name), ``resireg.deploy`` (export) and ``resireg_train`` (training, the run's model card); the text tower's
kinds are the table :data:`resireg.specs.text.TEXT_SPECS`.
"""

from resireg.models.vlm.eupe import EUPE_MODELS, BackboneOutput, EUPEBackbone
from resireg.models.vlm.head import HeadOutput, LanguageHead
from resireg.models.vlm.model import ResiregVLM
from resireg.models.vlm.text import FrozenTextTower, TextProjection, dense_text_half

__all__ = [
    "EUPE_MODELS",
    "BackboneOutput",
    "EUPEBackbone",
    "FrozenTextTower",
    "HeadOutput",
    "LanguageHead",
    "ResiregVLM",
    "TextProjection",
    "dense_text_half",
]
