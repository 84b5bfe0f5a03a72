"""Cost of choosing ReSiReg Full's prototype count by the ELBO (``full.n_prototypes=elbo``)
against Full's clustering at the protocol's size.

Setting: ``bench_reconstruct.py``'s (8 images of a 36 x 48 grid, 384-d intermediates with
region structure, upscale 2 -> 55,296 points), the candidates of ``conf/resireg/default.yaml``
(``full.elbo_candidates``), PCA components tied to the count (``full.n_components: null``).
One run prints, as ratios to ``ReSiRegFull.assign`` at the chosen count (Full's clustering:
PCA, projection, upsampling, k-means), the fastest of ``--repeats`` interleaved calls of:

1. the choice alone (:meth:`ReSiRegFull._elbo_count`: the subsample's points on the largest
   candidate's axes, then :func:`resireg.method.elbo.elbo_prototype_count`: k-means and a
   variational mixture per candidate, in increasing order, on ``max_points`` points, until
   two candidates in a row fall below the best bound),
2. ``ReSiRegFull(n_prototypes="elbo").assign``: the choice and the clustering,

with ``--impl DIR`` the same two of the ``ReSiRegFull`` in ``DIR/full.py`` (or ``reconstruct.py``; bound to
the clustering of ``DIR``, see ``bench_reconstruct.load_impl``; e.g. an earlier version, for
before/after in one run), and the count
chosen. Then, per candidate, the full scan's VB iterations and bound (``elbo_fits``,
``stop_after=None``), and which candidates the chooser's scan fitted.

    python benchmarks/bench_elbo.py [--threads 2] [--repeats 3] [--impl DIR]
    git show c69510a:src/resireg/cluster.py > /tmp/before/cluster.py   # and reconstruct.py
    # (for a version after the split: its pca.py, kmeans.py and elbo.py instead of cluster.py)
"""

from __future__ import annotations

import argparse

import torch

from _common import resireg_defaults
from bench_reconstruct import interleaved_best, load_impl, make_features
from resireg.method.elbo import elbo_fits, elbo_subsample
from resireg.method.full import ReSiRegFull, upsampled_spectrum


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__,
                                     formatter_class=argparse.RawDescriptionHelpFormatter)  # fmt: skip
    parser.add_argument("--repeats", type=int, default=3)
    parser.add_argument("--threads", type=int, default=2)
    parser.add_argument("--device", default="cpu")
    parser.add_argument(
        "--impl", default=None, help="folder of another full.py or reconstruct.py + its clustering"
    )
    args = parser.parse_args()
    torch.set_num_threads(args.threads)
    candidates = resireg_defaults()["full"]["elbo_candidates"]
    inter, _ = make_features()
    inter = inter.to(args.device)
    elbo = ReSiRegFull(n_prototypes="elbo", elbo_candidates=candidates, n_components=None)
    spectrum = upsampled_spectrum(inter.float(), elbo.upscale)
    chosen = elbo._elbo_count(inter.float(), spectrum)
    fixed = ReSiRegFull(n_prototypes=chosen, n_components=None)
    print(f"points {inter.shape[0] * inter.shape[2] * inter.shape[3] * 4}, device {args.device}, "
          f"threads {args.threads}, candidates {candidates}: chosen {chosen}")  # fmt: skip

    def sync():
        if inter.device.type == "cuda":
            torch.cuda.synchronize()

    fns = {
        "full clustering (assign, chosen n)": lambda: (fixed.assign(inter), sync()),
        "elbo choice": lambda: (elbo._elbo_count(inter.float(), spectrum), sync()),
        "elbo assign (choice + clustering)": lambda: (elbo.assign(inter), sync()),
    }
    if args.impl is not None:
        other_cls = load_impl(args.impl)[1].ReSiRegFull
        other = other_cls(n_prototypes="elbo", elbo_candidates=candidates, n_components=None)
        print(f"--impl {args.impl}: chosen {other._elbo_count(inter.float(), spectrum)}")
        fns["--impl: elbo choice"] = lambda: (other._elbo_count(inter.float(), spectrum), sync())
        fns["--impl: elbo assign"] = lambda: (other.assign(inter), sync())
    best = interleaved_best(fns, args.repeats)
    base = best["full clustering (assign, chosen n)"]
    print("| path | seconds | ratio to Full's clustering |\n|---|---|---|")
    for name, seconds in best.items():
        print(f"| {name} | {seconds:.3f} | {seconds / base:.2f} |")
    # Per candidate: the full scan's VB iterations and bounds, on the chooser's subsample.
    n_points = inter.shape[0] * inter.shape[2] * inter.shape[3] * elbo.upscale**2
    rows = elbo_subsample(n_points, elbo.elbo_max_points, elbo.seed)
    points = elbo._elbo_points(inter.float(), spectrum, rows)
    options = {"seed": elbo.seed, "n_points": n_points, "max_points": elbo.elbo_max_points,
               "tol": elbo.elbo_tol}  # fmt: skip
    fits = elbo_fits(points, candidates, **options)
    scanned = elbo_fits(points, candidates, stop_after=elbo.elbo_stop_after, **options)
    print(
        "\n| k | fitted by the scan | VB iterations | ELBO per point | components holding >= 1 point |"
    )
    print("|---|---|---|---|---|")
    for k, fit in fits.items():
        held = int((fit.weights * n_points >= 1).sum())
        mark = "yes" if k in scanned else "no"
        print(f"| {k} | {mark} | {fit.n_iter} | {fit.elbo / n_points:.3f} | {held} |")


if __name__ == "__main__":
    main()
