"""Speed of ReSiReg's clustering (torch PCA + k-means) against scikit-learn, and of Full/Lite.

Setting of the issue: 8 images of a 36 x 48 patch grid, 384-d intermediates, 512-d
language tokens, upscale 2 -> 55,296 points, 36 components, 36 prototypes. The
intermediates carry region structure (a smooth random field of region codes plus
noise) so k-means sees clusters as it does on real ViT features. All timings of one run
are reported as ratios because absolute times on a shared 2-core machine drift.

    python benchmarks/bench_reconstruct.py [--repeats 3]
"""

from __future__ import annotations

import argparse
import time

import numpy as np
import torch
import torch.nn.functional as F
from sklearn.cluster import KMeans
from sklearn.decomposition import PCA

from resireg import ReSiRegFull, ReSiRegLite
from resireg.cluster import kmeans, pca


def make_features(b=8, h=36, w=48, dv=384, dl=512, regions=48, seed=0):
    g = torch.Generator().manual_seed(seed)
    logits = F.interpolate(
        torch.randn(b, regions, h // 6, w // 6, generator=g), size=(h, w), mode="bicubic"
    )
    labels = logits.argmax(1)
    codes = torch.randn(regions, dv, generator=g)
    inter = codes[labels].permute(0, 3, 1, 2) + 0.5 * torch.randn(b, dv, h, w, generator=g)
    lang = torch.randn(b, dl, h, w, generator=g)
    return inter, lang


def best_of(fn, repeats):
    times, out = [], None
    for _ in range(repeats):
        t = time.perf_counter()
        out = fn()
        times.append(time.perf_counter() - t)
    return min(times), out


def main() -> None:
    parser = argparse.ArgumentParser(
        description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter
    )
    parser.add_argument("--repeats", type=int, default=3)
    parser.add_argument("--components", type=int, default=36)
    parser.add_argument("--prototypes", type=int, default=36)
    parser.add_argument(
        "--seeds", type=int, default=20, help="k-means seeds for the inertia comparison"
    )
    args = parser.parse_args()
    torch.manual_seed(0)
    inter, lang = make_features()
    points = F.interpolate(inter, scale_factor=2, mode="bilinear", align_corners=False)
    points = points.permute(0, 2, 3, 1).reshape(-1, inter.shape[1]).contiguous()
    r, n = args.components, args.prototypes
    print(
        f"points: {points.shape[0]} x {points.shape[1]}, components {r}, prototypes {n}, threads {torch.get_num_threads()}"
    )

    full = ReSiRegFull(n_prototypes=n, n_components=r)

    def resireg_path():  # what ReSiReg Full runs: from the low-res grid, upsampling included
        return full.assign(inter)

    def torch_generic():  # the same algorithms on the materialised points
        z = F.normalize(pca(points, r).transform(points), dim=1)
        return kmeans(z, n, seed=0).inertia.item()

    x_np = points.numpy()

    def sklearn_fit(seed):
        z = PCA(n_components=r, random_state=0).fit_transform(x_np)
        z = z / np.linalg.norm(z, axis=1, keepdims=True)
        return KMeans(n_clusters=n, n_init=1, random_state=seed).fit(z).inertia_

    t_resireg, _ = best_of(resireg_path, args.repeats)
    t_generic, _ = best_of(torch_generic, args.repeats)
    t_sk, _ = best_of(lambda: sklearn_fit(0), args.repeats)
    # Inertia over several seeds (single runs land in different local minima).
    seeds = range(args.seeds)
    inertias_torch = []
    for seed in seeds:
        dist, _ = ReSiRegFull(n_prototypes=n, n_components=r, seed=seed).assign(inter)
        inertias_torch.append(float((dist.min(dim=1).values ** 2).sum()))
    inertias_sk = [sklearn_fit(seed) for seed in seeds]
    t_full, _ = best_of(lambda: full(inter, lang), args.repeats)
    t_lite, _ = best_of(lambda: ReSiRegLite()(inter, lang), args.repeats)

    print(f"sklearn PCA+KMeans(n_init=1) on the points     {t_sk:8.3f} s")
    print(
        f"torch PCA+k-means on the points                {t_generic:8.3f} s   {t_sk / t_generic:5.1f}x faster than sklearn"
    )
    print(
        f"ReSiReg Full clustering (upsampling included)  {t_resireg:8.3f} s   {t_sk / t_resireg:5.1f}x faster than sklearn"
    )
    ratio = np.mean(inertias_torch) / np.mean(inertias_sk)
    print(
        f"k-means inertia, mean of {args.seeds} seeds: torch {np.mean(inertias_torch):.1f}, sklearn {np.mean(inertias_sk):.1f} (ratio {ratio:.4f})"
    )
    print(
        f"ReSiReg Full forward                           {t_full:8.3f} s   ({t_full / t_resireg:.2f}x its clustering)"
    )
    print(
        f"ReSiReg Lite forward                           {t_lite:8.3f} s   ({t_lite / t_full:.2f}x Full)"
    )


if __name__ == "__main__":
    main()
