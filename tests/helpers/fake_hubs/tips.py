"""TIPSv2's release files (no hub: ``.npz`` state dicts) at a tiny size (:data:`TIPS_TINY`):
:func:`write_tips_release` writes them, :class:`TipsWordTokenizer` stands in for the
SentencePiece model and :func:`train_sentencepiece` trains a real tokenizer file.
"""

from __future__ import annotations

from pathlib import Path

import numpy as np

TIPS_P, TIPS_WIDTH, TIPS_DEPTH, TIPS_HEADS, TIPS_GRID, TIPS_VOCAB, TIPS_TEXT_MLP = (
    14,
    32,
    2,
    2,
    4,
    64,
    48,
)
TIPS_STEM = "tips_v2_oss_tiny14"
TIPS_TINY = {
    "width": TIPS_WIDTH,
    "depth": TIPS_DEPTH,
    "heads": TIPS_HEADS,
    "mlp_hidden": 64,
    "ffn": "mlp",
    "text_layers": 1,
    "text_heads": TIPS_HEADS,
    "text_mlp": TIPS_TEXT_MLP,
    "pos_grid": TIPS_GRID,
    "vocab_size": TIPS_VOCAB,
    "stem": TIPS_STEM,
}


class TipsWordTokenizer:
    """A stand-in for the SentencePiece model: one id per word (1..TIPS_VOCAB-1), 0 never used."""

    def __init__(self):
        self.seen = []

    def encode(self, text):
        self.seen.append(text)
        return [1 + sum(map(ord, w)) % (TIPS_VOCAB - 1) for w in text.split()]


def _tips_vision_shapes(width, depth, pos_grid, ffn, mlp_hidden, patch=TIPS_P):
    d = width
    shapes = {
        "cls_token": (1, 1, d),
        "pos_embed": (1, 1 + pos_grid**2, d),
        "register_tokens": (1, 1, d),
        "mask_token": (1, d),
        "patch_embed.proj.weight": (d, 3, patch, patch),
        "patch_embed.proj.bias": (d,),
        "norm.weight": (d,),
        "norm.bias": (d,),
    }
    for i in range(depth):
        b = f"blocks.{i}."
        shapes.update({
            b + "norm1.weight": (d,), b + "norm1.bias": (d,),
            b + "attn.qkv.weight": (3 * d, d), b + "attn.qkv.bias": (3 * d,),
            b + "attn.proj.weight": (d, d), b + "attn.proj.bias": (d,),
            b + "ls1.gamma": (d,),
            b + "norm2.weight": (d,), b + "norm2.bias": (d,),
            b + "ls2.gamma": (d,),
        })  # fmt: skip
        if ffn == "swiglu":
            h = (int(mlp_hidden * 2 / 3) + 7) // 8 * 8
            shapes.update({
                b + "mlp.w12.weight": (2 * h, d), b + "mlp.w12.bias": (2 * h,),
                b + "mlp.w3.weight": (d, h), b + "mlp.w3.bias": (d,),
            })  # fmt: skip
        else:
            shapes.update({
                b + "mlp.fc1.weight": (mlp_hidden, d), b + "mlp.fc1.bias": (mlp_hidden,),
                b + "mlp.fc2.weight": (d, mlp_hidden), b + "mlp.fc2.bias": (d,),
            })  # fmt: skip
    return shapes


def _tips_text_shapes(width, layers, mlp, vocab):
    d = width
    shapes = {
        "token_embedding.weight": (vocab, d),
        "ln_final.weight": (d,),
        "ln_final.bias": (d,),
        "temperature": (),
    }
    for i in range(layers):
        b = f"transformer.resblocks.{i}."
        shapes.update({
            b + "attn.in_proj_weight": (3 * d, d), b + "attn.in_proj_bias": (3 * d,),
            b + "attn.out_proj.weight": (d, d), b + "attn.out_proj.bias": (d,),
            b + "ln_1.weight": (d,), b + "ln_1.bias": (d,),
            b + "mlp.c_fc.weight": (mlp, d), b + "mlp.c_fc.bias": (mlp,),
            b + "mlp.c_proj.weight": (d, mlp), b + "mlp.c_proj.bias": (d,),
            b + "ln_2.weight": (d,), b + "ln_2.bias": (d,),
        })  # fmt: skip
    return shapes


def _tips_random(shapes, seed):
    rng = np.random.default_rng(seed)
    out = {}
    for name, shape in shapes.items():
        x = rng.standard_normal(shape).astype(np.float32)
        scale = 0.1 if name.endswith(("norm1.weight", "norm2.weight", "gamma")) else 0.2
        offset = 1.0 if name.endswith(("norm.weight", "norm1.weight", "norm2.weight")) else 0.0
        out[name] = offset + scale * x if shape else np.float32(0.07)
    return out


def write_tips_release(folder, ffn="mlp", seed=0):
    """A tiny TIPS release (google-deepmind/tips ``pytorch/image_encoder.py`` /
    ``text_encoder.py`` parameter names and shapes): ``<TIPS_STEM>_vision.npz``, ``<TIPS_STEM>_text.npz`` and ``tokenizer.model`` in ``folder``."""
    vision = _tips_random(
        _tips_vision_shapes(TIPS_WIDTH, TIPS_DEPTH, TIPS_GRID, ffn, TIPS_TINY["mlp_hidden"]), seed
    )
    text = _tips_random(_tips_text_shapes(TIPS_WIDTH, 1, TIPS_TEXT_MLP, TIPS_VOCAB), seed + 1)
    np.savez(folder / f"{TIPS_STEM}_vision.npz", **vision)
    np.savez(folder / f"{TIPS_STEM}_text.npz", **text)
    (folder / "tokenizer.model").write_bytes(b"not read: a tokenizer object is passed")
    return vision, text


def train_sentencepiece(folder: Path) -> Path:
    """A real SentencePiece model (``folder / "sp.model"``, trained here on a few captions; pad
    id 0, no BOS / EOS, as TIPS's tokenizer), for loading by path like ``tokenizer.model``."""
    import sentencepiece as spm

    corpus = folder / "corpus.txt"
    corpus.write_text("\n".join(["a photo of a cat", "a photo of the sky", "road and tree"] * 20))
    spm.SentencePieceTrainer.train(
        input=str(corpus), model_prefix=str(folder / "sp"), vocab_size=TIPS_VOCAB // 2,
        model_type="unigram", pad_id=0, unk_id=1, bos_id=-1, eos_id=-1, hard_vocab_limit=False,
    )  # fmt: skip
    return folder / "sp.model"
