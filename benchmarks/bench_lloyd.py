"""Lloyd on ReSiReg Full's points of the 25M architecture: iterations, distance rows, seconds.

The points k-means sees in the prototype/batch ablation: the 25M architecture (EUPE ViT-S/16,
random init, the 25M head) on 8 generated 576 x 768 images, Full's PCA to r = n components,
upsampled by s = 2 and normalised (55,296 points). For each prototype count, one k-means++
seeding, then Lloyd from it with each implementation, interleaved, fastest of ``--repeats``:

    python benchmarks/bench_lloyd.py
    python benchmarks/bench_lloyd.py --impl <folder with an older cluster.py>   # before/after

"distance rows" is ``KMeansResult.dist_rows / N``: rows of point-to-all-centroid distances
Lloyd computed, the first and the final assignment included (plain Lloyd: iterations + 1).
"same result" compares labels, centroids and the final distances with the installed version.
"""

from __future__ import annotations

import argparse
import time

import torch

from _common import build_model, encode_generated
from bench_reconstruct import load_impl
from resireg.reconstruct import ReSiRegFull


def full_points(n_values: list[int], images: int, short_side: int) -> dict[int, torch.Tensor]:
    """The normalised points Full clusters for each prototype count ``n`` (components = n)."""
    import resireg.reconstruct as reconstruct

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


def main(argv: list[str] | None = None) -> None:
    parser = argparse.ArgumentParser(
        description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter
    )
    parser.add_argument("--counts", type=int, nargs="+", default=[24, 72, 132])
    parser.add_argument("--images", type=int, default=8)
    parser.add_argument("--short-side", type=int, default=576)
    parser.add_argument("--repeats", type=int, default=3)
    parser.add_argument("--impl", default=None, help="folder of an older cluster.py to compare")
    args = parser.parse_args(argv)
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
            for name, cluster in impls.items():
                start = time.perf_counter()
                results[name] = cluster._lloyd(z, init.clone(), 100, tol, x_sq=x_sq)
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
