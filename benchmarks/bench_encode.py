"""Throughput of ``ResiregVLM.encode_image`` with no ReSiReg, Lite and Full.

Random-init EUPE ViT-S/16 + the 3.7M language head (the real architecture; weights do not
change the cost), images of 448 px short side (448 x 592, a 28 x 37 patch grid), batch
sizes 1, 2, 4, 8. Throughputs are reported as ratios to the backbone-only figure of the
same batch size, measured in the same run.

    python benchmarks/bench_encode.py [--repeats 2] [--batch-sizes 1 2 4 8]
"""

from __future__ import annotations

import argparse
import time

import torch

from _common import TINY_TEXT
from resireg import ReSiRegFull, ReSiRegLite
from resireg.models import ResiregVLM


def images_per_second(fn, batch: int, repeats: int) -> float:
    fn()  # warm-up
    best = float("inf")
    for _ in range(repeats):
        t = time.perf_counter()
        fn()
        best = min(best, time.perf_counter() - t)
    return batch / best


def main() -> None:
    parser = argparse.ArgumentParser(
        description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter
    )
    parser.add_argument("--repeats", type=int, default=2)
    parser.add_argument("--batch-sizes", type=int, nargs="+", default=[1, 2, 4, 8])
    parser.add_argument("--height", type=int, default=448)
    parser.add_argument("--width", type=int, default=592)
    args = parser.parse_args()
    torch.manual_seed(0)
    model = ResiregVLM.build({"model_name": "eupe_vit_s16", "weights": None}, {}, TINY_TEXT).eval()
    lite, full = ReSiRegLite(), ReSiRegFull()
    print(f"threads {torch.get_num_threads()}, image {args.height}x{args.width}")
    print(
        "batch | backbone img/s | +head | +head+Lite | +head+Full | Lite over head | Full over head"
    )
    for b in args.batch_sizes:
        x = torch.randn(b, 3, args.height, args.width)
        with torch.no_grad():
            ips_bb = images_per_second(lambda x=x: model.backbone(x), b, args.repeats)
            ips_head = images_per_second(
                lambda x=x: model.encode_image(x, normalized=True), b, args.repeats
            )
            ips_lite = images_per_second(
                lambda x=x: model.encode_image(x, lite, normalized=True), b, args.repeats
            )
            ips_full = images_per_second(
                lambda x=x: model.encode_image(x, full, normalized=True), b, args.repeats
            )
        print(
            f"{b:5d} | {ips_bb:14.2f} | {ips_head / ips_bb:5.2f}x | {ips_lite / ips_bb:10.2f}x | {ips_full / ips_bb:10.2f}x"
            f" | {ips_head / ips_lite - 1:+14.0%} | {ips_head / ips_full - 1:+14.0%}"
        )


if __name__ == "__main__":
    main()
