"""Per encoder, at its protocol resolution with same-architecture random weights: seconds per
image of the encoder pass, and of BB / Calib / Lite / Full on its outputs (CPU by default).

The canvas is the protocol's: shorter side 576, here a 576 x 768 image, sides rounded to the
encoder's patch size; CLIP resizes it to its native 224 / 336 and upsamples its maps back to
the canvas grid. Reported as ratios to the encoder pass, one run (shared machines drift).
RADIO, RADSeg and dino.txt need their hub repositories' code (torch.hub) and checkpoints to
build, which this project's machines do not have: they are not timed here.

    python benchmarks/bench_encoders.py [--encoders resireg_vlm clip_vit_b16 clip_vit_l14_336]
"""

from __future__ import annotations

import argparse
import time

import torch

from _common import TINY_TEXT
from resireg.method.variants import build_variant
from resireg.models import ClipEncoder, ResiregVLM
from resireg.specs.variants import VARIANTS


def _encoders(names: list[str]) -> dict[str, torch.nn.Module]:
    builders = {
        # The 25M architecture: EUPE ViT-S/16 (random), the 2-block head; the text tower does
        # not take part in an image pass, so the tiny one stands in.
        "resireg_vlm": lambda: ResiregVLM.build(
            {"model_name": "eupe_vit_s16", "weights": None}, {}, TINY_TEXT
        ),
        "clip_vit_b16": lambda: ClipEncoder("ViT-B-16", weights=None),
        "clip_vit_l14_336": lambda: ClipEncoder("ViT-L-14-336", weights=None),
    }
    return {n: builders[n]().eval() for n in names}


def _time(fn, repeats: int) -> float:
    fn()  # warm-up
    best = float("inf")
    for _ in range(repeats):
        start = time.perf_counter()
        fn()
        best = min(best, time.perf_counter() - start)
    return best


def main() -> None:
    parser = argparse.ArgumentParser(
        description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter
    )
    parser.add_argument("--encoders", nargs="+", default=["resireg_vlm", "clip_vit_b16",
                        "clip_vit_l14_336"])  # fmt: skip
    parser.add_argument("--size", nargs=2, type=int, default=(576, 768), metavar=("H", "W"))
    parser.add_argument("--repeats", type=int, default=2)
    parser.add_argument("--n-prototypes", type=int, default=36)
    args = parser.parse_args()
    torch.manual_seed(0)
    print(f"CPU threads {torch.get_num_threads()}, canvas {args.size[0]} x {args.size[1]}")
    print("| encoder | parameters | grid | encode s | " + " | ".join(
        f"+{v} (x encode)" for v in VARIANTS) + " |")  # fmt: skip
    print("|---|---:|---|---:|" + "---:|" * len(VARIANTS))
    for name, encoder in _encoders(args.encoders).items():
        rule = encoder.input_rule
        image = torch.rand(3, *args.size)
        x = rule.normalize(rule.resize(image, args.size[0])[None])
        with torch.no_grad():
            t_encode = _time(lambda e=encoder, x=x: e.encode(x), args.repeats)
            out = encoder.encode(x)
            cells = []
            for v in VARIANTS:
                kwargs = {"n_prototypes": args.n_prototypes} if v == "full" else {}
                variant = build_variant(v, **kwargs)
                t = _time(lambda m=variant, o=out: m(o.intermediates, o.language), args.repeats)
                cells.append(f"{t:.3f} ({t / t_encode:.2f})")
        params = sum(p.numel() for p in encoder.parameters()) / 1e6
        grid = "x".join(map(str, out.language.shape[-2:]))
        print(f"| {name} | {params:.1f}M | {grid} | {t_encode:.3f} | " + " | ".join(cells) + " |")


if __name__ == "__main__":
    main()
