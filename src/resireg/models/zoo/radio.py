"""C-RADIO (NVlabs/RADIO) as a :class:`DenseEncoder`, and the helpers RADSeg
(:mod:`resireg.models.zoo.radseg`) builds on.

It loads through ``torch.hub`` (``source="github"``, or a local clone with
``source="local"``). What the real code does, and therefore how we call it:

**RADIO** (``NVlabs/RADIO``: ``hubconf.py`` ``radio_model``, ``radio/radio_model.py``
``RADIOModel``, ``radio/adaptor_generic.py`` ``GenericAdaptor``,
``radio/siglip2_adaptor.py`` / ``radio/open_clip_adaptor.py``,
``radio/input_conditioner.py``, ``radio/common.py`` ``RESOURCE_MAP``):

- ``radio_model(version, progress, adaptor_names, ...)`` downloads ``RESOURCE_MAP[version]``
  with ``load_state_dict_from_url`` (the torch hub cache ``<hub>/checkpoints``; a path to
  a checkpoint file works as ``version`` too) and builds, per name in ``adaptor_names``,
  the checkpoint teacher of that name (``ValueError`` listing the known names otherwise):
  a ``GenericAdaptor`` with ``head_mlp`` (the summary / CLS head) and ``feat_mlp`` (the
  patch head); the ``siglip2`` / ``open_clip`` types add ``tokenizer`` and
  ``encode_text(tokens, normalize=False)`` (a Hugging Face SigLIP 2 text model /
  an open_clip model, downloaded when the adaptor is built).
- ``RADIOModel.forward(x, feature_fmt="NLC"|"NCHW")`` conditions ``x`` (RGB in
  ``[0, 1]``) with ``input_conditioner`` (``(x - norm_mean) / norm_std``, values from the
  checkpoint, cast to the checkpoint dtype), runs the ViT and returns
  ``RadioOutput(summary, features)``, or, with adaptors, a dict: ``"backbone"`` ->
  ``RadioOutput`` of the backbone, ``<adaptor>`` -> ``RadioOutput(head_mlp(CLS token of
  the adaptor's slot), feat_mlp(features))`` (float32). Input sides must be multiples of
  ``min_resolution_step`` (the patch size, 16; times the window size with ViTDet).
- ``make_preprocessor_external()`` replaces the conditioner by an identity and returns it,
  so the caller normalises.

Versions: C-RADIOv3 ``c-radio_v3-{b,l,h,g}``, C-RADIOv4 ``c-radio_v4-so400m`` and
``c-radio_v4-h`` (all patch 16). Language adaptors: RADIO's README lists ``clip`` and
``siglip2-g`` for C-RADIOv3 and ``siglip2-g`` for C-RADIOv4; RADSeg (and the RADIO issue
tracker) load C-RADIOv3 with ``siglip2``. The name is the checkpoint's teacher name, so
:data:`DEFAULT_ADAPTORS` holds our defaults and a wrong name fails with RADIO's list.

:class:`RadioEncoder`, one pass ``model(x, feature_fmt="NCHW")``:

- ``intermediates`` ``[B, C, h, w]``: ``out["backbone"].features`` (the shared
  backbone's spatial tokens, after RADIO's feature normaliser when the checkpoint has one),
- ``language`` ``[B, D_text, h, w]``: the adaptor's *summary* head ``head_mlp`` applied to
  every spatial token of ``intermediates`` (the CLS/patch head swap of RayFronts'
  ``NARadioEncoder`` / ``RadioEncoder(use_summ_proj_for_spatial=True)`` and RADSeg's
  ``align_spatial_features_with_language``), float32,
- ``embedding`` ``[B, D_text]``: ``out[adaptor].summary`` (``head_mlp`` of the adaptor's
  CLS token), float32,
- ``encode_text``: ``adaptor.encode_text(adaptor.tokenizer(texts), normalize=True)``,
  renormalised in float32.

Input rule (RADIO and RADSeg alike, :func:`external_input_rule`): RADIO's conditioner is made external and its ``norm_mean`` /
``norm_std`` become :class:`InputRule`'s ``mean`` / ``std`` (the same affine map RADIO
applies to ``[0, 1]`` RGB), patch size ``min_resolution_step``; inputs are cast to the
conditioner's dtype as RADIO does.

The encoder is frozen (eval, no gradients, forward under ``torch.no_grad``). RADSeg, which
builds RADIO itself, is :mod:`resireg.models.zoo.radseg` (on this module's helpers).
"""

from __future__ import annotations

import os
from collections.abc import Sequence
from typing import Any

import torch
import torch.nn.functional as F
from torch import Tensor, nn

