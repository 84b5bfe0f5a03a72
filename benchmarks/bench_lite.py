"""ReSiReg Lite on the CPU: its cost against the 25M VLM's image pass, per computation, and
its accuracy per dtype and SDPA backend.

Lite attends every upsampled point of an image to every other (queries = keys = the
normalised bilinear upsampling of the intermediates; values = the nearest upsampling of the
language tokens). ``ReSiRegLite(attention=...)`` computes it two exact ways
(docs/method.md#resireg-lite): ``sdpa`` (``scaled_dot_product_attention`` on the upsampled
points, ``4 N^2 W`` FLOP per image) and ``factorised`` (from the coarse grid's Gram matrix).

1. **Lite / VLM** (the issue's measure). One batch of ``--batch`` generated 3:4 images at
   ``--short-side`` (576 x 768: a 36 x 48 patch grid, 6,912 upsampled points per image), the
   25M architecture (EUPE ViT-S/16 and the 25M head, random init). Timed in alternating
   rounds (``--rounds``; one call of each per round, after one warm-up call each): the VLM's
   image pass (``encode_image`` with the ``bb`` variant: backbone + head, what the throughput
   protocol calls "VLM alone") and Lite on that batch's features with each computation (and,
   with ``--impl DIR``, the ``ReSiRegLite`` of another ``lite.py`` (or ``reconstruct.py``), e.g. the version
   before a change). Medians, each path's ratio to the VLM, and the ratios per round.
2. **Accuracy** (``--no-accuracy`` skips it). Each computation in fp32 and bf16 (the features
   cast: what ``precision=bf16`` gives Lite), SDPA with PyTorch's default backend choice and
   each CPU backend forced (``torch.nn.attention.sdpa_kernel``: ``FLASH_ATTENTION``, the fused
   O(N)-memory kernel; ``MATH``, the reference that materialises the ``N x N`` scores),
   against a float64 dense evaluation of the formula (per image, explicit softmax): the
   largest absolute difference of the unit-norm features, the smallest cosine between the two
   features of a patch, and the share of patches whose nearest of 150 random unit "class"
   vectors (ADE20K-sized prototypes) changes. Median seconds of ``--repeats`` calls.

    python benchmarks/bench_lite.py                      # batch 4 at 576 px (the protocol)
    python benchmarks/bench_lite.py --impl /tmp/base/src/resireg    # before/after, one run
    python benchmarks/bench_lite.py --batch 2 --short-side 288 --rounds 2 --repeats 1  # quick
"""

from __future__ import annotations

import argparse
import statistics
import time
from collections.abc import Callable
from contextlib import nullcontext
from typing import Any

import torch
import torch.nn.functional as F
from torch.nn.attention import SDPBackend, sdpa_kernel

from _common import build_model, generated_spec, median_seconds
from bench_reconstruct import load_impl
from resireg.method.lite import ReSiRegLite
from resireg.method.variants import build_variant
from resireg_train.data.segmentation import build_segmentation_set

BACKENDS = {
    "default": None,
    "flash": SDPBackend.FLASH_ATTENTION,
    "math": SDPBackend.MATH,
}


def generated_batch(model: Any, images: int, short_side: int) -> torch.Tensor:
    """The normalised pixels of ``images`` generated scenes at ``short_side`` (one batch)."""
    data = build_segmentation_set(generated_spec(images, short_side), model.input_rule.patch_size)
    pixels = torch.stack([data[i]["image"] for i in range(images)])
    return model.input_rule.normalize(pixels)


def dense_reference(
    inter: torch.Tensor, lang: torch.Tensor, alpha: float, upscale: int
) -> torch.Tensor:
    """Lite's formula (docs/method.md#resireg-lite, tau = 0, no prior) evaluated densely in
    float64, image by image: ``normalise(softmax(alpha u u^T) l)``. ``[B, Dl, H, W]``."""
    up = F.normalize(
        F.interpolate(inter.double(), scale_factor=upscale, mode="bilinear", align_corners=False),
        dim=1,
    )
    b, _, h, w = up.shape
    tokens = F.interpolate(lang.double(), size=(h, w), mode="nearest")
    out = torch.empty(b, lang.shape[1], h, w, dtype=torch.float64)
    for i in range(b):
        u = up[i].flatten(1).T  # [N, Dv]
        v = tokens[i].flatten(1).T  # [N, Dl]
        weights = torch.softmax(alpha * (u @ u.T), dim=1)
        out[i] = F.normalize(weights @ v, dim=1).T.reshape(-1, h, w)
    return out


def alternating(fns: dict[str, Callable[[], Any]], rounds: int) -> dict[str, list[float]]:
    """Seconds of one call of every function per round, the functions called in turn within
    each round (after one untimed warm-up call each), so load that drifts over minutes on a
    shared machine hits every path alike."""
    for fn in fns.values():
        fn()
    times: dict[str, list[float]] = {name: [] for name in fns}
    for _ in range(rounds):
        for name, fn in fns.items():
            start = time.perf_counter()
            fn()
            times[name].append(time.perf_counter() - start)
    return times


