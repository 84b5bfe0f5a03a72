"""TIPSv2 (Google DeepMind, "Text-Image Pretraining with Spatial awareness", v2) as a
:class:`DenseEncoder`: a backbone-only reference.

What the release is (read from github.com/google-deepmind/tips: ``README.md``,
``pytorch/image_encoder.py``, ``pytorch/text_encoder.py``,
``pytorch/run_image_encoder_inference.py``, ``pytorch/run_text_encoder_inference.py``,
``pytorch/checkpoints/download_checkpoints.sh``, ``pytorch/TIPS_Demo.ipynb`` and
``pytorch/TIPS_zeroshot_segmentation.ipynb``); this module reimplements the same
architecture with the same parameter names, so it loads the release files as they are:

- Files: one NumPy ``.npz`` per tower, a flat PyTorch state dict (name -> array), read with
  ``np.load(path, allow_pickle=False)`` and loaded with ``load_state_dict`` (strict):
  ``tips_v2_oss_{b14,l14,so14,g14}_{vision,text}.npz`` at
  ``https://storage.googleapis.com/tips_data/v2_0/checkpoints/pytorch/``; the text file also
  holds ``temperature`` (dropped, as the repo does). The tokenizer is a SentencePiece model
  shared with TIPS v1, ``https://storage.googleapis.com/tips_data/v1_0/checkpoints/tokenizer.model``
  (32000 ids, padding id 0). (JAX/Scenic ``.npz`` files with other names and layouts are
  published too, and converted weights as Hugging Face ``google/tipsv2-{b14,l14,so400m14,g14}``
  for transformers' ``Tipsv2Model``; neither is what this module reads.)
- Image and text encoders: :mod:`resireg.models.zoo.tips_towers` (their sizes and layers,
  with the release's parameter names).
- Input: RGB in [0, 1], no normalisation (``IMAGE_MEAN = (0, 0, 0)``, ``IMAGE_STD = (1, 1, 1)``).
- Zero-shot segmentation (``TIPS_zeroshot_segmentation.ipynb``): the MaskCLIP "values trick"
  on the last block. With ``x`` the last block's input, the value slice of
  ``attn.qkv(norm1(x))`` goes through ``attn.proj`` and ``ls1`` and is added to ``x`` (no
  attention), then the block's MLP residual (``x + ls2(mlp(norm2(x)))``) and the final
  ``norm`` follow; the patch tokens of that (CLS and register dropped) are compared, L2
  normalised, with the normalised text embeddings. No projection on either side.
- Image-text (``TIPS_Demo.ipynb``, Hugging Face ``Tipsv2Model``): the first CLS token after
  the final norm.

This adapter, in one pass of the vision tower:

- ``intermediates`` ``[B, D, h, w]``: the final-norm patch tokens of the ordinary forward
  (``x_norm_patchtokens``),
- ``language`` ``[B, D, h, w]``: the value-path patch tokens above (what TIPS segments with;
  a different tensor from the intermediates, sharing all blocks but the last), raw (the
  ``bb`` variant normalises). ``language_tokens="final"`` takes the final-norm patch tokens
  instead (then ``language`` and ``intermediates`` are the same tokens; the snippet once on
  the Hugging Face model cards did this, the repo's zero-shot notebook does not),
- ``embedding`` ``[B, D]``: the first CLS token (not normalised),
- ``encode_text``: the text tower's pooled embedding, L2-normalised (``[K, D]``, the width of
  the language tokens).

Resolution: with ``image_size=574`` (default) every canvas batch ``[B, 3, H, W]`` is resized
(bilinear, ``align_corners=False``) to ``574 x 574`` (41 x 41 patches; the 32 x 32
positional grid is interpolated as the repo does), and both dense maps are resized
bilinearly (``align_corners=False``) to the canvas's patch grid ``(H / 14, W / 14)``.
``image_size=None`` runs each canvas at its own size. TIPS's own zero-shot evaluation instead
slides 448 px windows (stride 336) over a short-side-448 image; here it is one pass.
"""

