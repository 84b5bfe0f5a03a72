"""Speed of Calib against ReSiReg Lite and Full on one 36 x 36 grid of random features (CPU).

384-d intermediates, 512-d language tokens, default parameters of each variant (Lite and
Full upsample by 2, Calib stays on the grid). Times are best-of-``repeats`` and reported
as ratios to Calib, since absolute times on a shared machine drift.

    python benchmarks/bench_calib.py [--batch 1] [--repeats 3]
"""

from __future__ import annotations

import argparse
import time

import torch

from resireg.method.variants import build_variant


def best_of(fn, repeats: int) -> float:
    times = []
    for _ in range(repeats):
        t = time.perf_counter()
        fn()
        times.append(time.perf_counter() - t)
    return min(times)


def main() -> None:
    parser = argparse.ArgumentParser(
        description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter
    )
    parser.add_argument("--batch", type=int, default=1)
    parser.add_argument("--size", type=int, default=36)
    parser.add_argument("--repeats", type=int, default=3)
    args = parser.parse_args()
    g = torch.Generator().manual_seed(0)
    b, s = args.batch, args.size
    inter = torch.randn(b, 384, s, s, generator=g)
    lang = torch.randn(b, 512, s, s, generator=g)
    print(f"B={b}, grid {s} x {s}, Dv=384, Dl=512, threads {torch.get_num_threads()}")
    times = {}
    with torch.no_grad():
        for name in ("calib", "lite", "full"):
            variant = build_variant(name)
            variant(inter, lang)  # warm-up
            times[name] = best_of(lambda v=variant: v(inter, lang), args.repeats)
    print("| variant | seconds | x Calib |\n|---|---:|---:|")
    for name, t in times.items():
        print(f"| {name} | {t:.3f} | {t / times['calib']:.2f} |")


if __name__ == "__main__":
    main()
