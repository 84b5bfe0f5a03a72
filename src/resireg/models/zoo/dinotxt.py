"""dino.txt (DINOv2 ViT-L/14 with 4 registers + text alignment) as a :class:`DenseEncoder`.

The model comes from ``torch.hub`` (``facebookresearch/dinov2``, entry point
``dinov2_vitl14_reg4_dinotxt_tet1280d20h24l``, or a local clone with ``source="local"``).
What its code does, and therefore how we call it (read from ``hubconf.py``,
``dinov2/hub/dinotxt.py`` and ``dinov2/hub/text/{dinotxt_model,vision_tower,
dinov2_wrapper,tokenizer}.py`` of facebookresearch/dinov2, and its
``notebooks/dinotxt.ipynb``):

- The entry point takes no arguments and returns only the model, a ``DinoTxt``:
  ``visual_model`` (a ``VisionTower``: ``backbone`` = ``DINOv2Wrapper`` around the
  frozen ``dinov2_vitl14_reg`` ViT, then ``head`` = ``VisionHead``: two attention blocks,
  ``ln_final``, and an identity ``linear_projection`` because ``2 * 1024 == embed_dim``),
  ``text_model`` and ``model_config`` (``embed_dim=2048``). It downloads the backbone
  (``dinov2_vitl14_reg4_pretrain.pth``) and the dino.txt vision head / text encoder
  weights with ``torch.hub.load_state_dict_from_url`` (the torch hub cache,
  ``<torch.hub.get_dir()>/checkpoints``).
- The tokenizer is not a hub entry point: ``dinov2.hub.dinotxt.get_tokenizer()`` downloads
  the CLIP BPE vocabulary (``bpe_simple_vocab_16e6.txt.gz``) on every call, and
  ``dinov2.hub.text.tokenizer.Tokenizer(vocab_path=...)`` builds it from a local file;
  ``tokenizer.tokenize(texts) -> LongTensor [K, 77]``. We import both modules from the
  package the hub model came from.
- ``VisionTower.get_backbone_features(x)`` takes the backbone's last block
  (``get_intermediate_layers(n=1, return_class_token=True, return_register_tokens=True)``,
  final norm applied) -> CLS ``[B, 1024]``, patch tokens ``[B, N, 1024]`` (CLS and the 4
  registers removed), registers. ``get_class_and_patch_tokens`` runs the head on
  ``cat([cls, registers, patches])`` and splits it again; ``forward`` / ``encode_image``
  return ``cat([head CLS, mean of head patch tokens])`` ``[B, 2048]``.
- ``encode_text(tokens)`` ``[K, 2048]``: "the first half corresponds to global image
  features and the second half to pooled patch features"; the notebook's dense
  ("patch embeddings") example compares ``get_visual_class_and_patch_tokens`` patch tokens
  with ``encode_text(...)[:, 1024:]``, each L2-normalised.
- Input: RGB normalised with ImageNet mean / std (the docstring of ``encode_image`` and
  ``make_classification_eval_transform``), sides multiples of 14.

This adapter, in one backbone pass:

- ``intermediates`` ``[B, 1024, h, w]``: the backbone's final-norm patch tokens, before
  the vision head (``get_backbone_features``),
- ``language`` ``[B, 1024, h, w]``: the vision head's patch tokens (what dino.txt
  segments with), raw (the ``bb`` variant normalises),
- ``embedding`` ``[B, 2048]``: ``cat([head CLS, mean head patch tokens])``, i.e. what
  ``DinoTxt.encode_image`` returns (not normalised), computed from the same pass,
- ``encode_text``: the patch half ``encode_text(tokens)[:, embed_dim // 2:]``,
  L2-normalised (``text_features`` = that half before normalisation).

Resolution: with ``image_size=518`` (default) every canvas batch ``[B, 3, H, W]`` is
resized (bilinear, ``align_corners=False``, after normalisation) to ``518 x 518``, the
size at which DINOv2's positional embedding (37 x 37) is used without interpolation; both
dense maps ``[B, D, 37, 37]`` are then resized bilinearly (``align_corners=False``) to the
canvas's patch grid ``(H / 14, W / 14)``. This is not a hard limit of the model: DINOv2
interpolates its positional embedding (bicubic, antialiased) for any multiple of 14, and
dino.txt was trained at 224 (its notebook runs 224 crops and upsamples the patch
similarities bicubically). ``image_size=None`` runs each canvas at its own size, no resizing.
"""

from __future__ import annotations

import importlib
import os
from collections.abc import Sequence
from typing import Any

