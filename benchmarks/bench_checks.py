"""The cost of the variants' input check against ReSiReg Full's and Lite's forward.

``ReSiRegFull``, ``ReSiRegLite`` and ``Calib`` refuse non-finite, non-floating and empty
inputs before computing (``resireg.method.checks.check_variant_inputs``, whose finiteness rule is
``resireg.method.checks.check_features``): the shape tests are free, the finiteness test reads every
value of ``intermediates`` and ``language`` once (one fused ``isfinite(...).all()`` each).
This measures that check as a share of each variant's forward (which includes it), on the
25M architecture's features (EUPE ViT-S/16 + the 25M head, random weights: ``Dv = 384``,
``Dl = 512``) of one batch of ``--batch`` generated 576 x 768 images (a 36 x 48 grid), with
the defaults of ``conf/resireg/default.yaml``. The variants and the check are timed in
alternating rounds (one call of each per round, after a warm-up), medians reported; the check
is timed ``--inner`` times per round (it is short) and divided.

    python benchmarks/bench_checks.py                    # batch 4 at 576 px, 5 rounds
    python benchmarks/bench_checks.py --batch 2 --short-side 288 --rounds 2   # quick
"""

from __future__ import annotations

import argparse
import statistics
import time

import torch

from _common import build_model, encode_generated, resireg_defaults
from resireg.method.checks import check_variant_inputs
from resireg.method.full import ReSiRegFull
from resireg.method.lite import ReSiRegLite


def main(argv: list[str] | None = None) -> None:
    parser = argparse.ArgumentParser(
        description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter
    )
    parser.add_argument("--batch", type=int, default=4)
    parser.add_argument("--short-side", type=int, default=576)
    parser.add_argument("--rounds", type=int, default=5)
    parser.add_argument("--inner", type=int, default=20, help="check calls per round")
    parser.add_argument("--threads", type=int, default=None, help="torch threads")
    args = parser.parse_args(argv)
    if args.threads:
        torch.set_num_threads(args.threads)
    torch.manual_seed(0)
    out = encode_generated(build_model(), args.batch, args.short_side)
    inter, lang = out.intermediates, out.language
    conf = resireg_defaults()
    full = ReSiRegFull(**{k: v for k, v in conf["full"].items() if v is not None})
    lite = ReSiRegLite(**conf["lite"])

    def check() -> None:
        for _ in range(args.inner):
            check_variant_inputs(inter, lang, None)

    fns = {"full": lambda: full(inter, lang), "lite": lambda: lite(inter, lang), "check": check}
    for fn in fns.values():  # warm-up
        fn()
    times: dict[str, list[float]] = {name: [] for name in fns}
    for _ in range(args.rounds):
        for name, fn in fns.items():
            start = time.perf_counter()
            fn()
            times[name].append(time.perf_counter() - start)
    times["check"] = [t / args.inner for t in times["check"]]
    med = {name: statistics.median(t) for name, t in times.items()}
    print(
        f"batch {args.batch}: intermediates {tuple(inter.shape)}, language {tuple(lang.shape)}, "
        f"{torch.get_num_threads()} threads, {args.rounds} rounds (medians)"
    )
    print("| call | median s | check / call (median) | per round |")
    print("|---|---:|---:|---|")
    print(f"| check (`check_variant_inputs`) | {med['check']:.6f} | | |")
    for name in ("full", "lite"):
        per_round = ", ".join(
            f"{c / t:.2e}" for c, t in zip(times["check"], times[name], strict=True)
        )
        print(
            f"| {name} forward | {med[name]:.3f} | {med['check'] / med[name]:.2e} | {per_round} |"
        )


if __name__ == "__main__":
    main()
