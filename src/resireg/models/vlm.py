"""``ResiregVLM``: the 25M dense VLM bundled for inference.

Frozen EUPE backbone + trained language head + frozen text tower + trained text
projection. ``encode_image`` gives 512-d dense features (optionally reconstructed by
ReSiReg Lite or Full, with the EUPE patch tokens as intermediates and the head's patch
outputs as language tokens); ``encode_text`` gives the matching 512-d text queries.

Export format (``save_pretrained``): ``config.json`` names every part and where the
frozen parts' weights come from; ``model.safetensors`` holds the trained parts (head,
text projection). Frozen parts without an external weights source (random init, as in
tests and the smoke experiment) are saved in ``frozen.safetensors`` so a reload is
exact; ``include_frozen=True`` embeds them always (a self-contained bundle).
"""

from __future__ import annotations

import json
import os
from collections.abc import Sequence
from pathlib import Path
from typing import Any

import torch
import torch.nn.functional as F
from PIL import Image
from safetensors.torch import load_file, save_file
from torch import Tensor, nn

from resireg.models.eupe import EUPEBackbone
from resireg.models.head import LanguageHead
from resireg.models.hub import require_online
from resireg.models.text import FrozenTextTower, TextProjection, dense_text_half
from resireg.reconstruct import ReSiRegFull, ReSiRegLite

__all__ = ["ResiregVLM", "patch_grid_size", "resize_to_patch_grid"]

_FORMAT = "resireg-vlm"


def _pil_to_tensor(image: Image.Image) -> Tensor:
    import numpy as np

    array = np.asarray(image.convert("RGB"), dtype=np.uint8).copy()
    return torch.from_numpy(array).permute(2, 0, 1)


def resize_to_patch_grid(image: Tensor, short_side: int | None, patch_size: int) -> Tensor:
    """An RGB image ``[3, H, W]`` (uint8, or float in [0, 1]) -> float ``[3, h, w]`` in [0, 1].

    With ``short_side`` the shorter side is scaled to it (aspect kept); either way each
    side is rounded to a multiple of ``patch_size`` (bilinear, antialiased).
    """
    if image.ndim != 3 or image.shape[0] != 3:
        raise ValueError(f"images must be RGB [3, H, W], got shape {tuple(image.shape)}")
    image = image.float() / 255.0 if not image.is_floating_point() else image.float()
    size = patch_grid_size(tuple(image.shape[-2:]), short_side, patch_size)
    if size == tuple(image.shape[-2:]):
        return image
    return F.interpolate(
        image[None], size=size, mode="bilinear", align_corners=False, antialias=True
    )[0]


def patch_grid_size(
    size: tuple[int, int], short_side: int | None, patch_size: int
) -> tuple[int, int]:
    """``(H, W)`` after :func:`resize_to_patch_grid` (no pixels needed)."""
    h, w = size
    scale = short_side / min(h, w) if short_side else 1.0
    p = patch_size
    return (max(p, round(h * scale / p) * p), max(p, round(w * scale / p) * p))


def _prefixed(parts: dict[str, nn.Module]) -> dict[str, Tensor]:
    """One flat CPU state dict of several modules, keys prefixed ``"<name>."``."""
    return {
        f"{name}.{k}": v.detach().cpu().contiguous()
        for name, module in parts.items()
        for k, v in module.state_dict().items()
    }


def _load_prefixed(tensors: dict[str, Tensor], parts: dict[str, nn.Module]) -> None:
    """Inverse of :func:`_prefixed`: load each module's keys (strictly) where present."""
    for name, module in parts.items():
        prefix = f"{name}."
        part = {k[len(prefix) :]: v for k, v in tensors.items() if k.startswith(prefix)}
        if part:
            module.load_state_dict(part)


