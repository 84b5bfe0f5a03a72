"""Lloyd on ReSiReg Full's points of the 25M architecture: iterations, distance rows, seconds.

The points k-means sees in the prototype/batch ablation: the 25M architecture (EUPE ViT-S/16,
random init, the 25M head) on 8 generated 576 x 768 images, Full's PCA to r = n components,
upsampled by s = 2 and normalised (55,296 points). For each prototype count, one k-means++
seeding, then Lloyd from it with each implementation, interleaved, fastest of ``--repeats``:

    python benchmarks/bench_lloyd.py
    python benchmarks/bench_lloyd.py --impl <folder with an older kmeans.py or cluster.py>

"distance rows" is ``KMeansResult.dist_rows / N``: rows of point-to-all-centroid distances
Lloyd computed, the first and the final assignment included (plain Lloyd: iterations + 1).
"same result" compares labels, centroids and the final distances with the installed version.

``--configurations`` instead times what the prototype/batch ablation adds per batch: ReSiReg
Full's forward for each count of ``--counts`` (one shared spectrum per batch, as the
evaluation shares it), over the images cut into batches of each ``--batch-sizes``, each
implementation in turn within each of ``--repeats`` rounds (medians), and checks that the
implementations' outputs are equal:

    python benchmarks/bench_lloyd.py --configurations --impl <folder> \
        --counts 24 36 48 60 72 84 96 108 120 132 --batch-sizes 2 4 8
"""

from __future__ import annotations

import argparse
import statistics
import time

import torch

from _common import build_model, encode_generated
from bench_reconstruct import load_impl
from resireg.method.full import ReSiRegFull


def full_points(n_values: list[int], images: int, short_side: int) -> dict[int, torch.Tensor]:
    """The normalised points Full clusters for each prototype count ``n`` (components = n)."""
    import resireg.method.full as reconstruct

    torch.manual_seed(0)
    out = encode_generated(build_model(), images, short_side)
    points: dict[int, torch.Tensor] = {}
    original = reconstruct.kmeans

    def capture(z, n, **kwargs):  # the points assign() hands to k-means
        points[n] = z.clone()
        return original(z, n, **kwargs)

    reconstruct.kmeans = capture
    try:
        for n in n_values:
            ReSiRegFull(n_prototypes=n, n_components=None).assign(out.intermediates)
    finally:
        reconstruct.kmeans = original
    return points


def configurations(args: argparse.Namespace) -> None:
    """The ``--configurations`` table (module docstring)."""
    torch.manual_seed(0)
    out = encode_generated(build_model(), args.images, args.short_side)
    impls = {"installed": load_impl(None)[1]}
    if args.impl:
        impls = {"before": load_impl(args.impl)[1], "after": impls["installed"]}

    def run(reconstruct, batch: int) -> tuple[float, list[torch.Tensor]]:
        seconds, outputs = 0.0, []
        for start in range(0, args.images, batch):
            inter = out.intermediates[start : start + batch]
            lang = out.language[start : start + batch]
            shared = reconstruct.FullShared(inter, lang, 2)
            begin = time.perf_counter()
            for n in args.counts:
                outputs.append(reconstruct.ReSiRegFull(n_prototypes=n)(inter, lang, shared=shared))
            seconds += time.perf_counter() - begin
        return seconds, outputs

    print(f"{args.images} images at {args.short_side} px, {torch.get_num_threads()} threads, "
          f"counts {args.counts}; seconds of all configurations over all batches, median of "
          f"{args.repeats}")  # fmt: skip
    names = list(impls)
    print("| batch size | " + " | ".join(f"{name} s" for name in names)
          + (" | speed-up | same outputs |" if len(names) == 2 else " |"))  # fmt: skip
    print("|---:|" + "---:|" * len(names) + ("---:|---|" if len(names) == 2 else ""))
    for batch in args.batch_sizes:
        times: dict[str, list[float]] = {name: [] for name in names}
        outputs = {}
        for _ in range(args.repeats):
            for name, reconstruct in impls.items():
                seconds, outputs[name] = run(reconstruct, batch)
                times[name].append(seconds)
        med = {name: statistics.median(t) for name, t in times.items()}
        row = f"| {batch} | " + " | ".join(f"{med[name]:.2f}" for name in names)
        if len(names) == 2:
            same = all(torch.equal(a, b) for a, b in zip(*outputs.values(), strict=True))
            row += f" | {med[names[0]] / med[names[1]]:.2f}x | {'yes' if same else 'NO'}"
        print(row + " |")


def main(argv: list[str] | None = None) -> None:
    parser = argparse.ArgumentParser(
        description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter
    )
    parser.add_argument("--counts", type=int, nargs="+", default=[24, 72, 132])
    parser.add_argument("--images", type=int, default=8)
    parser.add_argument("--short-side", type=int, default=576)
    parser.add_argument("--repeats", type=int, default=3)
    parser.add_argument(
        "--impl", default=None, help="folder of an older kmeans.py (or cluster.py) to compare"
    )
    parser.add_argument(
        "--configurations", action="store_true",
        help="time Full's forward for every count per batch (the ablation's added work)",
    )  # fmt: skip
    parser.add_argument("--batch-sizes", type=int, nargs="+", default=[2, 4, 8])
    args = parser.parse_args(argv)
    if args.configurations:
        configurations(args)
        return
    impls = {"installed": load_impl(None)[0]}
    if args.impl:
        impls = {"before": load_impl(args.impl)[0], "after": impls["installed"]}
    points = full_points(args.counts, args.images, args.short_side)
    print(f"{args.images} images at {args.short_side} px, {torch.get_num_threads()} threads")
    print("| n | implementation | Lloyd iterations | distance rows / N | seconds | same result |")
    print("|---:|---|---:|---:|---:|---|")
    for n in args.counts:
        z = points[n].float().contiguous()
        x_sq = (z * z).sum(1)
        reference = impls["installed"] if "installed" in impls else impls["after"]
        init = reference.kmeans_plusplus(z, n, torch.Generator().manual_seed(0))
        tol = reference._tolerance(z, 1e-4)
        best = {name: float("inf") for name in impls}
        results = {}
        for _ in range(args.repeats):
            for name, impl in impls.items():
                start = time.perf_counter()
                results[name] = impl._lloyd(z, init.clone(), 100, tol, x_sq=x_sq)
                best[name] = min(best[name], time.perf_counter() - start)
        ours = results["installed" if "installed" in results else "after"]
        for name, r in results.items():
            same = (
                torch.equal(r.labels, ours.labels)
                and torch.equal(r.centroids, ours.centroids)
                and torch.equal(r.sq_dists, ours.sq_dists)
            )
            print(f"| {n} | {name} | {r.n_iter} | {r.dist_rows / len(z):.2f} | "
                  f"{best[name]:.3f} | {'yes' if same else 'NO'} |")  # fmt: skip


if __name__ == "__main__":
    main()
