"""A tiny random-initialised SAM 2 in transformers format, saved to a local directory.

The same classes as ``facebook/sam2.1-hiera-tiny`` (``Sam2Model``: Hiera backbone, FPN neck,
prompt encoder, two-way mask decoder; ``Sam2ImageProcessor``) at toy sizes: 128 x 128
input, Hiera stages [1, 2, 2, 1] of width 8..64, 32-d neck and decoder (about 126k
parameters; built and saved in well under a second). ``SamPrior(model=<dir>)`` loads it
offline by path, so tests and notebooks run the real pipeline without the hub.

    python tests/helpers/sam.py /tmp/tiny-sam2      # or: from helpers.sam import save_tiny_sam
"""

from __future__ import annotations

import sys
from pathlib import Path

#: Side of the tiny model's square input (SAM 2 proper: 1024).
TINY_SAM_SIZE = 128


def tiny_sam_config():
    """``Sam2Config`` of the tiny model (image 128, backbone strides 4/8/16/32)."""
    from transformers import (
        Sam2Config,
        Sam2HieraDetConfig,
        Sam2MaskDecoderConfig,
        Sam2PromptEncoderConfig,
        Sam2VisionConfig,
    )

    size, hidden = TINY_SAM_SIZE, 32
    backbone = Sam2HieraDetConfig(
        hidden_size=8,
        num_attention_heads=1,
        image_size=[size, size],
        blocks_per_stage=[1, 2, 2, 1],
        embed_dim_per_stage=[8, 16, 32, 64],
        num_attention_heads_per_stage=[1, 1, 1, 1],
        window_size_per_stage=[4, 4, 4, 2],
        global_attention_blocks=[4],  # not a stage's first block (its window would pool)
        window_positional_embedding_background_size=[4, 4],
    )
    vision = Sam2VisionConfig(
        backbone_config=backbone,
        backbone_channel_list=[64, 32, 16, 8],
        backbone_feature_sizes=[[size // 4] * 2, [size // 8] * 2, [size // 16] * 2],
        fpn_hidden_size=hidden,
    )
    prompt = Sam2PromptEncoderConfig(
        hidden_size=hidden, image_size=size, patch_size=16, mask_input_channels=4
    )
    decoder = Sam2MaskDecoderConfig(
        hidden_size=hidden, mlp_dim=64, num_attention_heads=2, iou_head_hidden_dim=32
    )
    return Sam2Config(
        vision_config=vision, prompt_encoder_config=prompt, mask_decoder_config=decoder
    )


def save_tiny_sam(path: str | Path, seed: int = 0) -> Path:
    """Build the tiny SAM 2 (random weights from ``seed``) and its image processor and save
    both to ``path`` (created); returns ``path``."""
    import torch
    from transformers import Sam2ImageProcessor, Sam2Model

    path = Path(path)
    path.mkdir(parents=True, exist_ok=True)
    state = torch.random.get_rng_state()
    torch.manual_seed(seed)
    try:
        model = Sam2Model(tiny_sam_config()).eval()
    finally:
        torch.random.set_rng_state(state)
    size = {"height": TINY_SAM_SIZE, "width": TINY_SAM_SIZE}
    mask_size = {"height": TINY_SAM_SIZE // 4, "width": TINY_SAM_SIZE // 4}
    model.save_pretrained(path)
    Sam2ImageProcessor(size=size, mask_size=mask_size).save_pretrained(path)
    return path


if __name__ == "__main__":
    print(save_tiny_sam(sys.argv[1] if len(sys.argv) > 1 else "tiny-sam2"))
