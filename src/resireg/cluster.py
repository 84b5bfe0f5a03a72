"""Torch PCA and k-means for ReSiReg's prototype clustering.

Both run on whatever device their input lives on and are written with matrix
products and scatter ops only. They exist (rather than calling scikit-learn) because
the clustering sits inside a GPU forward pass: moving tens of thousands of points to
the host per batch would cost more than the clustering itself (see
``benchmarks/bench_reconstruct.py`` for the measured comparison).
"""

from __future__ import annotations

import math
from dataclasses import dataclass

import torch
from torch import Tensor

__all__ = [
    "PCAResult",
    "KMeansResult",
    "pca",
    "pca_from_moments",
    "kmeans",
    "kmeans_plusplus",
    "sq_distances",
]


@dataclass
class PCAResult:
    """A fitted PCA.

    Attributes:
        mean: ``[D]`` mean of the fitted points.
        components: ``[r, D]`` principal axes (rows, unit norm), by decreasing variance.
        explained_variance: ``[r]`` variance along each axis (unbiased, like scikit-learn).
    """

    mean: Tensor
    components: Tensor
    explained_variance: Tensor

    def transform(self, x: Tensor) -> Tensor:
        """Project ``[N, D]`` points onto the components -> ``[N, r]``."""
        return (x - self.mean) @ self.components.T


def pca(x: Tensor, n_components: int) -> PCAResult:
    """PCA of ``x`` ``[N, D]`` by eigendecomposition of the ``D x D`` covariance.

    The covariance route costs one ``N x D x D`` matrix product plus a ``D x D`` ``eigh``,
    which for ReSiReg's tall inputs (N in the tens of thousands, D a few hundred) is far
    cheaper than an SVD of the data. ``n_components`` is clipped to ``D`` (a full-rank PCA
    is a rotation, so clipping changes no distance). Axis signs follow scikit-learn's
    ``svd_flip`` convention (largest-magnitude loading positive) so results are stable.
    """
    if x.ndim != 2:
        raise ValueError(f"pca expects x of shape [N, D], got shape {tuple(x.shape)}")
    x = x.float()
    mean = x.mean(dim=0)
    xc = x - mean
    return pca_from_moments(
        xc.T @ xc, x.new_zeros(x.shape[1]), x.shape[0], n_components, shift=mean
    )


def pca_from_moments(
    second: Tensor, first: Tensor, n: int, n_components: int, shift: Tensor | None = None
) -> PCAResult:
    """PCA from the moments of ``n`` points ``y`` taken relative to a ``shift``.

    Args:
        second: ``[D, D]`` sum of ``(y - shift)(y - shift)^T``.
        first: ``[D]`` sum of ``(y - shift)``.
        n: number of points.
        n_components: components to keep (clipped to ``D``).
        shift: ``[D]`` offset the moments are relative to (default zero). Choosing it
            near the mean avoids cancellation in float32.

    Lets callers that know their points' structure (e.g. bilinear upsampling of a
    smaller grid, see :func:`resireg.reconstruct.upsampled_moments`) fit the exact PCA of
    points they never materialise.
    """
    d = second.shape[0]
    if n < 2:
        raise ValueError(f"pca needs at least 2 points, got N={n}")
    r = min(int(n_components), d)
    if r < 1:
        raise ValueError(f"n_components must be >= 1, got {n_components}")
    centre = first.double() / n
    cov = (second.double() - n * torch.outer(centre, centre)) / (n - 1)
    # eigh of a D x D matrix is cheap; float64 keeps small eigenvalues ordered correctly.
    evals, evecs = torch.linalg.eigh(cov)
    evals = evals.flip(0)[:r].clamp_min(0).float()
    comps = evecs.flip(1)[:, :r].T.float()  # [r, D]
    signs = torch.sign(comps.gather(1, comps.abs().argmax(dim=1, keepdim=True)))
    mean = centre.float() + (shift.float() if shift is not None else 0.0)
    return PCAResult(mean=mean, components=comps * signs, explained_variance=evals)


@dataclass
class KMeansResult:
    """A fitted k-means.

    Attributes:
        centroids: ``[k, D]``.
        labels: ``[N]`` index of the nearest centroid of every point.
        inertia: sum of squared distances of points to their centroid (scalar tensor).
        n_iter: Lloyd iterations run.
    """

    centroids: Tensor
    labels: Tensor
    inertia: Tensor
    n_iter: int


def sq_distances(x: Tensor, c: Tensor, x_sq: Tensor | None = None) -> Tensor:
    """Squared Euclidean distances ``[N, k]`` between ``x`` ``[N, D]`` and ``c`` ``[k, D]``.

    Uses the ``|x|^2 - 2 x.c + |c|^2`` expansion (one matrix product), clamped at zero;
    ``x_sq`` ``[N, 1]`` may pass precomputed ``|x|^2``.
    """
    x_sq = (x * x).sum(1, keepdim=True) if x_sq is None else x_sq
    return torch.addmm(x_sq, x, c.T, alpha=-2.0).add_((c * c).sum(1)).clamp_min_(0.0)


