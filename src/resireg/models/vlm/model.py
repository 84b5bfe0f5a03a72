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
``config.json`` records the SHA-256 of every tensor file (``digests``), verified by
:meth:`from_pretrained` before a tensor is read (:mod:`resireg.integrity`); files are written
atomically with the umask's mode. :meth:`push_to_hub` publishes an export folder with a model
card (:mod:`resireg.models.vlm.card`) to the Hugging Face Hub.
"""

from __future__ import annotations

import json
import os
import tempfile
from collections.abc import Mapping, Sequence
from pathlib import Path
from typing import Any

import torch
from safetensors.torch import save_file
from torch import Tensor, nn

from resireg.integrity import atomic_write, digests, load_safetensors, resolve_inside
from resireg.models.interface import DenseEncoder, DenseOutput, InputRule
from resireg.models.vlm.card import hub_folder
from resireg.models.vlm.eupe import EUPEBackbone
from resireg.models.vlm.folder import (
    EXPORT_FORMAT,
    EXPORT_WHAT,
    export_dir,
    frozen_sources,
    read_config,
)
from resireg.models.vlm.head import LanguageHead
from resireg.models.vlm.text import FrozenTextTower, TextProjection, dense_text_half
from resireg.specs.exports import registry_model

# read_config: also importable from here, where it was defined before resireg.models.vlm.folder
__all__ = ["ResiregVLM", "read_config"]


def _local_file(weights: Any) -> tuple[str, ...]:
    """``(weights,)`` when it names an existing local file (a checkpoint, not a tag, ``"hub"``
    or ``None``), else ``()``."""
    return (weights,) if isinstance(weights, str) and os.path.isfile(weights) else ()


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
        self.export_external: dict[str, dict[str, Any]] | None = None  # its files given outside

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
        spec: dict[str, Any] = {"kind": "resireg_vlm", "path": self.export_source}
        if self.export_external:
            spec["external"] = self.export_external
        return spec

    # ---------------------------------------------------------------- save / load
    def config(self) -> dict[str, Any]:
        return {
            "format": EXPORT_FORMAT,
            "version": 1,
            "backbone": self.backbone.spec(),
            "head": self.head.spec(),
            "text": self.text.spec(),
            "intermediate_layer": self.intermediate_layer,
        }

    def save_pretrained(self, directory: str | os.PathLike, include_frozen: bool = False) -> Path:
        """Write ``config.json`` + ``model.safetensors`` (+ ``frozen.safetensors`` when needed).

        Each file is written atomically (:func:`~resireg.integrity.atomic_write`: a reader sees
        the old file or the new one; mode from the umask, not safetensors' 0600), tensor files
        first, and ``config.json`` records their SHA-256 (``digests``) for
        :meth:`from_pretrained` to verify."""
        out = Path(directory)
        out.mkdir(parents=True, exist_ok=True)
        cfg = self.config()
        trained = _prefixed({"head": self.head, "text_proj": self.text_proj})
        atomic_write(out / "model.safetensors", lambda tmp: save_file(trained, tmp))
        files = ["model.safetensors"]
        frozen: dict[str, nn.Module] = {}
        # A backbone from a local file is embedded: an export names no file outside itself
        # (from_pretrained refuses one: frozen_sources), and its digests cover what it loads.
        if include_frozen or self.backbone.weights in (None, *_local_file(self.backbone.weights)):
            frozen["backbone"] = self.backbone
            cfg["backbone"]["weights"] = None
        if include_frozen or cfg["text"]["kind"] == "tiny":
            frozen["text"] = self.text
        if frozen:
            tensors = _prefixed(frozen)
            atomic_write(out / "frozen.safetensors", lambda tmp: save_file(tensors, tmp))
            cfg["frozen_weights"] = "frozen.safetensors"
            files.append("frozen.safetensors")
        cfg["digests"] = digests(out, files)
        text = json.dumps(cfg, indent=2)
        atomic_write(out / "config.json", lambda tmp: tmp.write_text(text))
        return out

    @classmethod
    def from_pretrained(
        cls,
        source: str | os.PathLike,
        map_location: str | torch.device = "cpu",
        external: Mapping[str, Mapping[str, Any]] | None = None,
    ) -> ResiregVLM:
        """Load a bundle from a directory written by :meth:`save_pretrained`, from a Hugging
        Face repo id ``owner/name`` (the local cache first; the hub only when online), or from
        MLflow's model registry (``models:/NAME@ALIAS``, ``models:/NAME/VERSION``: downloaded
        once, verified before every use; :mod:`resireg.models.vlm.registry`).

        Every file the export's ``config.json`` names stays inside the export and is covered
        by its digests (:func:`~resireg.models.vlm.folder.frozen_sources`); a frozen part's
        file outside it is taken only from ``external`` (``{"backbone": {"weights": path}}``,
        ``{"text": {"weights": ..., "tokenizer": ...}}``), given by the caller."""
        path = local_export(source)
        cfg = read_config(path)  # (its file names checked: they stay inside the folder)
        cfg = frozen_sources(path, cfg, external)
        model = cls.build(cfg["backbone"], cfg["head"], cfg["text"], cfg.get("intermediate_layer"))
        if "frozen_weights" in cfg:
            frozen = resolve_inside(
                path, cfg["frozen_weights"], f"{path}/config.json: frozen_weights"
            )
            _load_prefixed(
                load_safetensors(frozen, EXPORT_WHAT),
                {"backbone": model.backbone, "text": model.text},
            )
        model.load_trained(path, verified=True)
        model.export_source = os.fspath(source)
        model.export_external = {p: dict(k) for p, k in external.items()} if external else None
        return model.to(map_location).eval()

    def load_trained(self, directory: str | os.PathLike, verified: bool = False) -> list[str]:
        """Load an export's trained parts (head, text projection) into this model.

        The digests of the export's ``config.json`` are checked first, where it has one
        (``verified``: the caller, :meth:`from_pretrained`, has done so). Returns the names of the loaded tensors
        (``"head.…"``, ``"text_proj.…"``).
        """
        if not verified and (Path(directory) / "config.json").is_file():
            read_config(directory)
        file = Path(directory) / "model.safetensors"
        trained = load_safetensors(file, EXPORT_WHAT)
        parts = {"head": self.head, "text_proj": self.text_proj}
        missing = [n for n in parts if not any(k.startswith(f"{n}.") for k in trained)]
        if missing:
            raise ValueError(f"{str(file)!r} holds no weights for {missing}")
        _load_prefixed(trained, parts)
        return sorted(trained)

    # ------------------------------------------------------------------ the Hub
    def push_to_hub(
        self,
        repo_id: str,
        *,
        export: str | os.PathLike | None = None,
        private: bool | None = None,
        token: str | None = None,
        revision: str | None = None,
        commit_message: str = "Upload ResiregVLM export",
        card: dict[str, Any] | None = None,
    ) -> Any:
        """Publish this model to the Hugging Face Hub repository ``repo_id`` (``owner/name``).

        The folder uploaded is :func:`resireg.models.vlm.card.hub_folder`'s: an export with its
        digests (by default a fresh :meth:`save_pretrained` of this model as it is now, so
        weights changed since loading are what is published; ``export``: an existing export
        folder or repo id as it is, verified first), plus a model card ``README.md``
        (``card``: extra card fields, e.g. ``{"license": "apache-2.0", "metrics": ...}``).
        The repository is created if missing (``HfApi.create_repo(exist_ok=True)``), then
        the folder is sent in one commit (``HfApi.upload_folder``). Returns its
        ``CommitInfo``. ``from_pretrained(repo_id)`` loads it back."""
        from huggingface_hub import HfApi

        with tempfile.TemporaryDirectory(prefix="resireg-push-") as tmp:
            source = export if export is not None else self.save_pretrained(Path(tmp) / "export")
            folder = hub_folder(local_export(source), Path(tmp) / "upload", repo_id, card)
            api = HfApi(token=token)
            api.create_repo(repo_id, private=private, repo_type="model", exist_ok=True)
            return api.upload_folder(
                repo_id=repo_id,
                folder_path=str(folder),
                repo_type="model",
                revision=revision,
                commit_message=commit_message,
            )


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


def local_export(source: str | os.PathLike) -> Path:
    """The local folder of an export: :func:`~resireg.models.vlm.folder.export_dir` (a folder,
    a Hugging Face snapshot), or for ``models:/NAME@ALIAS`` / ``models:/NAME/VERSION`` the
    verified local copy of an export in MLflow's model registry (:mod:`resireg.models.vlm.registry`,
    which reads exports through the folder module: the dispatch lives here, above both)."""
    if registry_model(os.fspath(source)) is not None:
        from resireg.models.vlm.registry import registry_export

        return registry_export(os.fspath(source))
    return export_dir(source)
