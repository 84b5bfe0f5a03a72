"""RADSeg (RADSeg-OVSS/RADSeg) as a :class:`DenseEncoder`, and the one RADSeg loader
(:func:`load_radseg`) the encoder and the distillation teacher share. RADSeg runs on RADIO
(:mod:`resireg.models.zoo.radio`: its checkpoints, input rule and summary head).

It loads through ``torch.hub`` (``source="github"``, or a local clone with ``source="local"``).

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

Input rule (:func:`resireg.models.zoo.radio.external_input_rule`): RADIO's conditioner is made external and its ``norm_mean`` /
``norm_std`` become :class:`InputRule`'s ``mean`` / ``std`` (the same affine map RADIO
applies to ``[0, 1]`` RGB), patch size ``min_resolution_step``; inputs are cast to the
conditioner's dtype as RADIO does.

The encoder is frozen (eval, no gradients, forward under ``torch.no_grad``).
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
from torch import Tensor

from resireg.errors import ConfigError
from resireg.models.frozen import FrozenModule
from resireg.models.hub import (
    PINNED_REFS,
    check_hub_ref,
    check_hub_source,
    hub_cache_dir,
    hub_target,
    require_hub_repo,
)
from resireg.models.images import tokens_to_grid
from resireg.models.interface import DenseEncoder, DenseOutput, InputRule
from resireg.models.zoo.radio import (
    RADIO_REF,
    RADIO_REPO,
    external_input_rule,
    require_radio_weights,
)

__all__ = ["RADSEG_REF", "RadSegEncoder", "load_radseg", "require_radio_for_radseg"]


def require_radio_for_radseg(ref: str | None = None) -> None:
    """Fail at once when RADSeg could get RADIO's code (at ``ref``) neither from the hub cache
    nor GitHub."""
    target = hub_cache_dir(RADIO_REPO, ref or "main")
    require_hub_repo(
        RADIO_REPO,
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


#: RADSeg's hub repo, RADIO version and language adaptor by default: those of
#: conf/encoder/radseg.yaml and conf/model/teacher/radseg.yaml, for the one loader and the two
#: modules over it (RadSegEncoder here, the distillation teacher in resireg_train.training).
RADSEG_REPO = "RADSeg-OVSS/RADSeg"
RADSEG_MODEL_VERSION = "c-radio_v3-b"
RADSEG_LANG_MODEL = "siglip2"
#: The pinned commit of RADSeg's code (:data:`resireg.models.hub.PINNED_REFS`).
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
    with _nested_hub_ref(RADIO_REPO, radio_ref):
        return torch.hub.load(
            hub_target(repo, source, ref), "radseg_encoder", source=source,
            model_version=model_version, lang_model=lang_model,
            device=str(torch.device(device or "cpu")), **kwargs,
        )  # fmt: skip


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