import torch
from timm.data import IMAGENET_DEFAULT_MEAN, IMAGENET_DEFAULT_STD
from torch import Tensor

from resireg.errors import ConfigError
from resireg.models.frozen import FrozenModule
from resireg.models.hub import (
    PINNED_REFS,
    check_hub_source,
    hub_target,
    require_hub_checkpoints,
    require_online,
)
from resireg.models.images import resize_square, tokens_to_grid
from resireg.models.interface import DenseEncoder, DenseOutput, InputRule

__all__ = ["DINOTXT_ENTRY_POINT", "DINOTXT_CHECKPOINTS", "DinoTxtEncoder"]

#: The torch.hub entry point of dino.txt in facebookresearch/dinov2.
DINOTXT_ENTRY_POINT = "dinov2_vitl14_reg4_dinotxt_tet1280d20h24l"

#: Files the entry point fetches with ``torch.hub.load_state_dict_from_url`` (looked up in
#: ``<torch.hub.get_dir()>/checkpoints``) from ``https://dl.fbaipublicfiles.com/dinov2/``.
DINOTXT_CHECKPOINTS = (
    "dinov2_vitl14_reg4_pretrain.pth",
    "dinov2_vitl14_reg4_dinotxt_tet1280d20h24l_vision_head.pth",
    "dinov2_vitl14_reg4_dinotxt_tet1280d20h24l_text_encoder.pth",
)

_WEIGHTS_HOST = "dl.fbaipublicfiles.com"
_VOCAB = "bpe_simple_vocab_16e6.txt.gz"


def _hint() -> str:
    return (
        f"Clone facebookresearch/dinov2 elsewhere and pass repo=/path/to/dinov2 "
        f"source=local; put its weights ({', '.join(DINOTXT_CHECKPOINTS)}, from "
        f"https://{_WEIGHTS_HOST}/dinov2/dinov2_vitl14/) in the torch hub cache "
        f"({os.path.join(torch.hub.get_dir(), 'checkpoints')}) and pass "
        f"vocab=/path/to/{_VOCAB} (https://{_WEIGHTS_HOST}/dinov2/thirdparty/{_VOCAB})."
    )