def _generator(device: torch.device, seed: int) -> torch.Generator:
    gen = torch.Generator(device=device)
    gen.manual_seed(int(seed))
    return gen


def kmeans_plusplus(
    x: Tensor, k: int, generator: torch.Generator, n_local_trials: int | None = None
) -> Tensor:
    """Greedy k-means++ seeding (Arthur & Vassilvitskii, 2007; greedy variant as in scikit-learn).

    Each new centre is the best of ``n_local_trials`` candidates drawn with probability
    proportional to the squared distance to the nearest chosen centre. The loop runs over
    the ``k`` seeding steps (inherently sequential); every step is vectorised over points.

    Returns:
        ``[k, D]`` initial centroids.
    """
    n, _ = x.shape
    if n_local_trials is None:
        n_local_trials = 2 + int(math.log(k))
    x_sq = (x * x).sum(1)
    x_t = x.T.contiguous()  # [D, N]: candidate distances as [t, N] rows reduce fastest
    first = torch.randint(n, (1,), generator=generator, device=x.device)
    centers = [x[first]]
    closest = sq_distances(x, centers[0]).squeeze(1)  # [N]
    for _ in range(1, k):
        # Inverse-CDF sampling proportional to the current potential (all points equally
        # likely once every point coincides with a centre).
        cdf = torch.cumsum(closest if bool(closest.sum() > 0) else torch.ones_like(closest), 0)
        draws = torch.rand(n_local_trials, generator=generator, device=x.device) * cdf[-1]
        cand = torch.searchsorted(cdf, draws).clamp_max_(n - 1)
        c = x[cand]
        cand_d = torch.addmm(x_sq.unsqueeze(0), c, x_t, alpha=-2.0).add_(
            (c * c).sum(1, keepdim=True)
        )
        cand_d = torch.minimum(closest.unsqueeze(0), cand_d.clamp_min_(0.0))  # [t, N]
        best = cand_d.sum(1).argmin()
        closest = cand_d[best]
        centers.append(c[best].unsqueeze(0))
    return torch.cat(centers, dim=0)


def kmeans(
    x: Tensor,
    n_clusters: int,
    *,
    seed: int = 0,
    max_iter: int = 100,
    tol: float = 1e-4,
    n_init: int = 1,
) -> KMeansResult:
    """Lloyd's k-means on ``x`` ``[N, D]`` with k-means++ seeding.

    Assignments use one matrix product per iteration; centroid updates use ``index_add_``
    and ``bincount`` (no Python loop over clusters). Empty clusters are re-seeded with the
    points farthest from their current centroid. Stops when the squared centroid shift
    falls below ``tol`` times the mean per-feature variance (scikit-learn's criterion) or
    after ``max_iter`` iterations. Deterministic for a fixed ``seed`` on a given device.
    The best of ``n_init`` runs (lowest inertia) is returned.
    """
    if x.ndim != 2:
        raise ValueError(f"kmeans expects x of shape [N, D], got shape {tuple(x.shape)}")
    n, d = x.shape
    if n_clusters < 1:
        raise ValueError(f"n_clusters must be >= 1, got {n_clusters}")
    if n_clusters > n:
        raise ValueError(f"n_clusters={n_clusters} exceeds the number of points N={n}")
    x = x.float()
    gen = _generator(x.device, seed)
    tol_abs = tol * x.var(dim=0).mean() if n > 1 else x.new_zeros(())
    best: KMeansResult | None = None
    for _ in range(max(1, n_init)):
        result = _lloyd(x, kmeans_plusplus(x, n_clusters, gen), max_iter, tol_abs)
        if best is None or result.inertia < best.inertia:
            best = result
    assert best is not None
    return best


def _lloyd(x: Tensor, centroids: Tensor, max_iter: int, tol_abs: Tensor) -> KMeansResult:
    k = centroids.shape[0]
    x_sq = (x * x).sum(1, keepdim=True)
    n_iter = 0
    for n_iter in range(1, max_iter + 1):  # noqa: B007 - n_iter is reported
        # |x|^2 is the same for every centre, so the argmin needs only -2 x.c + |c|^2.
        part, labels = torch.addmm((centroids * centroids).sum(1), x, centroids.T, alpha=-2.0).min(
            dim=1
        )
        min_d2 = part.add_(x_sq.squeeze(1))
        counts = torch.bincount(labels, minlength=k)
        sums = torch.zeros_like(centroids).index_add_(0, labels, x)
        new = sums / counts.clamp_min(1).unsqueeze(1).to(x.dtype)
        empty = counts == 0
        if bool(empty.any()):
            # Re-seed empty clusters with the points worst served by the current solution.
            new[empty] = x[min_d2.topk(int(empty.sum())).indices]
        shift = ((new - centroids) ** 2).sum()
        centroids = new
        if shift <= tol_abs:
            break
    min_d2, labels = sq_distances(x, centroids, x_sq).min(dim=1)
    return KMeansResult(centroids=centroids, labels=labels, inertia=min_d2.sum(), n_iter=n_iter)
