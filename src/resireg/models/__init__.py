"""Dense encoders: the interface, the encoder zoo (CLIP, RADIO, RADSeg, dino.txt) and the
25M dense VLM with its parts (EUPE, head, SigLIP 2 text, teachers)."""

from resireg.models.clip import CLIP_MODELS, ClipEncoder
from resireg.models.dinotxt import DinoTxtEncoder
from resireg.models.encoder import DenseEncoder, DenseOutput, InputRule
from resireg.models.encoders import ENCODERS, build_encoder, count_parameters
from resireg.models.eupe import EUPE_MODELS, BackboneOutput, EUPEBackbone
from resireg.models.head import HeadOutput, LanguageHead
from resireg.models.hub import WeightsUnavailableError
from resireg.models.otas import OtasEncoder
from resireg.models.radio import RadioEncoder, RadSegEncoder
from resireg.models.teacher import ConvTeacher, RadSegTeacher, build_teacher
from resireg.models.text import FrozenTextTower, TextProjection, dense_text_half
from resireg.models.tips import TipsEncoder
from resireg.models.vlm import ResiregVLM

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
    "ConvTeacher",
    "RadSegTeacher",
    "build_teacher",
    "FrozenTextTower",
    "TextProjection",
    "dense_text_half",
    "ResiregVLM",
]

#: Model sizes used by tests and the smoke experiment: same architectures, tiny widths.
TINY_BACKBONE = {
    "model_name": "eupe_vit_s16",
    "weights": None,
    "embed_dim": 64,
    "depth": 2,
    "num_heads": 2,
}
TINY_HEAD = {"out_dim": 48, "num_heads": 8, "drop_path": 0.0}
TINY_TEXT = {
    "kind": "tiny",
    "width": 64,
    "layers": 2,
    "heads": 2,
    "out_dim": 96,
    "context_length": 32,
}
