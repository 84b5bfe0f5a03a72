"""Dense SigLIP 2-aligned teachers for stage-1 patch distillation.

:class:`RadSegTeacher` loads RADSeg through ``torch.hub`` (``RADSeg-OVSS/RADSeg``, entry
``radseg_encoder``, or a local clone with ``source="local"``). What its code does, and
therefore how we call it (read from the repository's ``hubconf.py`` and
``radseg/radseg.py``):

- ``radseg_encoder(model_version, lang_model, scra_scaling, scga_scaling, **kwargs)``
  builds ``RADSegEncoder``, which itself ``torch.hub.load``s ``NVlabs/RADIO``'s
  ``radio_model`` with the language adaptor (``siglip2``) and the SAM adaptor, detaches
  the adaptors, and replaces the last block's attention by self-correlating recursive
  attention (SCRA).
- It expects RGB in ``[0, 1]`` (RADIO normalises internally) at a resolution RADIO
  supports (``get_nearest_size``).
- ``encode_image_to_feat_map(rgb)`` returns RADIO's spatial features ``[B, C, h, w]``
  after self-correlating global aggregation (SCGA); with ``predict=False`` (the default)
  it returns just that map. ``slide_crop > 0`` (default 336) runs sliding-window
  inference; we default to ``slide_crop=0`` (one pass), the setting for training crops.
- ``align_spatial_features_with_language(feat_map)`` applies the SigLIP 2 adaptor's
  ``head_mlp`` per location -> language-aligned dense features ``[B, C_lang, h, w]``.

- ``RADSegEncoder`` is a plain object, not an ``nn.Module``: it takes a ``device`` when it
  is built and keeps RADIO there, so ``.to()`` of a parent module never reaches it. The
  teacher is therefore built in each process on that process's device (the training
  module does it in ``setup``), and inputs are moved to the encoder's device.

The teacher output is resized (bilinear) to the student's patch grid. A learned Linear
(teacher dim -> 512) in the training module is the distillation head. The kinds
(``model.teacher.kind``) are the entries of the teacher table,
:data:`resireg_train.training.specs.TEACHER_SPECS`, which :func:`build_teacher` reads.
"""

from __future__ import annotations

from abc import ABC, abstractmethod
from collections.abc import Sequence
from typing import Any

import torch
import torch.nn.functional as F
from timm.data import IMAGENET_DEFAULT_MEAN, IMAGENET_DEFAULT_STD
from torch import Tensor, nn

from resireg.errors import parameters
from resireg.models.frozen import FrozenModule
from resireg.models.zoo.radseg import load_radseg
from resireg_train.config.errors import config_path
from resireg_train.training.specs import TEACHER_SPECS

__all__ = ["ConvTeacher", "FrozenTeacher", "RadSegTeacher", "build_teacher"]


class FrozenTeacher(FrozenModule, ABC):
    """A frozen teacher: ``dense`` features resized to the student's grid."""

    out_dim: int

    @abstractmethod
    def dense(self, images: Tensor) -> Tensor:
        """Teacher features ``[B, out_dim, h, w]`` at the teacher's own resolution."""

    def forward(self, images: Tensor, grid: Sequence[int]) -> Tensor:
        """Dense teacher features ``[B, out_dim, *grid]`` for ``images`` (normalised like the student's)."""
        with torch.no_grad():
            feats = self.dense(images).float()
        return F.interpolate(feats, size=tuple(grid), mode="bilinear", align_corners=False)


class RadSegTeacher(FrozenTeacher):
    """RADSeg (RADIO + SigLIP 2 adaptor) dense features.

    Args:
        mean, std: normalisation of the student's images, undone before RADIO.
        slide_crop: RADSeg's sliding-window crop (0 = single pass).
        device: where RADSeg builds and runs RADIO (default: CPU); inputs are moved there
            and outputs moved back to the input's device.
        config_key: the config prefix named in errors.
        **radseg: the keywords of the one RADSeg loader, :func:`resireg.models.zoo.radseg.
            load_radseg`, with its defaults (those of conf/encoder/radseg.yaml and
            conf/model/teacher/radseg.yaml): ``repo`` (``owner/name`` on GitHub, or a local
            clone with ``source="local"``), ``source``, ``model_version`` (RADIO's),
            ``lang_model`` (its language adaptor), ``ref`` / ``radio_ref`` (the pinned commits of
            RADSeg and of the RADIO it loads itself), and ``radseg_encoder``'s own.
    """

    def __init__(
        self,
        mean: Sequence[float] = IMAGENET_DEFAULT_MEAN,
        std: Sequence[float] = IMAGENET_DEFAULT_STD,
        slide_crop: int = 0,
        device: str | torch.device | None = None,
        config_key: str = "model.teacher",
        **radseg: Any,
    ) -> None:
        super().__init__()
        self.encoder_device = torch.device(device if device is not None else "cpu")
        with config_path(config_key, parameters(load_radseg)):  # errors: model.teacher.repo=
            self.encoder = load_radseg(
                device=self.encoder_device,
                hint_extra=", or disable distillation (model.loss.distill.scale=0)",
                slide_crop=slide_crop, **radseg,
            )  # fmt: skip
        self.register_buffer("mean", torch.tensor(mean).view(1, 3, 1, 1), persistent=False)
        self.register_buffer("std", torch.tensor(std).view(1, 3, 1, 1), persistent=False)
        probe = torch.zeros(1, 3, 224, 224, device=self.encoder_device)
        self.out_dim = int(self._language_map(probe).shape[1])
        self.freeze()

    def dense(self, images: Tensor) -> Tensor:
        rgb = (images * self.std + self.mean).clamp(0, 1).to(self.encoder_device)
        return self._language_map(rgb).to(images.device)

    def _language_map(self, rgb: Tensor) -> Tensor:
        """RADSeg's language-aligned map of RGB in [0, 1] on the encoder's device."""
        h, w = self.encoder.get_nearest_size(*rgb.shape[-2:])
        if (h, w) != tuple(rgb.shape[-2:]):
            rgb = F.interpolate(rgb, size=(h, w), mode="bilinear", align_corners=False)
        feat_map = self.encoder.encode_image_to_feat_map(rgb)
        return self.encoder.align_spatial_features_with_language(feat_map)


class ConvTeacher(FrozenTeacher):
    """A small random conv net standing in for RADSeg offline (tests, smoke runs).

    Two stride-4 convolutions give a 1/16-resolution map of ``out_dim`` channels, on
    ``device`` (default CPU).
    """

    def __init__(
        self,
        out_dim: int = 48,
        hidden: int = 16,
        seed: int = 0,
        device: str | torch.device | None = None,
    ) -> None:
        super().__init__()
        with torch.random.fork_rng(devices=[]):
            torch.manual_seed(seed)
            self.net = nn.Sequential(
                nn.Conv2d(3, hidden, 4, stride=4),
                nn.GELU(),
                nn.Conv2d(hidden, out_dim, 4, stride=4),
            )
        self.out_dim = out_dim
        self.freeze()
        self.to(device or "cpu")

    def dense(self, images: Tensor) -> Tensor:
        return self.net(images)


def build_teacher(
    kind: str, device: str | torch.device | None = None, **kwargs: Any
) -> FrozenTeacher:
    """The teacher of ``kind`` (an entry of :data:`~resireg_train.training.specs.TEACHER_SPECS`:
    ``radseg`` -> :class:`RadSegTeacher`, ``conv`` -> :class:`ConvTeacher`) built with
    ``kwargs`` on ``device``; an unknown kind names the closest ones."""
    return TEACHER_SPECS.load(kind)(device=device, **kwargs)