class DinoTxtEncoder(DenseEncoder, FrozenModule):
    """Frozen dino.txt (DINOv2 ViT-L/14 reg4) dense encoder (see the module docstring).

    Args:
        repo: ``owner/name`` on GitHub, or a local clone (with ``source="local"``).
        source: ``"github"`` or ``"local"``.
        entry_point: the hub entry point.
        image_size: side of the square model input (a multiple of the patch size) every
            canvas is resized to, or ``None`` to run canvases at their own size.
        vocab: the BPE vocabulary ``bpe_simple_vocab_16e6.txt.gz``; ``None`` = the repo's
            ``get_tokenizer()``, which downloads it.
        device: where the model is placed (default CPU).
        text_batch_size: texts per text-tower call.
        ref: the git tag or commit SHA loaded from GitHub (``"repo:ref"``;
            :func:`resireg.models.hub.hub_target`); conf/encoder/dinotxt.yaml pins the one the
            adapter was checked against (:data:`resireg.models.hub.PINNED_REFS`, the default).
            ``None``: the default branch. Ignored for a local clone.
        **kwargs: passed to ``torch.hub.load`` (``trust_repo``, ``force_reload``, or the
            entry point's own arguments; the real one takes none).
    """

    def __init__(
        self,
        repo: str = "facebookresearch/dinov2",
        source: str = "github",
        entry_point: str = DINOTXT_ENTRY_POINT,
        image_size: int | None = 518,
        vocab: str | os.PathLike | None = None,
        device: str | torch.device | None = None,
        text_batch_size: int = 256,
        ref: str | None = PINNED_REFS["facebookresearch/dinov2"],
        **kwargs: Any,
    ) -> None:
        super().__init__()
        if vocab is not None and not os.path.isfile(vocab):
            raise FileNotFoundError(f"vocab={os.fspath(vocab)!r}: no such file")
        # Fail at once, before torch.hub asks for anything it cannot reach.
        check_hub_source(repo, source, "dino.txt", _hint(), ref)
        target = hub_target(repo, source, ref)
        if entry_point == DINOTXT_ENTRY_POINT:
            require_hub_checkpoints(DINOTXT_CHECKPOINTS, "dino.txt weights", _WEIGHTS_HOST, _hint())
        if vocab is None:
            require_online(f"the dino.txt vocabulary ({_VOCAB})", _WEIGHTS_HOST, _hint(), hf=False)

        # A pinned commit is no branch or tag, which torch.hub's fork check looks for.
        pinned = {"skip_validation": True} if target != repo else {}
        model = torch.hub.load(target, entry_point, source=source, **{**pinned, **kwargs})
        self.repo, self.source, self.entry_point, self.ref = repo, source, entry_point, ref
        #: what torch.hub loaded, ``"owner/name:ref"``, or ``None`` (a local clone, unpinned)
        self.hub_ref = target if target != repo else None
        self.vocab = None if vocab is None else os.fspath(vocab)
        self.hub_kwargs = dict(kwargs)  # torch.hub.load's (spec)
        visual = model.visual_model
        if not (visual.use_class_token and visual.use_patch_tokens):
            raise ConfigError(
                f"entry_point={entry_point!r}: the model's embedding has no patch half "
                "(needs use_class_token and use_patch_tokens)"
            )
        self.model = model
        self.embed_dim = int(model.model_config.embed_dim)
        self.num_registers = int(visual.num_register_tokens)
        backbone = visual.backbone
        self.patch_size = int(getattr(backbone, "patch_size", None) or backbone.model.patch_size)
        if image_size is not None and image_size % self.patch_size:
            raise ConfigError(
                f"image_size={image_size}: not a multiple of the patch size {self.patch_size}"
            )
        self.image_size = image_size
        self.text_batch_size = int(text_batch_size)
        self.tokenizer = self._tokenizer(vocab)
        self.to(torch.device(device if device is not None else "cpu"))
        self.freeze()

    def _tokenizer(self, vocab: str | os.PathLike | None) -> Any:
        """The repo's own tokenizer, imported from the package the hub model came from."""
        text_pkg = type(self.model).__module__.rpartition(".")[0]  # dinov2.hub.text
        if vocab is None:
            hub_pkg = text_pkg.rpartition(".")[0]  # dinov2.hub
            return importlib.import_module(f"{hub_pkg}.dinotxt").get_tokenizer()
        tokenizer_cls = importlib.import_module(f"{text_pkg}.tokenizer").Tokenizer
        return tokenizer_cls(vocab_path=os.fspath(vocab))

    def spec(self) -> dict[str, Any]:
        """``kind`` and the constructor arguments that rebuild this encoder (``device`` aside)."""
        return {
            "kind": "dinotxt",
            "repo": self.repo,
            "source": self.source,
            "ref": self.ref,
            "entry_point": self.entry_point,
            "image_size": self.image_size,
            "vocab": self.vocab,
            "text_batch_size": self.text_batch_size,
            **self.hub_kwargs,
        }

    # ------------------------------------------------------------------ interface
    @property
    def input_rule(self) -> InputRule:
        return InputRule(self.patch_size, IMAGENET_DEFAULT_MEAN, IMAGENET_DEFAULT_STD)

    def encode(self, images: Tensor) -> DenseOutput:
        self.input_rule.check_size(images)
        b, _, h, w = images.shape
        p = self.patch_size
        x = resize_square(images.to(self.device, torch.float32), self.image_size)
        gh, gw = x.shape[-2] // p, x.shape[-1] // p
        visual = self.model.visual_model
        with torch.no_grad():
            cls, patches, registers = visual.get_backbone_features(x)
            tokens = visual.head(torch.cat([cls.unsqueeze(1), registers, patches], dim=1))
        head_cls, head_patches = tokens[:, 0], tokens[:, 1 + self.num_registers :]
        embedding = (
            torch.cat([head_cls, head_patches.mean(dim=1)], dim=-1)
            if visual.patch_tokens_pooler_type == "mean"
            else None
        )
        grid = (h // p, w // p)
        return DenseOutput(
            intermediates=tokens_to_grid(patches, (gh, gw), grid),
            language=tokens_to_grid(head_patches, (gh, gw), grid),
            embedding=embedding,
        )

    def text_features(self, texts: Sequence[str]) -> Tensor:
        """The patch half ``[K, embed_dim / 2]`` of dino.txt's text embedding (not normalised)."""
        texts = [texts] if isinstance(texts, str) else list(texts)
        out = []
        with torch.no_grad():
            for i in range(0, len(texts), self.text_batch_size):
                tokens = self.tokenizer.tokenize(texts[i : i + self.text_batch_size])
                out.append(self.model.encode_text(tokens.to(self.device)).float())
        features = torch.cat(out) if out else torch.zeros(0, self.embed_dim, device=self.device)
        return features[:, self.embed_dim // 2 :]

    def encode_text(self, texts: Sequence[str]) -> Tensor:
        return self.dense_text(self.text_features(texts))
