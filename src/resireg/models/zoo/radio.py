"""C-RADIO (NVlabs/RADIO) and RADSeg as :class:`DenseEncoder` s.

Both load through ``torch.hub`` (``source="github"``, or a local clone with
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

**RADSeg** (``RADSeg-OVSS/RADSeg``: ``hubconf.py`` ``radseg_encoder``,
``radseg/radseg.py`` ``RADSegEncoder``): builds RADIO itself with
``torch.hub.load("NVlabs/RADIO", "radio_model", adaptor_names=[lang_model, "sam"])``
(always from GitHub, or torch's hub cache ``<hub>/NVlabs_RADIO_main`` when GitHub is
unreachable; pinned: ``<hub>/NVlabs_RADIO_<radio_ref>``; the repository is hard-coded, so RADSeg's own ``ref`` does not reach it:
:func:`load_radseg` pins that nested call to ``radio_ref`` itself, see there), detaches the adaptors (``model.adaptors = None``, so ``model(x)`` returns
one ``RadioOutput``) and replaces the last block's attention by self-correlating
recursive attention (SCRA). ``encode_image_to_feat_map(rgb)``: ``slide_crop > 0``
(default 336) runs sliding windows, ``slide_crop=0`` one pass ``_single_inference``
(``model(rgb).features`` -> ``[B, C, h, w]``); then self-correlating global aggregation
(SCGA); ``predict=True`` would turn it into class probabilities (with prompt denoising,
``prompt_denoising_thresh``, and optional SAM refinement). ``predict=False`` (default)
returns the aggregated map; ``align_spatial_features_with_language`` applies the language
adaptor's ``head_mlp`` per location. ``encode_prompts(texts)``: tokenizer, ``encode_text``,
each row L2-normalised (``encode_labels`` adds the 80 ImageNet templates, which ReSiReg's
evaluation does itself). RADSeg needs a ``sam`` teacher, which C-RADIOv4 checkpoints do not
list (they have ``sam3``), so RADSeg runs on RADIO v2.5 / C-RADIOv3.

:class:`RadSegEncoder`, one pass with ``slide_crop=0, predict=False,
sam_refinement=False``:

- ``intermediates`` ``[B, C, h, w]``: RADIO's spatial features inside RADSeg (its
  backbone with the SCRA last block), taken from the single ``model(rgb)`` call by a
  forward hook; ``intermediates="aggregated"`` gives the SCGA map instead,
- ``language`` ``[B, D_text, h, w]``:
  ``align_spatial_features_with_language(encode_image_to_feat_map(x))``,
- ``embedding``: ``None``,
- ``encode_text``: ``encode_prompts(texts)``.

Input rule (both): RADIO's conditioner is made external and its ``norm_mean`` /
``norm_std`` become :class:`InputRule`'s ``mean`` / ``std`` (the same affine map RADIO
applies to ``[0, 1]`` RGB), patch size ``min_resolution_step``; inputs are cast to the
conditioner's dtype as RADIO does.

Both encoders are frozen (eval, no gradients, forward under ``torch.no_grad``).
``RADSegEncoder`` is a plain object holding its modules on the ``device`` it was built
for, so :class:`RadSegEncoder` reports and feeds that device; ``.to()`` does not move it.
"""

from __future__ import annotations

import os
from collections.abc import Iterator, Sequence
from contextlib import contextmanager
from typing import Any

import torch
import torch.nn.functional as F
from torch import Tensor, nn

from resireg.errors import ConfigError
from resireg.models.frozen import FrozenModule
from resireg.models.hub import (
    PINNED_REFS,
    check_hub_ref,
    check_hub_source,
    hub_cache_dir,
    hub_repo_cached,
    hub_target,
    require_hub_checkpoints,
    require_hub_repo,
)
from resireg.models.images import tokens_to_grid
from resireg.models.interface import DenseEncoder, DenseOutput, InputRule