from __future__ import annotations

import os
from collections.abc import Mapping, Sequence
from dataclasses import asdict
from typing import Any, Protocol

import numpy as np
import torch
from torch import Tensor, nn

from resireg.errors import ConfigError
from resireg.models.frozen import FrozenModule
from resireg.models.hub import WeightsUnavailableError
from resireg.models.images import resize_square, tokens_to_grid
from resireg.models.interface import DenseEncoder, DenseOutput, InputRule
from resireg.models.zoo.tips_towers import (
    TIPS_VARIANTS,
    TipsArch,
    TipsTextEncoder,
    TipsVisionTransformer,
    resolve_arch,
)

__all__ = [
    "TIPS_TOKENIZER_URL",
    "TIPS_WEIGHTS_URL",
    "SentencePieceTokenizer",
    "TipsEncoder",
    "load_npz_state_dict",
]

#: Folder of the TIPSv2 PyTorch checkpoints (``<stem>_vision.npz``, ``<stem>_text.npz``).
TIPS_WEIGHTS_URL = "https://storage.googleapis.com/tips_data/v2_0/checkpoints/pytorch/"
#: The SentencePiece tokenizer (shared by TIPS v1 and v2).
TIPS_TOKENIZER_URL = "https://storage.googleapis.com/tips_data/v1_0/checkpoints/tokenizer.model"
TOKENIZER_FILE = "tokenizer.model"


# ---------------------------------------------------------------------- files and tokens
class _Tokenizer(Protocol):
    def encode(self, text: str) -> list[int]: ...


class SentencePieceTokenizer:
    """TIPS's tokenizer file through the ``sentencepiece`` package (no BOS / EOS)."""

    def __init__(self, path: str | os.PathLike) -> None:
        try:
            import sentencepiece
        except ImportError as err:
            raise ImportError(
                "TIPS's tokenizer is a SentencePiece model: pip install sentencepiece"
            ) from err
        self.path = os.fspath(path)
        self.model = sentencepiece.SentencePieceProcessor(model_file=self.path)

    def encode(self, text: str) -> list[int]:
        return list(self.model.encode(text))


_ASCII_LOWER = str.maketrans("ABCDEFGHIJKLMNOPQRSTUVWXYZ", "abcdefghijklmnopqrstuvwxyz")


def load_npz_state_dict(path: str | os.PathLike) -> dict[str, Tensor]:
    """A release ``.npz`` -> ``{name: float32 tensor}`` (``np.load(allow_pickle=False)``)."""
    with np.load(os.fspath(path), allow_pickle=False) as arrays:
        return {k: torch.from_numpy(np.asarray(arrays[k])).to(torch.float32) for k in arrays.files}


def _hint(stem: str) -> str:
    return (
        f"TIPSv2 weights are not downloaded automatically: fetch {stem}_vision.npz and "
        f"{stem}_text.npz from {TIPS_WEIGHTS_URL} and {TOKENIZER_FILE} from "
        f"{TIPS_TOKENIZER_URL} into one folder, then pass weights=/path/to/"
        f"{stem}_vision.npz (or the folder); the text weights and the tokenizer are found "
        f"beside it, or pass text_weights= / tokenizer=."
    )


