"""``ResiregVLM``: the 25M dense VLM bundled for inference; a :class:`DenseEncoder`.

Frozen EUPE backbone + trained language head + frozen text tower + trained text
projection. ``encode`` gives the intermediates (EUPE patch tokens, or the block chosen by
``intermediate_layer``), the head's 512-d patch tokens and the 1024-d image embedding;
``encode_text`` gives the matching 512-d dense text queries. ``encode_image`` (ReSiReg
Lite / Full optional) and ``similarity`` come from :class:`DenseEncoder`.

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
from safetensors.torch import load_file, save_file
from torch import Tensor, nn

from resireg.models.encoder import DenseEncoder, DenseOutput, InputRule
from resireg.models.hub import require_online
from resireg.models.vlm.eupe import EUPEBackbone
from resireg.models.vlm.head import LanguageHead
from resireg.models.vlm.text import FrozenTextTower, TextProjection, dense_text_half
from resireg.sources import is_repo_id

__all__ = ["ResiregVLM"]

_FORMAT = "resireg-vlm"


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


class ResiregVLM(DenseEncoder):
    """Dense vision-language model: images -> ``[B, 512, h, w]``, texts -> ``[K, 512]``.

    Args:
        backbone: frozen EUPE backbone.
        head: trained language head.
        text: frozen text tower.
        text_proj: trained text projection.
        intermediate_layer: ReSiReg's intermediates: ``None`` (default) the backbone's
            final-norm patch tokens, or a block index (its output tokens).
    """

    def __init__(
        self,
        backbone: EUPEBackbone,
        head: LanguageHead,
        text: FrozenTextTower,
        text_proj: TextProjection,
        intermediate_layer: int | None = None,
    ) -> None:
        super().__init__()
        _check_sizes(backbone, head, text, text_proj)
        self.backbone = backbone
        self.head = head
        self.text = text
        self.text_proj = text_proj
        self.intermediate_layer = backbone.check_layer(intermediate_layer)
        self._input_rule = InputRule(backbone.patch_size, backbone.mean, backbone.std)
        self.export_source: str | None = None  # set by from_pretrained (spec)

    # ------------------------------------------------------------------ building
    @classmethod
    def build(
        cls, backbone: dict, head: dict, text: dict, intermediate_layer: int | None = None
    ) -> ResiregVLM:
        """Build from plain config dicts.

        Args:
            backbone: ``EUPEBackbone`` kwargs (``model_name``, ``weights``, timm overrides).
            head: ``LanguageHead`` kwargs except ``in_dim`` (taken from the backbone).
            text: a text tower spec: ``{"kind": "pretrained", "model_name", "weights",
                "tokenizer"}`` or ``{"kind": "tiny", ...}``, optionally ``cache_size``.
            intermediate_layer: see the class.
        """
        bb = EUPEBackbone(**backbone)
        hd = LanguageHead(in_dim=bb.embed_dim, **head)
        tx = FrozenTextTower.from_spec(text)
        return cls(bb, hd, tx, TextProjection(tx.out_dim, hd.out_dim), intermediate_layer)

    # ------------------------------------------------------- DenseEncoder interface
    @property
    def input_rule(self) -> InputRule:
        return self._input_rule

    def encode(self, images: Tensor) -> DenseOutput:
        """Normalised images -> (intermediates ``[B, D, h, w]``, head patch tokens
        ``[B, 512, h, w]``, image embedding ``[B, 1024]``). The head keeps its graph (training)."""
        feats = self.backbone(images, self.intermediate_layer)
        out = self.head(feats)
        return DenseOutput(feats.intermediates, out.patches, out.embedding)

    def text_features(self, texts: Sequence[str]) -> Tensor:
        """Pooled outputs ``[K, 768]`` of the frozen tower, computed on exactly ``texts`` (no
        cache), so they do not depend on which captions training cached."""
        return self.text(list(texts), cache=False)

    def dense_text(self, features: Tensor) -> Tensor:
        """The current projection's normalised dense half ``[K, 512]`` of tower outputs."""
        return dense_text_half(self.text_proj(features.to(self.device, torch.float32)))

    def encode_text(self, texts: Sequence[str]) -> Tensor:
        """Dense text queries ``[K, 512]``: normalised second half of the projected embedding."""
        with torch.no_grad():
            return self.dense_text(self.text_features(texts))

    def text_embedding(self, texts: Sequence[str]) -> Tensor:
        """Projected text embeddings ``[K, 1024]`` matching ``encode(...).embedding`` (training;
        tower outputs come from the caption cache)."""
        return self.text_proj(self.text(list(texts)).to(self.device))

    def spec(self) -> dict[str, Any]:
        """``{"kind": "resireg_vlm", "path": <export>}``: the encoder config that rebuilds this
        model, for a model loaded by :meth:`from_pretrained` (the export holds the weights);
        a model built in Python has none until it is saved and loaded (ValueError)."""
        if self.export_source is None:
            raise ValueError(
                "this ResiregVLM was not loaded from an export: save_pretrained(directory), then "
                "from_pretrained(directory) gives one with an encoder config (kind resireg_vlm)"
            )
        return {"kind": "resireg_vlm", "path": self.export_source}

    # ---------------------------------------------------------------- save / load
    def config(self) -> dict[str, Any]:
        return {
            "format": _FORMAT,
            "version": 1,
            "backbone": self.backbone.spec(),
            "head": self.head.spec(),
            "text": self.text.spec(),
            "intermediate_layer": self.intermediate_layer,
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
        """Load a bundle from a directory written by :meth:`save_pretrained`, or from a Hugging
        Face repo id ``owner/name`` (the local cache first; the hub only when online)."""
        path = _export_dir(source)
        cfg_file = path / "config.json"
        if not cfg_file.is_file():
            raise FileNotFoundError(f"{str(path)!r} holds no config.json (not a ResiregVLM export)")
        cfg = json.loads(cfg_file.read_text())
        if cfg.get("format") != _FORMAT:
            raise ValueError(
                f"{str(cfg_file)!r} is not a {_FORMAT} config (format={cfg.get('format')!r})"
            )
        model = cls.build(cfg["backbone"], cfg["head"], cfg["text"], cfg.get("intermediate_layer"))
        if "frozen_weights" in cfg:
            _load_prefixed(
                load_file(path / cfg["frozen_weights"]),
                {"backbone": model.backbone, "text": model.text},
            )
        model.load_trained(path)
        model.export_source = os.fspath(source)
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


def _check_sizes(
    backbone: EUPEBackbone, head: LanguageHead, text: FrozenTextTower, text_proj: TextProjection
) -> None:
    """Raise ``ValueError`` naming both sizes where two parts do not fit together: the head
    reads the backbone's tokens, the text projection reads the tower's pooled output, and the
    projection's dense half is what the head's patch tokens are scored against."""
    problems = []
    head_in = head.proj.in_features
    if head_in != backbone.embed_dim:
        problems.append(
            f"the head takes {head_in}-d tokens but the backbone gives {backbone.embed_dim}-d"
        )
    if text_proj.in_features != text.out_dim:
        problems.append(f"the text projection takes {text_proj.in_features}-d inputs but the text "
                        f"tower gives {text.out_dim}-d")  # fmt: skip
    if text_proj.out_features != 2 * head.out_dim:
        problems.append(
            f"the text projection's dense half is {text_proj.out_features // 2}-d "
            f"({text_proj.out_features} outputs) but the head's patch tokens are {head.out_dim}-d"
        )
    if problems:
        raise ValueError("ResiregVLM parts do not fit: " + "; ".join(problems))


def _export_dir(source: str | os.PathLike) -> Path:
    """The local folder of an export: ``source`` itself, or a Hugging Face snapshot.

    A source that is not an existing folder is a repo id only if it has the form
    ``owner/name`` and names no existing file; the local cache is tried first and only a
    cache miss (``LocalEntryNotFoundError``) leads to a download.
    """
    path = Path(source)
    if path.is_dir():
        return path
    text = os.fspath(source)
    if path.exists() or not is_repo_id(text):  # (resireg.sources: the config checks' rule too)
        raise FileNotFoundError(
            f"{text!r} is not an export folder (and not a Hugging Face repo id 'owner/name')"
        )
    from huggingface_hub import snapshot_download
    from huggingface_hub.errors import LocalEntryNotFoundError

    try:
        return Path(snapshot_download(text, local_files_only=True))
    except LocalEntryNotFoundError:
        require_online(
            f"ResiregVLM {text!r} (no such local folder; as a Hugging Face repo id it is not cached)",
            "huggingface.co",
            "Pass the export directory instead (resireg-eval: model_path=/path/to/export).",
        )
    return Path(snapshot_download(text))
