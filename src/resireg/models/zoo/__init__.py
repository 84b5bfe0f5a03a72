"""The encoder zoo: third-party dense encoders behind the :class:`~resireg.models.DenseEncoder`
interface (CLIP, RADIO / RADSeg, dino.txt, TIPSv2, OTAS), each loaded through its own upstream
code (open_clip, ``torch.hub``, the release's files).

May be imported by the encoder builder (:mod:`resireg.models.factory`, through the encoder
table's names) and, for RADSeg's loader, ``resireg_train.training``; tests and benchmarks.
"""

from resireg.models.zoo.clip import CLIP_MODELS, ClipEncoder
from resireg.models.zoo.dinotxt import DinoTxtEncoder
from resireg.models.zoo.otas import OtasEncoder
from resireg.models.zoo.radio import RadioEncoder
from resireg.models.zoo.radseg import RadSegEncoder
from resireg.models.zoo.tips import TipsEncoder

__all__ = [
    "CLIP_MODELS",
    "ClipEncoder",
    "DinoTxtEncoder",
    "OtasEncoder",
    "RadioEncoder",
    "RadSegEncoder",
    "TipsEncoder",
]
