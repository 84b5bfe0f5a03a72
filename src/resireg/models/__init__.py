"""Dense encoders: the interface (``encoder``, ``images``; ``hub`` and ``frozen`` for loaders), the
encoder zoo (``zoo/``) and the 25M dense VLM with its parts (``vlm/``: EUPE, head, SigLIP 2 text);
``encoders`` builds any of them by kind, the kinds being the table of
:mod:`resireg.specs.encoders`.

Imports ``resireg.specs``, ``resireg.errors`` and ``resireg.integrity``. May be imported by ``resireg.sources``, the method's variants,
``resireg.priors``, ``mapping``, ``deploy``, ``ros2`` and ``resireg_train``.
"""

from resireg.models.factory import ENCODERS, build_encoder, count_parameters
from resireg.models.hub import WeightsUnavailableError
from resireg.models.interface import DenseEncoder, DenseOutput, InputRule
from resireg.models.vlm import (
    EUPE_MODELS,
    BackboneOutput,
    EUPEBackbone,
    FrozenTextTower,
    HeadOutput,
    LanguageHead,
    ResiregVLM,
    TextProjection,
    dense_text_half,
)
from resireg.models.zoo import (
    CLIP_MODELS,
    ClipEncoder,
    DinoTxtEncoder,
    OtasEncoder,
    RadioEncoder,
    RadSegEncoder,
    TipsEncoder,
)

__all__ = [
    "DenseEncoder",
    "DenseOutput",
    "InputRule",
    "ENCODERS",
    "build_encoder",
    "count_parameters",
    "CLIP_MODELS",
    "ClipEncoder",
    "DinoTxtEncoder",
    "RadioEncoder",
    "RadSegEncoder",
    "TipsEncoder",
    "OtasEncoder",
    "EUPE_MODELS",
    "BackboneOutput",
    "EUPEBackbone",
    "HeadOutput",
    "LanguageHead",
    "WeightsUnavailableError",
    "FrozenTextTower",
    "TextProjection",
    "dense_text_half",
    "ResiregVLM",
]
