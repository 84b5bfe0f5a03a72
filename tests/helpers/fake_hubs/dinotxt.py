"""The fake dino.txt hub code of facebookresearch/dinov2: :data:`DINOTXT_FILES` (``hubconf.py`` ->
``dinov2.hub.dinotxt``; ``DinoTxt``, its tokenizer package, the backbone
:data:`helpers.fake_hubs.dinov2.DINOV2_VIT`), its vocabulary (:data:`DINOTXT_VOCAB`,
:data:`DINOTXT_WORDS`) and :func:`dinotxt_repo`, a local clone.
"""

from __future__ import annotations

import gzip
import textwrap
from pathlib import Path

from helpers.fake_hubs.common import write_repo
from helpers.fake_hubs.dinov2 import DINOV2_VIT

DINOTXT_VOCAB = "dinov2/hub/bpe_simple_vocab_16e6.txt.gz"  # inside the fake repo
DINOTXT_WORDS = "a photo of the cat dog car sky road tree person bicycle"

DINOTXT_FILES = {
    "hubconf.py": """
        dependencies = ["torch"]
        from dinov2.hub.dinotxt import dinov2_vitl14_reg4_dinotxt_tet1280d20h24l
    """,
    "dinov2/__init__.py": "",
    "dinov2/hub/__init__.py": "",
    "dinov2/layers/__init__.py": """
        from torch import nn

        class NestedTensorBlock(nn.Module):  # pre-norm attention block
            def __init__(self, dim, num_heads):
                super().__init__()
                self.norm1 = nn.LayerNorm(dim)
                self.attn = nn.MultiheadAttention(dim, num_heads, batch_first=True)
                self.norm2 = nn.LayerNorm(dim)
                self.mlp = nn.Sequential(nn.Linear(dim, 2 * dim), nn.GELU(), nn.Linear(2 * dim, dim))

            def forward(self, x):
                y = self.norm1(x)
                x = x + self.attn(y, y, y, need_weights=False)[0]
                return x + self.mlp(self.norm2(x))
    """,
    "dinov2/models/__init__.py": "",
    "dinov2/models/vision_transformer.py": textwrap.dedent(
        """
        import math
        import torch
        from torch import nn
        from dinov2.layers import NestedTensorBlock as Block
        """
    )
    + DINOV2_VIT,
    "dinov2/hub/text/dinov2_wrapper.py": """
        import torch

        class DINOv2Wrapper(torch.nn.Module):
            def __init__(self, model):
                super().__init__()
                self.model = model
                self.embed_dim = model.embed_dim
                self.num_heads = model.num_heads
                self.num_register_tokens = model.num_register_tokens

            def get_intermediate_layers(self, x, n=1, reshape=False, return_class_token=False,
                                        return_register_tokens=False, norm=True):
                outputs = self.model._get_intermediate_layers_not_chunked(x, n)
                if norm:
                    outputs = [self.model.norm(out) for out in outputs]
                r = self.model.num_register_tokens
                class_tokens = [out[:, 0] for out in outputs]
                register_tokens = [out[:, 1 : 1 + r] for out in outputs]
                outputs = [out[:, 1 + r :] for out in outputs]
                assert not reshape
                if return_class_token and return_register_tokens:
                    return tuple(zip(outputs, class_tokens, register_tokens))
                if return_class_token:
                    return tuple(zip(outputs, class_tokens))
                if return_register_tokens:
                    return tuple(zip(outputs, register_tokens))
                return tuple(outputs)
    """,
    "dinov2/hub/text/vision_tower.py": """
        import torch
        from torch import nn
        from dinov2.layers import NestedTensorBlock as AttentionBlock

        class VisionHead(nn.Module):
            def __init__(self, input_dim, embed_dim, num_heads, num_blocks, use_class_token,
                         use_patch_tokens):
                super().__init__()
                self.block_list = nn.ModuleList(
                    AttentionBlock(input_dim, num_heads) for _ in range(num_blocks))
                self.ln_final = nn.LayerNorm(input_dim)
                self.num_blocks = num_blocks
                multiplier = 2 if use_class_token and use_patch_tokens else 1
                self.linear_projection = nn.Identity()
                if multiplier * input_dim != embed_dim:
                    self.linear_projection = nn.Linear(input_dim, embed_dim // multiplier, bias=False)

            def forward(self, image_tokens):
                for block in self.block_list:
                    image_tokens = block(image_tokens)
                return self.linear_projection(self.ln_final(image_tokens))

        class VisionTower(nn.Module):
            def __init__(self, backbone, embed_dim, num_head_blocks, use_class_token,
                         use_patch_tokens, patch_token_layer, patch_tokens_pooler_type):
                super().__init__()
                self.backbone = backbone
                self.use_class_token = use_class_token
                self.use_patch_tokens = use_patch_tokens
                self.patch_token_layer = patch_token_layer
                self.patch_tokens_pooler_type = patch_tokens_pooler_type
                self.num_register_tokens = backbone.num_register_tokens
                self.head = VisionHead(backbone.embed_dim, embed_dim, backbone.num_heads,
                                       num_head_blocks, use_class_token, use_patch_tokens)

            def get_backbone_features(self, images):
                tokens = self.backbone.get_intermediate_layers(
                    images, n=self.patch_token_layer, return_class_token=True,
                    return_register_tokens=True)
                return tokens[-1][1], tokens[0][0], tokens[0][2]

            def get_class_and_patch_tokens(self, images):
                class_token, patch_tokens, register_tokens = self.get_backbone_features(images)
                image_tokens = self.head(
                    torch.cat([class_token.unsqueeze(1), register_tokens, patch_tokens], dim=1))
                return image_tokens[:, 0], image_tokens[:, self.num_register_tokens + 1 :]

            def forward(self, images):
                class_token, patch_tokens = self.get_class_and_patch_tokens(images)
                return torch.cat([class_token, patch_tokens.mean(dim=1)], dim=-1)
    """,
    "dinov2/hub/text/text_tower.py": """
        import torch
        from torch import nn
        from dinov2.layers import NestedTensorBlock

        class TextTransformer(nn.Module):
            def __init__(self, context_length, vocab_size, dim, num_heads, num_layers):
                super().__init__()
                self.embed_dim, self.num_heads = dim, num_heads
                self.token_embedding = nn.Embedding(vocab_size, dim)
                self.positional_embedding = nn.Parameter(torch.randn(context_length, dim))
                self.blocks = nn.ModuleList(NestedTensorBlock(dim, num_heads) for _ in range(num_layers))
                self.ln_final = nn.LayerNorm(dim)

            def forward(self, token_indices):
                x = self.token_embedding(token_indices) + self.positional_embedding[: token_indices.shape[1]]
                for block in self.blocks:
                    x = block(x)
                return self.ln_final(x)

        class TextTower(nn.Module):
            def __init__(self, backbone, embed_dim):
                super().__init__()
                self.backbone = backbone
                self.head = nn.Linear(backbone.embed_dim, embed_dim, bias=False)
                self.tokens_pooler_type = "argmax"

            def forward(self, token_indices):
                text_tokens = self.head(self.backbone(token_indices))
                return text_tokens[torch.arange(text_tokens.shape[0]), token_indices.argmax(dim=-1)]
    """,
    "dinov2/hub/text/dinotxt_model.py": """
        from dataclasses import dataclass
        import torch.nn.functional as F
        from torch import nn
        from .vision_tower import VisionTower
        from .text_tower import TextTower

        @dataclass
        class DinoTxtConfig:
            embed_dim: int
            vision_model_use_class_token: bool = True
            vision_model_use_patch_tokens: bool = True
            vision_model_num_head_blocks: int = 2
            vision_model_patch_tokens_pooler_type: str = "mean"
            vision_model_patch_token_layer: int = 1

        class DinoTxt(nn.Module):
            def __init__(self, model_config, vision_backbone, text_backbone):
                super().__init__()
                c = self.model_config = model_config
                self.visual_model = VisionTower(
                    vision_backbone, c.embed_dim, c.vision_model_num_head_blocks,
                    c.vision_model_use_class_token, c.vision_model_use_patch_tokens,
                    c.vision_model_patch_token_layer, c.vision_model_patch_tokens_pooler_type)
                self.text_model = TextTower(text_backbone, c.embed_dim)

            def get_visual_class_and_patch_tokens(self, image):
                return self.visual_model.get_class_and_patch_tokens(image)

            def encode_image(self, image, normalize=False):
                features = self.visual_model(image)
                return F.normalize(features, dim=-1) if normalize else features

            def encode_text(self, text, normalize=False):
                features = self.text_model(text)
                return F.normalize(features, dim=-1) if normalize else features
    """,
    "dinov2/hub/text/tokenizer.py": """
        import gzip
        import torch

        class Tokenizer:  # whitespace words of the vocabulary file; SOT / EOT are the top ids
            def __init__(self, vocab_path):
                self.vocab_path = vocab_path
                with gzip.open(vocab_path) as f:
                    words = f.read().decode("utf-8").split()
                self.encoder = {w: i + 2 for i, w in enumerate(words)}  # 0 pad, 1 unknown
                self.encoder["<|startoftext|>"] = len(words) + 2
                self.encoder["<|endoftext|>"] = len(words) + 3

            def encode(self, text):
                return [self.encoder.get(w, 1) for w in text.lower().split()]

            def tokenize(self, texts, context_length=77):
                if isinstance(texts, str):
                    texts = [texts]
                sot, eot = self.encoder["<|startoftext|>"], self.encoder["<|endoftext|>"]
                result = torch.zeros(len(texts), context_length, dtype=torch.long)
                for i, text in enumerate(texts):
                    tokens = [sot] + self.encode(text) + [eot]
                    result[i, : len(tokens)] = torch.tensor(tokens[:context_length])
                return result
    """,
    "dinov2/hub/dinotxt.py": """
        import os
        from dinov2.models.vision_transformer import DinoVisionTransformer

        def dinov2_vitl14_reg4_dinotxt_tet1280d20h24l():
            from .text.dinotxt_model import DinoTxtConfig, DinoTxt
            from .text.dinov2_wrapper import DINOv2Wrapper
            from .text.text_tower import TextTransformer

            vision_backbone = DINOv2Wrapper(DinoVisionTransformer(
                img_size=56, depth=2, num_register_tokens=4, interpolate_antialias=True,
                interpolate_offset=0.0))
            text_backbone = TextTransformer(context_length=77, vocab_size=64, dim=32,
                                            num_heads=2, num_layers=1)
            model = DinoTxt(DinoTxtConfig(embed_dim=64), vision_backbone, text_backbone)
            model.eval()
            return model

        def get_tokenizer():  # the real one downloads the vocabulary; this one is bundled
            from .text.tokenizer import Tokenizer
            return Tokenizer(vocab_path=os.path.join(os.path.dirname(__file__),
                                                     "bpe_simple_vocab_16e6.txt.gz"))
    """,
}


def dinotxt_repo(folder: Path) -> Path:
    """A local facebookresearch/dinov2 clone with dino.txt (:data:`DINOTXT_FILES`) and its
    vocabulary at ``folder / DINOTXT_VOCAB``."""
    write_repo(folder, DINOTXT_FILES)
    with gzip.open(folder / DINOTXT_VOCAB, "wb") as f:
        f.write(DINOTXT_WORDS.replace(" ", "\n").encode())
    return folder