class ResiregVLM(nn.Module):
    """Dense vision-language model: images -> ``[B, 512, h, w]``, texts -> ``[K, 512]``.

    Args:
        backbone: frozen EUPE backbone.
        head: trained language head.
        text: frozen text tower.
        text_proj: trained text projection.
    """

    def __init__(
        self,
        backbone: EUPEBackbone,
        head: LanguageHead,
        text: FrozenTextTower,
        text_proj: TextProjection,
    ) -> None:
        super().__init__()
        self.backbone = backbone
        self.head = head
        self.text = text
        self.text_proj = text_proj
        self.head_config: dict[str, Any] = {}

    # ------------------------------------------------------------------ building
    @classmethod
    def build(cls, backbone: dict, head: dict, text: dict) -> ResiregVLM:
        """Build from plain config dicts.

        Args:
            backbone: ``EUPEBackbone`` kwargs (``model_name``, ``weights``, timm overrides).
            head: ``LanguageHead`` kwargs except ``in_dim`` (taken from the backbone).
            text: a text tower spec: ``{"kind": "pretrained", "model_name", "weights",
                "tokenizer"}`` or ``{"kind": "tiny", ...}``.
        """
        bb = EUPEBackbone(**backbone)
        hd = LanguageHead(in_dim=bb.embed_dim, **head)
        tx = FrozenTextTower.from_spec(text)
        model = cls(bb, hd, tx, TextProjection(tx.out_dim, hd.out_dim))
        model.head_config = dict(head)
        return model

    @property
    def device(self) -> torch.device:
        return next(self.head.parameters()).device

    # ------------------------------------------------------------- preprocessing
    def preprocess(self, images: Any, short_side: int | None = None) -> Tensor:
        """PIL images, or RGB tensors (uint8, or float in [0, 1]), -> normalised ``[B, 3, H, W]``.

        With ``short_side`` the shorter side is resized to it (aspect kept); either way each
        side is rounded to a multiple of the patch size.
        """
        if isinstance(images, (Image.Image, Tensor)) and not (
            isinstance(images, Tensor) and images.ndim == 4
        ):
            images = [images]
        tensors = [_pil_to_tensor(im) if isinstance(im, Image.Image) else im for im in images]
        out = [resize_to_patch_grid(t, short_side, self.backbone.patch_size) for t in tensors]
        if len({tuple(t.shape) for t in out}) != 1:
            raise ValueError(
                f"images of one batch must share a size after resizing, got {[tuple(t.shape[-2:]) for t in out]}"
            )
        batch = torch.stack(out).to(self.device)
        mean = torch.tensor(self.backbone.mean, device=batch.device).view(1, 3, 1, 1)
        std = torch.tensor(self.backbone.std, device=batch.device).view(1, 3, 1, 1)
        return (batch - mean) / std

    # ------------------------------------------------------------------ encoding
    def forward_dense(self, images: Tensor) -> tuple[Tensor, Tensor]:
        """Normalised images -> (EUPE patch tokens ``[B, D, h, w]``, head patch tokens ``[B, 512, h, w]``)."""
        feats = self.backbone(images)
        return feats.patches, self.head(feats).patches

    def encode_image(
        self,
        images: Any,
        resireg: str | nn.Module | None = None,
        *,
        normalized: bool = False,
        short_side: int | None = None,
        prior: Tensor | None = None,
        **resireg_kwargs: Any,
    ) -> Tensor:
        """Dense language features ``[B, 512, h, w]`` (unit norm over channels).

        Args:
            images: PIL images / RGB tensors, or (``normalized=True``) a normalised batch.
            resireg: ``None`` (head output), ``"lite"``, ``"full"``, or a ReSiReg module.
                With ReSiReg the grid is ``upscale`` times finer.
            short_side: resize for PIL/tensor input (see :meth:`preprocess`).
            prior: optional segmentation prior for ReSiReg.
            **resireg_kwargs: arguments of ``ReSiRegLite`` / ``ReSiRegFull``.
        """
        x = images if normalized else self.preprocess(images, short_side)
        with torch.no_grad():
            inter, lang = self.forward_dense(x)
            if resireg is None:
                return F.normalize(lang, dim=1)
            module = self._resireg(resireg, resireg_kwargs)
            return module(inter, lang, prior)

    @staticmethod
    def _resireg(resireg: str | nn.Module, kwargs: dict) -> nn.Module:
        if isinstance(resireg, nn.Module):
            return resireg
        if resireg == "lite":
            return ReSiRegLite(**kwargs)
        if resireg == "full":
            return ReSiRegFull(**kwargs)
        raise ValueError(f"resireg must be None, 'lite', 'full' or a module, got {resireg!r}")

    def encode_text(self, texts: Sequence[str]) -> Tensor:
        """Dense text queries ``[K, 512]``: normalised second half of the projected embedding."""
        with torch.no_grad():
            return dense_text_half(self.text_proj(self.text(list(texts)).to(self.device)))

    def similarity(
        self,
        images: Any,
        texts: Sequence[str],
        resireg: str | nn.Module | None = None,
        **kwargs: Any,
    ) -> Tensor:
        """Per-pixel cosine similarity maps ``[B, K, h, w]`` of images with text queries."""
        dense = self.encode_image(images, resireg, **kwargs)
        return torch.einsum("bdhw,kd->bkhw", dense.float(), self.encode_text(texts).float())

    # ---------------------------------------------------------------- save / load
    def config(self) -> dict[str, Any]:
        return {
            "format": _FORMAT,
            "version": 1,
            "backbone": self.backbone.spec(),
            "head": self.head_config,
            "text": self.text.spec(),
        }

    def save_pretrained(self, directory: str | os.PathLike, include_frozen: bool = False) -> Path:
        """Write ``config.json`` + ``model.safetensors`` (+ ``frozen.safetensors`` when needed)."""
        out = Path(directory)
        out.mkdir(parents=True, exist_ok=True)
        cfg = self.config()
        save_file(
            _prefixed({"head": self.head, "text_proj": self.text_proj}), out / "model.safetensors"
        )
        frozen: dict[str, nn.Module] = {}
        if include_frozen or self.backbone.weights is None:
            frozen["backbone"] = self.backbone
            cfg["backbone"]["weights"] = None
        if include_frozen or cfg["text"]["kind"] == "tiny":
            frozen["text"] = self.text
        if frozen:
            save_file(_prefixed(frozen), out / "frozen.safetensors")
            cfg["frozen_weights"] = "frozen.safetensors"
        (out / "config.json").write_text(json.dumps(cfg, indent=2))
        return out

    @classmethod
    def from_pretrained(
        cls, source: str | os.PathLike, map_location: str | torch.device = "cpu"
    ) -> ResiregVLM:
        """Load a bundle from a directory written by :meth:`save_pretrained` or a Hugging Face repo id."""
        path = Path(source)
        if not path.is_dir():
            path = cls._download(str(source))
        cfg_file = path / "config.json"
        if not cfg_file.is_file():
            raise FileNotFoundError(f"{str(path)!r} holds no config.json (not a ResiregVLM export)")
        cfg = json.loads(cfg_file.read_text())
        if cfg.get("format") != _FORMAT:
            raise ValueError(
                f"{str(cfg_file)!r} is not a {_FORMAT} config (format={cfg.get('format')!r})"
            )
        model = cls.build(cfg["backbone"], cfg["head"], cfg["text"])
        if "frozen_weights" in cfg:
            _load_prefixed(
                load_file(path / cfg["frozen_weights"]),
                {"backbone": model.backbone, "text": model.text},
            )
        model.load_trained(path)
        return model.to(map_location).eval()

    def load_trained(self, directory: str | os.PathLike) -> list[str]:
        """Load an export's trained parts (head, text projection) into this model.

        Returns the names of the loaded tensors (``"head.…"``, ``"text_proj.…"``).
        """
        file = Path(directory) / "model.safetensors"
        trained = load_file(file)
        parts = {"head": self.head, "text_proj": self.text_proj}
        missing = [n for n in parts if not any(k.startswith(f"{n}.") for k in trained)]
        if missing:
            raise ValueError(f"{str(file)!r} holds no weights for {missing}")
        _load_prefixed(trained, parts)
        return sorted(trained)

    @staticmethod
    def _download(repo_id: str) -> Path:
        if repo_id.count("/") != 1 or os.path.exists(repo_id):
            raise FileNotFoundError(
                f"{repo_id!r} is neither an export directory nor a Hugging Face repo id"
            )
        from huggingface_hub import snapshot_download

        try:
            return Path(snapshot_download(repo_id, local_files_only=True))
        except Exception:
            require_online(
                f"ResiregVLM {repo_id!r}", "huggingface.co", "Pass the export directory instead."
            )
            return Path(snapshot_download(repo_id))