def _resolve_files(
    arch: TipsArch,
    weights: str | os.PathLike | None,
    text_weights: str | os.PathLike | None,
    tokenizer: Any,
) -> tuple[str, str, Any]:
    """(vision npz, text npz, tokenizer path or object); a missing file raises at once."""
    stem = arch.stem or "tips_v2_oss_<size>14"
    hint = _hint(stem)
    if weights is None:
        raise WeightsUnavailableError(f"weights is not set. {hint}")
    vision = os.fspath(weights)
    if os.path.isdir(vision):
        if arch.stem is None:
            raise ConfigError(f"weights={vision!r}: a folder needs a release variant")
        vision = os.path.join(vision, f"{arch.stem}_vision.npz")
    if not os.path.isfile(vision):
        raise WeightsUnavailableError(f"weights={vision!r}: no such file. {hint}")
    folder = os.path.dirname(vision)
    if text_weights is None:
        base = os.path.basename(vision)
        if not base.endswith("_vision.npz"):
            raise WeightsUnavailableError(
                f"text_weights is not set and weights={vision!r} does not end in "
                f"'_vision.npz' (no release name to derive it from). {hint}"
            )
        text = os.path.join(folder, base[: -len("_vision.npz")] + "_text.npz")
    else:
        text = os.fspath(text_weights)
    if not os.path.isfile(text):
        raise WeightsUnavailableError(f"text_weights={text!r}: no such file. {hint}")
    if tokenizer is None or isinstance(tokenizer, (str, os.PathLike)):
        path = os.path.join(folder, TOKENIZER_FILE) if tokenizer is None else os.fspath(tokenizer)
        if not os.path.isfile(path):
            raise WeightsUnavailableError(f"tokenizer={path!r}: no such file. {hint}")
        tokenizer = path
    elif not callable(getattr(tokenizer, "encode", None)):
        raise TypeError("tokenizer: expected a path or an object with encode(text)")
    return vision, text, tokenizer


def _load(module: nn.Module, state: dict[str, Tensor], path: str) -> None:
    try:
        module.load_state_dict(state, strict=True, assign=True)
    except RuntimeError as err:
        raise ValueError(
            f"{path}: not a checkpoint of the configured TIPS size (variant): {err}"
        ) from err


