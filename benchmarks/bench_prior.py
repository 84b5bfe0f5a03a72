"""Seconds per image of the SAM 2.1 segmentation prior (``resireg.priors.SamPrior``).

Two random-initialised SAM 2 models in transformers format, saved to a temporary folder and
loaded by path (the weights do not change the model's cost; they change how many masks
survive the filters, hence the post-processing cost, see below):

- ``tiny``: the test model of ``tests/helpers/sam.py`` (128 px input, ~126k parameters),
- ``hiera-t``: the Hiera-T architecture of ``facebook/sam2.1-hiera-tiny`` (``Sam2Config()``'s
  defaults: Hiera stages [1, 2, 7, 2], widths 96..768, heads 1..8, global attention in
  blocks 5, 7, 9, window sizes [8, 4, 14, 7]; 256-d FPN neck and two-way mask decoder;
  1024 x 1024 input).

The image is 576 x 768 (the protocol's 576 px shorter side, 4:3), with blocky structure.
Timed: the image encoder alone (``get_image_embeddings`` of the 1024 x 1024 input), then
``provider.masks(image)`` end to end (the pipeline's resize, the image encoder once,
``points_per_side**2`` point prompts decoded ``points_per_batch`` at a time, every one of
the ``3 points_per_side**2`` masks upsampled to the image size and scored for stability,
the IoU / stability filters, RLE, NMS), and the instance-map rule apart; best of
``--repeats`` after ``--warmup`` calls. The upsampling and scoring of all masks happen
before the filters, so they cost the same for any weights; the RLE of the masks that pass
does not: SAM 2's default thresholds (0.8 / 0.95) keep no mask of these random models,
trained weights keep tens (their encoding adds to these figures).

    python benchmarks/bench_prior.py [--repeats 1] [--warmup 1] [--models tiny hiera-t]
"""

from __future__ import annotations

import argparse
import sys
import tempfile
import time
from pathlib import Path

import torch

sys.path.insert(0, str(Path(__file__).resolve().parents[1] / "tests"))

from helpers.sam import save_tiny_sam  # noqa: E402
from resireg.priors import SamPrior, masks_to_instances  # noqa: E402


def save_hiera_t(path: Path) -> Path:
    """Random-initialised SAM 2 with the Hiera-T configuration, saved with its processor."""
    from transformers import Sam2Config, Sam2ImageProcessor, Sam2Model

    torch.manual_seed(0)
    model = Sam2Model(Sam2Config()).eval()
    model.save_pretrained(path)
    Sam2ImageProcessor().save_pretrained(path)
    return path


def test_image(height: int, width: int) -> torch.Tensor:
    """uint8 ``[3, H, W]``: 12 x 16 blocks of random colour plus mild noise."""
    g = torch.Generator().manual_seed(0)
    blocks = torch.randint(0, 256, (3, 12, 16), generator=g)
    big = torch.nn.functional.interpolate(blocks[None].float(), size=(height, width))[0]
    noise = torch.randint(-10, 11, big.shape, generator=g)
    return (big + noise).clamp(0, 255).to(torch.uint8)


def best_seconds(fn, repeats: int, warmup: int) -> tuple[float, object]:
    """Best wall seconds of ``repeats`` calls after ``warmup`` calls, and the last result."""
    for _ in range(warmup):
        fn()
    best, out = float("inf"), None
    for _ in range(repeats):
        t = time.perf_counter()
        out = fn()
        best = min(best, time.perf_counter() - t)
    return best, out


def main() -> None:
    parser = argparse.ArgumentParser(
        description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter
    )
    parser.add_argument("--repeats", type=int, default=1)
    parser.add_argument("--warmup", type=int, default=1)
    parser.add_argument("--models", nargs="+", default=["tiny", "hiera-t"])
    parser.add_argument("--height", type=int, default=576)
    parser.add_argument("--width", type=int, default=768)
    parser.add_argument("--points-per-side", type=int, default=32)
    parser.add_argument("--threads", type=int, default=None)
    parser.add_argument("--device", default="cpu")
    args = parser.parse_args()
    if args.threads:
        torch.set_num_threads(args.threads)
    image = test_image(args.height, args.width)
    print(f"threads {torch.get_num_threads()}, device {args.device}, image {tuple(image.shape)}")
    print("model | parameters | image encoder s | s / image (masks) | map rule s | masks | ids")
    with tempfile.TemporaryDirectory() as tmp:
        for name in args.models:
            folder = Path(tmp) / name
            if name == "tiny":
                save_tiny_sam(folder)
            elif name == "hiera-t":
                save_hiera_t(folder)
            else:
                raise SystemExit(f"--models: unknown {name!r} (tiny, hiera-t)")
            prior = SamPrior(
                model=str(folder), device=args.device, points_per_side=args.points_per_side
            )
            pipe = prior._generator
            net = pipe.model
            pixels = pipe.image_processor(images=image, return_tensors="pt")["pixel_values"]
            pixels = pixels.to(prior.device)
            with torch.inference_mode():
                encoder_s, _ = best_seconds(
                    lambda p=pixels, n=net: n.get_image_embeddings(p), args.repeats, args.warmup
                )
            masks_s, (masks, scores) = best_seconds(
                lambda p=prior: p.masks(image), args.repeats, args.warmup
            )
            rule_s, ids = best_seconds(
                lambda m=masks, s=scores: masks_to_instances(m, s), args.repeats, 1
            )
            n_params = sum(p.numel() for p in net.parameters())
            print(
                f"{name} | {n_params / 1e6:.2f}M | {encoder_s:.3f} | {masks_s:.3f} | "
                f"{rule_s:.4f} | {masks.shape[0]} | {int(ids.max())}",
                flush=True,
            )


if __name__ == "__main__":
    main()