from resireg.errors import ConfigError
from resireg.models.frozen import FrozenModule
from resireg.models.hub import (
    PINNED_REFS,
    check_hub_source,
    hub_repo_cached,
    hub_target,
    require_hub_checkpoints,
)
from resireg.models.interface import DenseEncoder, DenseOutput, InputRule

__all__ = [
    "DEFAULT_ADAPTORS",
    "RADIO_CHECKPOINTS",
    "RADIO_REF",
    "RADIO_REPO",
    "RadioEncoder",
    "apply_summary_head",
    "external_input_rule",
    "radio_hub_cached",
    "require_radio_weights",
]

#: RADIO checkpoints (``radio/common.py`` ``RESOURCE_MAP``) by version: the file name that
#: ``load_state_dict_from_url`` keeps in ``<torch.hub.get_dir()>/checkpoints``.
RADIO_CHECKPOINTS = {
    "c-radio_v3-b": "c-radio_v3-b_half.pth.tar",
    "c-radio_v3-l": "c-radio-v3_l_half.pth.tar",
    "c-radio_v3-h": "c-radio_v3-h_half.pth.tar",
    "c-radio_v3-g": "c-radio_v3-g_half.pth.tar",
    "c-radio_v4-so400m": "c-radio_v4-so400m_half.pth.tar",
    "c-radio_v4-h": "c-radio_v4-h_half.pth.tar",
}

#: SigLIP 2 language adaptor used when ``adaptor`` is not given, by version prefix.
DEFAULT_ADAPTORS = {"c-radio_v3": "siglip2", "c-radio_v4": "siglip2-g"}

#: where RADIO's checkpoints are downloaded from; RADIO's hub repository (RADSeg loads it too).
_WEIGHTS_HOST = "huggingface.co"
RADIO_REPO = "NVlabs/RADIO"


# ------------------------------------------------------------------ shared helpers
def radio_hub_cached(ref: str | None = None) -> str | None:
    """torch's hub cache directory of ``NVlabs/RADIO`` at ``ref`` (``None``: ``main`` or
    ``master``), or ``None``.

    ``torch.hub.load("NVlabs/RADIO[:ref]", ...)`` (what RADSeg calls) uses it without GitHub.
    """
    return hub_repo_cached(RADIO_REPO, ref)


def require_radio_weights(version: str, hint: str) -> None:
    """Fail at once when RADIO ``version``'s checkpoint is neither cached nor downloadable.

    Only versions of :data:`RADIO_CHECKPOINTS` are checked (a checkpoint path, or an unknown
    version, is left to RADIO).
    """
    ckpt = RADIO_CHECKPOINTS.get(version)
    if ckpt is not None:
        require_hub_checkpoints([ckpt], "RADIO weights", _WEIGHTS_HOST, hint)


#: The pinned commit of RADIO's code (:data:`resireg.models.hub.PINNED_REFS`).
RADIO_REF = PINNED_REFS[RADIO_REPO]


def external_input_rule(radio: nn.Module) -> tuple[InputRule, torch.dtype | None]:
    """Take a ``RADIOModel``'s input conditioner out of it and express it as an :class:`InputRule`.

    Calls ``radio.make_preprocessor_external()`` (the model no longer normalises) and returns
    ``(InputRule(min_resolution_step, norm_mean, norm_std), conditioner dtype)``.
    """
    cond = radio.make_preprocessor_external()
    mean = tuple(float(v) for v in cond.norm_mean.detach().float().flatten().tolist())
    std = tuple(float(v) for v in cond.norm_std.detach().float().flatten().tolist())
    if len(mean) != 3 or len(std) != 3:
        raise ValueError(f"RADIO's conditioner has {len(mean)} channels; expected 3")
    return InputRule(int(radio.min_resolution_step), mean, std), getattr(cond, "dtype", None)


def apply_summary_head(head_mlp: nn.Module, features: Tensor) -> Tensor:
    """A RADIO adaptor's summary head applied at every location of ``[B, C, h, w]`` features.

    Runs in the head's parameter dtype (as ``GenericAdaptor.forward`` does) and returns
    float32 ``[B, D, h, w]``.
    """
    dtype = next(head_mlp.parameters()).dtype
    tokens = features.permute(0, 2, 3, 1).to(dtype)  # [B, h, w, C]
    return head_mlp(tokens).float().permute(0, 3, 1, 2).contiguous()


