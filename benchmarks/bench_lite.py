"""ReSiReg Lite on the CPU: fp32 (the protocol) against bf16 and each SDPA backend.

Lite is one attention step per image (queries = keys = the normalised, upsampled
intermediates; values = the language tokens) through ``scaled_dot_product_attention``.
This measures, on one batch of the 25M architecture's features (EUPE ViT-S/16 and the 25M
head, random init, on generated images at ``--short-side``), the median time of Lite

- in fp32 and in bf16 (the features cast to bf16: what ``precision=bf16`` gives Lite, whose
  computation follows its inputs' dtype), and
- with PyTorch's default SDPA backend choice, and each CPU backend forced through
  ``torch.nn.attention.sdpa_kernel`` (``FLASH_ATTENTION``: the fused, O(N)-memory CPU
  kernel; ``MATH``: the reference that materialises the ``N x N`` scores),

and how far each output is from the fp32 default: the largest absolute difference of the
unit-norm features, the smallest cosine between the two features of a patch, and the share
of patches whose nearest of 150 random unit "class" vectors (the prediction's argmax
against ADE20K-sized prototypes) changes.

    python benchmarks/bench_lite.py                      # 8 images at 576 px (protocol size)
    python benchmarks/bench_lite.py --images 2 --short-side 288 --repeats 2   # quick
"""

from __future__ import annotations

import argparse
from contextlib import nullcontext

import torch
import torch.nn.functional as F
from torch.nn.attention import SDPBackend, sdpa_kernel

from _common import build_model, encode_generated, median_seconds
from resireg.reconstruct import ReSiRegLite

BACKENDS = {
    "default": None,
    "flash": SDPBackend.FLASH_ATTENTION,
    "math": SDPBackend.MATH,
}


def _features(images: int, short_side: int) -> tuple[torch.Tensor, torch.Tensor]:
    torch.manual_seed(0)
    out = encode_generated(build_model(), images, short_side)
    return out.intermediates, out.language


def main(argv: list[str] | None = None) -> None:
    parser = argparse.ArgumentParser(
        description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter
    )
    parser.add_argument("--images", type=int, default=8)
    parser.add_argument("--short-side", type=int, default=576)
    parser.add_argument("--repeats", type=int, default=3)
    parser.add_argument("--threads", type=int, default=None, help="torch threads")
    args = parser.parse_args(argv)
    if args.threads:
        torch.set_num_threads(args.threads)
    inter, lang = _features(args.images, args.short_side)
    lite = ReSiRegLite()  # the protocol's parameters (alpha 10, tau 0, s 2)
    classes = F.normalize(
        torch.randn(150, lang.shape[1], generator=torch.Generator().manual_seed(1)), dim=1
    )
    with torch.no_grad():
        reference = lite(inter, lang).float()
    ref_labels = torch.einsum("bdhw,kd->bkhw", reference, classes).argmax(1)
    b, _, h, w = reference.shape
    print(f"Lite on {b} x {h} x {w} points per image (from {args.short_side} px), "
          f"{torch.get_num_threads()} threads, median of {args.repeats}")  # fmt: skip
    print(
        "| dtype | SDPA backend | seconds | x fp32 default | max abs diff | min cosine "
        "| labels changed |\n|---|---|---:|---:|---:|---:|---:|"
    )
    base = None
    for dtype in (torch.float32, torch.bfloat16):
        q, v = inter.to(dtype), lang.to(dtype)
        for backend, choice in BACKENDS.items():
            context = (lambda c=choice: sdpa_kernel([c])) if choice is not None else nullcontext

            def call(q=q, v=v, context=context):
                with torch.no_grad(), context():
                    return lite(q, v)

            seconds = median_seconds(call, args.repeats)
            out = call().float()
            base = seconds if base is None else base
            cos = (out * reference).sum(1).min()
            labels = torch.einsum("bdhw,kd->bkhw", out, classes).argmax(1)
            changed = (labels != ref_labels).float().mean()
            name = "fp32" if dtype == torch.float32 else "bf16"
            print(f"| {name} | {backend} | {seconds:.3f} | {seconds / base:.2f} | "
                  f"{(out - reference).abs().max():.2e} | {cos:.5f} | {changed:.3%} |")  # fmt: skip


if __name__ == "__main__":
    main()