# -------------------------------------------------------------------------------- encoder
class TipsEncoder(DenseEncoder, FrozenModule):
    """Frozen TIPSv2 dense encoder (see the module docstring).

    Args:
        variant: ``"B"``, ``"L"``, ``"So400m"`` (``"So"``) or ``"g"`` (the release's sizes,
            :data:`TIPS_VARIANTS`), or a mapping of :class:`TipsArch` fields (a custom size;
            ``base`` names a variant to start from).
        weights: the vision checkpoint ``<stem>_vision.npz`` (or the folder holding the
            release files). Required: nothing is downloaded.
        text_weights: the text checkpoint; ``None`` = ``<stem>_text.npz`` beside ``weights``.
        tokenizer: the SentencePiece ``tokenizer.model`` (``None`` = beside ``weights``), or
            an object with ``encode(text) -> list[int]``.
        image_size: side of the square model input every canvas is resized to (a multiple of
            14), or ``None`` to run canvases at their own size.
        language_tokens: ``"values"`` (the last block's value path, TIPS's zero-shot
            segmentation) or ``"final"`` (the final-norm patch tokens, = the intermediates).
        device: where the model is placed (default CPU).
        text_batch_size: texts per text-tower call.
    """

    def __init__(
        self,
        variant: str | Mapping[str, Any] | TipsArch = "g",
        weights: str | os.PathLike | None = None,
        text_weights: str | os.PathLike | None = None,
        tokenizer: str | os.PathLike | _Tokenizer | None = None,
        image_size: int | None = 574,
        language_tokens: str = "values",
        device: str | torch.device | None = None,
        text_batch_size: int = 256,
    ) -> None:
        super().__init__()
        if language_tokens not in ("values", "final"):
            raise ConfigError(f"language_tokens={language_tokens!r}: 'values' or 'final'")
        self.language_tokens = language_tokens
        arch = resolve_arch(variant)
        self.arch = arch
        self.patch_size = arch.patch_size
        if image_size is not None and (image_size <= 0 or image_size % self.patch_size):
            raise ConfigError(
                f"image_size={image_size}: not a positive multiple of the patch size "
                f"{self.patch_size}"
            )
        self.image_size = image_size
        self.text_batch_size = int(text_batch_size)
        vision_path, text_path, tok = _resolve_files(arch, weights, text_weights, tokenizer)
        self.weights, self.text_weights = vision_path, text_path
        self.tokenizer_path = tok if isinstance(tok, str) else None
        self.tokenizer = SentencePieceTokenizer(tok) if isinstance(tok, str) else tok

        with torch.device("meta"):  # no random init of ~1.5B parameters: the files fill them
            self.visual = TipsVisionTransformer(arch)
            self.text = TipsTextEncoder(arch)
        _load(self.visual, load_npz_state_dict(vision_path), vision_path)
        text_state = load_npz_state_dict(text_path)
        for name in [n for n in text_state if n.startswith("temperature")]:
            del text_state[name]  # the contrastive temperature (popped by the repo too)
        _load(self.text, text_state, text_path)
        self.to(torch.device(device if device is not None else "cpu"))
        self.freeze()

    def spec(self) -> dict[str, Any]:
        """``kind`` and the constructor arguments that rebuild this encoder (``device`` aside):
        the release size by name (else every :class:`TipsArch` field) and the resolved file
        paths. An encoder built with a tokenizer *object* has no such config (ValueError)."""
        if self.tokenizer_path is None:
            raise ValueError(
                f"this TipsEncoder was built with a tokenizer object "
                f"({type(self.tokenizer).__name__}); only a tokenizer file has a config"
            )
        named = [n for n, arch in TIPS_VARIANTS.items() if arch == self.arch]
        return {
            "kind": "tips",
            "variant": named[0] if named else asdict(self.arch),
            "weights": self.weights,
            "text_weights": self.text_weights,
            "tokenizer": self.tokenizer_path,
            "image_size": self.image_size,
            "language_tokens": self.language_tokens,
            "text_batch_size": self.text_batch_size,
        }

    # ------------------------------------------------------------------ interface
    @property
    def input_rule(self) -> InputRule:
        return InputRule(self.patch_size, (0.0, 0.0, 0.0), (1.0, 1.0, 1.0))

    def encode(self, images: Tensor) -> DenseOutput:
        self.input_rule.check_size(images)
        _, _, h, w = images.shape
        p = self.patch_size
        x = resize_square(images.to(self.device, torch.float32), self.image_size)
        native = (x.shape[-2] // p, x.shape[-1] // p)
        with torch.no_grad():
            cls, patches, values = self.visual.dense_features(x)
        grid = (h // p, w // p)
        intermediates = tokens_to_grid(patches, native, grid)
        if self.language_tokens == "final":
            language = intermediates
        else:
            language = tokens_to_grid(values, native, grid)
        return DenseOutput(intermediates, language, cls.float())

    def tokenize(self, texts: Sequence[str]) -> tuple[Tensor, Tensor]:
        """Texts -> (ids ``[K, 64]`` long, paddings ``[K, 64]`` float, 1 = padding), as the
        repo's ``Tokenizer.tokenize``: ASCII lower case, no BOS / EOS, cut / padded with 0."""
        n = self.arch.max_len
        ids = torch.zeros(len(texts), n, dtype=torch.long)
        for i, text in enumerate(texts):
            tokens = list(self.tokenizer.encode(text.translate(_ASCII_LOWER)))[:n]
            if not tokens:
                raise ValueError(f"text {text!r} has no tokens")
            ids[i, : len(tokens)] = torch.tensor(tokens, dtype=torch.long)
        return ids, (ids == 0).to(torch.float32)

    def text_features(self, texts: Sequence[str]) -> Tensor:
        """TIPS text embeddings ``[K, D]`` (not normalised)."""
        texts = [texts] if isinstance(texts, str) else list(texts)
        out = []
        with torch.no_grad():
            for i in range(0, len(texts), self.text_batch_size):
                ids, paddings = self.tokenize(texts[i : i + self.text_batch_size])
                out.append(self.text(ids.to(self.device), paddings.to(self.device)).float())
        return torch.cat(out) if out else torch.zeros(0, self.arch.width, device=self.device)

    def encode_text(self, texts: Sequence[str]) -> Tensor:
        return self.dense_text(self.text_features(texts))