# ------------------------------------------------------------------ RADIO
class RadioEncoder(DenseEncoder, FrozenModule):
    """Frozen C-RADIO with a language adaptor (see the module docstring).

    Args:
        repo: ``owner/name`` on GitHub, or a local clone of NVlabs/RADIO (``source="local"``).
        source: ``"github"`` or ``"local"``.
        version: RADIO version (``c-radio_v3-b``, ``c-radio_v4-so400m``, ``c-radio_v4-h``,
            ...) or a path to a checkpoint file.
        adaptor: language adaptor (checkpoint teacher) name; ``None`` takes
            :data:`DEFAULT_ADAPTORS` for the version (``clip`` is the other C-RADIOv3 one).
        device: where the model is placed (default CPU).
        ref: the git tag or commit SHA loaded from GitHub (``"repo:ref"``;
            :func:`resireg.models.hub.hub_target`); conf/encoder/radio_*.yaml pin the one the
            adapter was checked against (:data:`RADIO_REF`, the default). ``None``: the
            default branch. Ignored for a local clone.
        **kwargs: passed to ``radio_model`` (e.g. ``vitdet_window_size``) or to
            ``torch.hub.load`` (``force_reload``, ``trust_repo``).
    """

    def __init__(
        self,
        repo: str = "NVlabs/RADIO",
        source: str = "github",
        version: str = "c-radio_v3-b",
        adaptor: str | None = None,
        device: str | torch.device | None = None,
        ref: str | None = RADIO_REF,
        **kwargs: Any,
    ) -> None:
        super().__init__()
        if adaptor is None:
            prefix = next((p for p in DEFAULT_ADAPTORS if version.startswith(p)), None)
            if prefix is None:
                raise ConfigError(
                    f"adaptor is required for version={version!r} "
                    f"(defaults exist for {sorted(DEFAULT_ADAPTORS)})"
                )
            adaptor = DEFAULT_ADAPTORS[prefix]
        hint = (
            f"Clone NVlabs/RADIO elsewhere and pass repo=/path/to/RADIO source=local "
            f"(RADIO's checkpoint must be in {os.path.join(torch.hub.get_dir(), 'checkpoints')}, "
            f"or pass version=/path/to/checkpoint.pth.tar; the adaptor's text model must "
            "be in the Hugging Face cache)."
        )
        check_hub_source(repo, source, "RADIO", hint, ref)
        require_radio_weights(version, hint)
        self.repo, self.source, self.hub_kwargs = repo, source, dict(kwargs)  # (spec)
        target = hub_target(repo, source, ref)
        #: what torch.hub loaded, ``"owner/name:ref"``, or ``None`` (a local clone, unpinned)
        self.ref, self.hub_ref = ref, (target if target != repo else None)
        kwargs.setdefault("progress", False)
        if source == "github":
            kwargs.setdefault("skip_validation", True)
        try:
            model = torch.hub.load(
                target, "radio_model", source=source, version=version,
                adaptor_names=[adaptor], **kwargs,
            )  # fmt: skip
        except ValueError as err:
            if "adaptor" in str(err):
                raise ConfigError(f"adaptor={adaptor!r}: {err}") from err
            raise
        self.version = version
        self.adaptor_name = adaptor
        self.model = model
        self._input_rule, self._input_dtype = external_input_rule(model)
        self.to(torch.device(device) if device is not None else "cpu")
        self.freeze()

    def spec(self) -> dict[str, Any]:
        """``kind`` and the constructor arguments that rebuild this encoder (``device`` aside)."""
        return {
            "kind": "radio",
            "repo": self.repo,
            "source": self.source,
            "ref": self.ref,
            "version": self.version,
            "adaptor": self.adaptor_name,
            **self.hub_kwargs,
        }

    @property
    def adaptor(self) -> nn.Module:
        """The language adaptor (``head_mlp``, ``feat_mlp``, ``tokenizer``, ``encode_text``)."""
        return self.model.adaptors[self.adaptor_name]

    @property
    def input_rule(self) -> InputRule:
        return self._input_rule

    def encode(self, images: Tensor) -> DenseOutput:
        """Normalised images ``[B, 3, H, W]`` -> backbone features, ``head_mlp`` per location,
        the adaptor's summary."""
        self._input_rule.check_size(images, "RADIO's resolution step")
        x = images.to(self.device)
        if self._input_dtype is not None:
            x = x.to(self._input_dtype)
        with torch.no_grad():
            out = self.model(x, feature_fmt="NCHW")
            backbone, lang = out["backbone"], out[self.adaptor_name]
            language = apply_summary_head(self.adaptor.head_mlp, backbone.features)
        return DenseOutput(backbone.features.float(), language, lang.summary.float())

    def encode_text(self, texts: Sequence[str]) -> Tensor:
        """``adaptor.encode_text(adaptor.tokenizer(texts), normalize=True)`` -> ``[K, D_text]``."""
        adaptor = self.adaptor
        with torch.no_grad():
            tokens = adaptor.tokenizer(list(texts)).to(self.device)
            emb = adaptor.encode_text(tokens, normalize=True)
        return F.normalize(emb.float(), dim=-1)