def lite_vs_vlm(model: Any, pixels: torch.Tensor, paths: dict[str, torch.nn.Module], rounds: int):
    """Table 1: the VLM's image pass against Lite on its features, alternating rounds."""
    bb = build_variant("bb")
    with torch.no_grad():
        out = model.encode(pixels)
    inter, lang = out.intermediates, out.language

    def vlm():
        with torch.no_grad():
            return model.encode_image(pixels, bb, normalized=True)

    fns: dict[str, Callable[[], Any]] = {"VLM image pass": vlm}
    for name, lite in paths.items():

        def call(lite=lite):
            with torch.no_grad():
                return lite(inter, lang)

        fns[f"Lite, {name}"] = call
    times = alternating(fns, rounds)
    base = times["VLM image pass"]
    print(
        f"\nLite against the VLM's image pass: batch {pixels.shape[0]} at "
        f"{pixels.shape[2]} x {pixels.shape[3]}, {torch.get_num_threads()} threads, "
        f"{rounds} alternating rounds after a warm-up\n"
    )
    print("| path | median s | x VLM (median) | x VLM per round |\n|---|---:|---:|---|")
    for name, ts in times.items():
        ratios = [t / v for t, v in zip(ts, base, strict=True)]
        print(f"| {name} | {statistics.median(ts):.3f} | "
              f"{statistics.median(ts) / statistics.median(base):.3f} | "
              f"{', '.join(f'{r:.3f}' for r in ratios)} |")  # fmt: skip
    return inter, lang


def accuracy(inter: torch.Tensor, lang: torch.Tensor, repeats: int) -> None:
    """Table 2: every computation and dtype against the float64 dense formula."""
    reference = dense_reference(inter, lang, alpha=10.0, upscale=2).float()
    classes = F.normalize(
        torch.randn(150, lang.shape[1], generator=torch.Generator().manual_seed(1)), dim=1
    )
    ref_labels = torch.einsum("bdhw,kd->bkhw", reference, classes).argmax(1)
    b, _, h, w = reference.shape
    print(f"\nAccuracy against float64: {b} x {h} x {w} points, median of {repeats}\n")
    print(
        "| dtype | computation | seconds | x fp32 sdpa default | max abs diff | min cosine "
        "| labels changed |\n|---|---|---:|---:|---:|---:|---:|"
    )
    rows = [("sdpa", name, choice) for name, choice in BACKENDS.items()]
    rows.append(("factorised", "", None))
    base = None
    for dtype in (torch.float32, torch.bfloat16):
        q, v = inter.to(dtype), lang.to(dtype)
        for attention, backend, choice in rows:
            lite = ReSiRegLite(attention=attention)  # the protocol's alpha 10, tau 0, s 2
            context = (lambda c=choice: sdpa_kernel([c])) if choice is not None else nullcontext

            def call(q=q, v=v, context=context, lite=lite):
                with torch.no_grad(), context():
                    return lite(q, v)

            seconds = median_seconds(call, repeats)
            out = call().float()
            base = seconds if base is None else base
            cos = (out * reference).sum(1).min()
            labels = torch.einsum("bdhw,kd->bkhw", out, classes).argmax(1)
            changed = (labels != ref_labels).float().mean()
            name = "fp32" if dtype == torch.float32 else "bf16"
            label = f"sdpa ({backend})" if attention == "sdpa" else attention
            print(f"| {name} | {label} | {seconds:.3f} | {seconds / base:.2f} | "
                  f"{(out - reference).abs().max():.2e} | {cos:.6f} | {changed:.3%} |")  # fmt: skip


def main(argv: list[str] | None = None) -> None:
    parser = argparse.ArgumentParser(
        description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter
    )
    parser.add_argument("--batch", type=int, default=4)
    parser.add_argument("--short-side", type=int, default=576)
    parser.add_argument("--rounds", type=int, default=5, help="alternating rounds of table 1")
    parser.add_argument("--repeats", type=int, default=3, help="calls per row of table 2")
    parser.add_argument("--threads", type=int, default=None, help="torch threads")
    parser.add_argument(
        "--impl", default=None,
        help="folder of another lite.py or reconstruct.py (and its clustering) whose Lite joins "
        "table 1",
    )  # fmt: skip
    parser.add_argument("--no-accuracy", action="store_true", help="skip table 2")
    args = parser.parse_args(argv)
    if args.threads:
        torch.set_num_threads(args.threads)
    torch.manual_seed(0)
    model = build_model()
    pixels = generated_batch(model, args.batch, args.short_side)
    paths: dict[str, torch.nn.Module] = {
        "sdpa": ReSiRegLite(attention="sdpa"),
        "factorised": ReSiRegLite(attention="factorised"),
    }
    if args.impl:
        paths[f"--impl ({args.impl})"] = load_impl(args.impl).lite.ReSiRegLite()
    inter, lang = lite_vs_vlm(model, pixels, paths, args.rounds)
    if not args.no_accuracy:
        accuracy(inter, lang, args.repeats)


if __name__ == "__main__":
    main()