__all__ = [
    "RADIO_CHECKPOINTS",
    "RADIO_REF",
    "RADSEG_REF",
    "DEFAULT_ADAPTORS",
    "RadioEncoder",
    "RadSegEncoder",
    "load_radseg",
    "radio_hub_cached",
    "require_radio_for_radseg",
    "require_radio_weights",
    "external_input_rule",
    "apply_summary_head",
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

_WEIGHTS_HOST = "huggingface.co"
_RADIO_REPO = "NVlabs/RADIO"


# ------------------------------------------------------------------ shared helpers
def radio_hub_cached(ref: str | None = None) -> str | None:
    """torch's hub cache directory of ``NVlabs/RADIO`` at ``ref`` (``None``: ``main`` or
    ``master``), or ``None``.

    ``torch.hub.load("NVlabs/RADIO[:ref]", ...)`` (what RADSeg calls) uses it without GitHub.
    """
    return hub_repo_cached(_RADIO_REPO, ref)


def require_radio_for_radseg(ref: str | None = None) -> None:
    """Fail at once when RADSeg could get RADIO's code (at ``ref``) neither from the hub cache
    nor GitHub."""
    target = hub_cache_dir(_RADIO_REPO, ref or "main")
    require_hub_repo(
        _RADIO_REPO,
        "RADSeg loads NVlabs/RADIO through torch.hub and it",
        f"Put a clone of NVlabs/RADIO at {target} (RADIO's checkpoint in "
        f"{os.path.join(torch.hub.get_dir(), 'checkpoints')} and its text model in the "
        "Hugging Face cache).",
        ref,
    )


@contextmanager
def _nested_hub_ref(repo: str, ref: str | None) -> Iterator[None]:
    """While RADSeg builds: its hard-coded ``torch.hub.load(repo, ...)`` (``repo`` without a
    ref: the default branch) loads ``"repo:ref"`` instead. RADSeg's hubconf gives no argument
    for it, so the call is rewritten here, for this thread's load only, and restored after.
    ``ref=None`` leaves it alone."""
    if ref is None:
        yield
        return
    real = torch.hub.load

    def load(repo_or_dir: str, *args: Any, **kwargs: Any) -> Any:
        if repo_or_dir == repo and kwargs.get("source", "github") == "github":
            repo_or_dir = f"{repo}:{ref}"
            kwargs["skip_validation"] = True  # a commit is no branch or tag of the fork check
        return real(repo_or_dir, *args, **kwargs)

    torch.hub.load = load
    try:
        yield
    finally:
        torch.hub.load = real


def require_radio_weights(version: str, hint: str) -> None:
    """Fail at once when RADIO ``version``'s checkpoint is neither cached nor downloadable.

    Only versions of :data:`RADIO_CHECKPOINTS` are checked (a checkpoint path, or an unknown
    version, is left to RADIO).
    """
    ckpt = RADIO_CHECKPOINTS.get(version)
    if ckpt is not None:
        require_hub_checkpoints([ckpt], "RADIO weights", _WEIGHTS_HOST, hint)


#: RADSeg's hub repo, RADIO version and language adaptor by default: those of
#: conf/encoder/radseg.yaml and conf/model/teacher/radseg.yaml, for the one loader and the two
#: modules over it (RadSegEncoder here, the distillation teacher in resireg_train.training).
RADSEG_REPO = "RADSeg-OVSS/RADSeg"
RADSEG_MODEL_VERSION = "c-radio_v3-b"
RADSEG_LANG_MODEL = "siglip2"
#: The pinned commits (:data:`resireg.models.hub.PINNED_REFS`): RADIO's, RADSeg's.
RADIO_REF = PINNED_REFS[_RADIO_REPO]
RADSEG_REF = PINNED_REFS[RADSEG_REPO]


def load_radseg(
    repo: str = RADSEG_REPO,
    source: str = "github",
    model_version: str = RADSEG_MODEL_VERSION,
    lang_model: str = RADSEG_LANG_MODEL,
    device: str | torch.device | None = None,
    hint_extra: str = "",
    ref: str | None = RADSEG_REF,
    radio_ref: str | None = RADIO_REF,
    **kwargs: Any,
) -> Any:
    """RADSeg's ``RADSegEncoder`` through ``torch.hub``: the one RADSeg loader (the dense
    encoder :class:`RadSegEncoder` and the distillation teacher both use it).

    ``ref`` pins RADSeg's code (``"repo:ref"`` from GitHub; ignored for a local clone).
    RADSeg builds RADIO with a hard-coded ``torch.hub.load("NVlabs/RADIO", ...)``, which
    ``ref`` does not reach; ``radio_ref`` pins that nested load (:func:`_nested_hub_ref`,
    whatever ``source`` RADSeg itself comes from). conf/encoder/radseg.yaml and
    conf/model/teacher/radseg.yaml name both (:data:`RADSEG_REF`, :data:`RADIO_REF` by
    default); ``None`` follows the default branches.

    Checks first, failing at once with a message that names ``repo=`` /
    ``source=local`` (and ``hint_extra``, e.g. how to do without RADSeg): the repo / source
    pair, RADIO's code (RADSeg itself ``torch.hub.load`` s ``NVlabs/RADIO``: the hub cache or
    GitHub) and RADIO's checkpoint (the hub cache or its host). Then
    ``torch.hub.load(repo, "radseg_encoder", model_version=, lang_model=, device=, **kwargs)``
    (``kwargs``: ``radseg_encoder`` 's, e.g. ``slide_crop``, ``scra_scaling``, or
    ``torch.hub.load`` 's). RADSeg keeps its modules on ``device`` (default CPU); the result
    is a plain object, not an ``nn.Module``.
    """
    radio_folder = os.path.join(torch.hub.get_dir(), f"NVlabs_RADIO_{radio_ref or 'main'}")
    hint = (
        f"Clone RADSeg-OVSS/RADSeg elsewhere and pass repo=/path/to/RADSeg "
        f"source=local (NVlabs/RADIO must be in the torch hub cache as "
        f"{radio_folder}, with its checkpoint in checkpoints/){hint_extra}."
    )
    check_hub_source(repo, source, "RADSeg", hint, ref)
    check_hub_ref(radio_ref, "radio_ref")
    require_radio_for_radseg(radio_ref)
    require_radio_weights(model_version, hint)
    if source == "github":
        kwargs.setdefault("skip_validation", True)
    with _nested_hub_ref(_RADIO_REPO, radio_ref):
        return torch.hub.load(
            hub_target(repo, source, ref), "radseg_encoder", source=source,
            model_version=model_version, lang_model=lang_model,
            device=str(torch.device(device or "cpu")), **kwargs,
        )  # fmt: skip


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


# ------------------------------------------------------------------ RADSeg
class RadSegEncoder(DenseEncoder, FrozenModule):
    """Frozen RADSeg (RADIO + SCRA/SCGA + SigLIP 2 adaptor), one pass (see the module docstring).

    Args:
        repo: ``owner/name`` on GitHub, or a local clone of RADSeg (``source="local"``).
        source: ``"github"`` or ``"local"``.
        model_version: RADIO version (``c-radio_v3-b``).
        lang_model: RADIO language adaptor (``siglip2``).
        intermediates: ``"backbone"`` (RADIO's spatial features inside RADSeg) or
            ``"aggregated"`` (after SCGA, what the language head reads).
        device: where RADSeg builds and runs RADIO (default CPU).
        ref, radio_ref: the git refs of RADSeg's code and of the RADIO it loads itself
            (:func:`load_radseg`; :data:`RADSEG_REF`, :data:`RADIO_REF` by default); ``None``:
            the default branches.
        **kwargs: passed to ``radseg_encoder`` (``scra_scaling``, ``scga_scaling``,
            ``amp``, ...) or to ``torch.hub.load``. ``slide_crop``, ``predict`` and
            ``sam_refinement`` are fixed (0, False, False).
    """

    _FIXED = {"slide_crop": 0, "predict": False, "sam_refinement": False}

    def __init__(
        self,
        repo: str = RADSEG_REPO,
        source: str = "github",
        model_version: str = RADSEG_MODEL_VERSION,
        lang_model: str = RADSEG_LANG_MODEL,
        intermediates: str = "backbone",
        device: str | torch.device | None = None,
        ref: str | None = RADSEG_REF,
        radio_ref: str | None = RADIO_REF,
        **kwargs: Any,
    ) -> None:
        super().__init__()
        if intermediates not in ("backbone", "aggregated"):
            raise ConfigError(
                f"intermediates={intermediates!r}: expected 'backbone' or 'aggregated'"
            )
        fixed = {k: kwargs.pop(k) for k in list(kwargs) if k in self._FIXED}
        bad = {k: v for k, v in fixed.items() if v != self._FIXED[k]}
        if bad:
            raise ValueError(
                f"RadSegEncoder runs one pass without prediction: {bad} is not supported "
                f"(fixed: {self._FIXED})"
            )
        self.repo, self.source, self.hub_kwargs = repo, source, dict(kwargs)  # (spec)
        self.encoder_device = torch.device(device if device is not None else "cpu")
        self.encoder = load_radseg(
            repo, source, model_version, lang_model, self.encoder_device,
            ref=ref, radio_ref=radio_ref, **self._FIXED, **kwargs,
        )  # fmt: skip
        target = hub_target(repo, source, ref)
        self.ref, self.radio_ref = ref, radio_ref
        #: what torch.hub loaded, ``"owner/name:ref"``, or ``None`` (a local clone, unpinned)
        self.hub_ref = target if target != repo else None
        self.model_version = model_version
        self.lang_model = lang_model
        self.intermediates = intermediates
        self._input_rule, self._input_dtype = external_input_rule(self.encoder.model)
        self.freeze()

    def spec(self) -> dict[str, Any]:
        """``kind`` and the constructor arguments that rebuild this encoder (``device`` aside)."""
        return {
            "kind": "radseg",
            "repo": self.repo,
            "source": self.source,
            "ref": self.ref,
            "radio_ref": self.radio_ref,
            "model_version": self.model_version,
            "lang_model": self.lang_model,
            "intermediates": self.intermediates,
            **self.hub_kwargs,
        }

    def freeze(self) -> None:
        super().freeze()
        for module in (self.encoder.model, self.encoder.lang_adaptor):
            module.requires_grad_(False)
            module.eval()

    @property
    def device(self) -> torch.device:
        return self.encoder_device

    @property
    def input_rule(self) -> InputRule:
        return self._input_rule

    def encode(self, images: Tensor) -> DenseOutput:
        """Normalised images ``[B, 3, H, W]`` -> RADIO features in RADSeg, RADSeg's language map."""
        self._input_rule.check_size(images, "RADIO's resolution step")
        x = images.to(self.encoder_device)
        if self._input_dtype is not None:
            x = x.to(self._input_dtype)
        radio = self.encoder.model
        calls: list[Any] = []
        handle = radio.register_forward_hook(lambda _m, _i, out: calls.append(out))
        try:
            with torch.no_grad():
                feat_map = self.encoder.encode_image_to_feat_map(x)
                language = self.encoder.align_spatial_features_with_language(feat_map)
        finally:
            handle.remove()
        if len(calls) != 1:
            raise RuntimeError(f"RADSeg ran RADIO {len(calls)} times for one batch; expected 1")
        if self.intermediates == "aggregated":
            inter = feat_map
        else:
            out = calls[0]
            out = out["backbone"] if isinstance(out, dict) else out
            inter = out.features
            if inter.ndim == 3:
                grid = tuple(feat_map.shape[-2:])
                inter = tokens_to_grid(inter, grid, grid)
        dev = images.device
        return DenseOutput(inter.float().to(dev), language.float().to(dev), None)

    def encode_text(self, texts: Sequence[str]) -> Tensor:
        """RADSeg's ``encode_prompts(texts)`` (each text as it is) -> unit-norm ``[K, D_text]``."""
        with torch.no_grad():
            emb = self.encoder.encode_prompts(list(texts))
        return F.normalize(emb.float(), dim=-1)
