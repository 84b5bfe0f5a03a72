"""Torch PCA and k-means for ReSiReg's prototype clustering.

Both run on whatever device their input lives on and are written with matrix
products and scatter ops only. They exist (rather than calling scikit-learn) because
the clustering sits inside a GPU forward pass: moving tens of thousands of points to
the host per batch would cost more than the clustering itself (see
``benchmarks/bench_reconstruct.py`` for the measured comparison).

:func:`kmeans` is scikit-learn's ``KMeans(init="k-means++", n_init=1)``: greedy k-means++
seeding, then Lloyd iterations stopped by scikit-learn's tolerance rule, with distance
bounds (Hamerly's upper bound, Yinyang's grouped lower bounds, both widened by a rigorous
float rounding bound) so that an iteration computes distances only for the points whose
nearest centroid might have changed (same labels, centroids and iteration count as plain
Lloyd).
:func:`gram` forms the symmetric product ``Y^T Y`` of the PCA at 2/3 of a matrix product.
:func:`elbo_prototype_count` chooses a prototype count by the evidence lower bound of a
variational Bayesian Gaussian mixture (:func:`vb_gmm`, scikit-learn's
``BayesianGaussianMixture`` with diagonal covariances, docs/design.md section 4.4b).
"""

from __future__ import annotations

import math
from collections.abc import Callable, Iterator, Sequence
from dataclasses import dataclass
from typing import Any

import torch
import torch.nn.functional as F
from torch import Tensor

__all__ = [
    "PCAResult",
    "PCASpectrum",
    "KMeansResult",
    "pca",
    "pca_from_moments",
    "kmeans",
    "kmeans_plusplus",
    "sq_distances",
    "gram",
    "VBGMMResult",
    "vb_gmm",
    "elbo_subsample",
    "elbo_fits",
    "elbo_prototype_count",
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

    The covariance route costs one ``N x D x D`` product (:func:`gram`, which forms only its
    upper block triangle) plus a ``D x D`` ``eigh``, which for ReSiReg's tall inputs (N in
    the tens of thousands, D a few hundred) is far cheaper than an SVD of the data. ``n_components`` is clipped to ``D`` (a full-rank PCA
    is a rotation, so clipping changes no distance). Axis signs follow scikit-learn's
    ``svd_flip`` convention (largest-magnitude loading positive) so results are stable.
    """
    if x.ndim != 2:
        raise ValueError(f"pca expects x of shape [N, D], got shape {tuple(x.shape)}")
    x = x.float()
    mean = x.mean(dim=0)
    xc = x - mean
    return pca_from_moments(gram(xc), x.new_zeros(x.shape[1]), x.shape[0], n_components, shift=mean)


@dataclass
class PCASpectrum:
    """The eigendecomposition of a covariance, from which a PCA of any size is sliced.

    ReSiReg Full's configurations of one batch differ in their component count only, so the
    evaluation decomposes once and takes :meth:`top` per configuration; a PCA sliced from
    the shared spectrum equals one decomposed alone (same ``eigh`` input, same slice).

    Attributes:
        centre: ``[D]`` float64 mean of the points relative to ``shift``.
        shift: ``[D]`` offset of the moments (``None``: zero).
        evals: ``[D]`` float64 eigenvalues, decreasing.
        evecs: ``[D, D]`` float64 eigenvectors (columns), in the order of ``evals``.
    """

    centre: Tensor
    shift: Tensor | None
    evals: Tensor
    evecs: Tensor

    @classmethod
    def from_moments(
        cls, second: Tensor, first: Tensor, n: int, shift: Tensor | None = None
    ) -> PCASpectrum:
        """Arguments as :func:`pca_from_moments` (without the component count)."""
        if n < 2:
            raise ValueError(f"pca needs at least 2 points, got N={n}")
        centre = first.double() / n
        cov = (second.double() - n * torch.outer(centre, centre)) / (n - 1)
        # eigh of a D x D matrix is cheap; float64 keeps small eigenvalues ordered correctly.
        evals, evecs = torch.linalg.eigh(cov)
        return cls(centre=centre, shift=shift, evals=evals.flip(0), evecs=evecs.flip(1))

    def top(self, n_components: int) -> PCAResult:
        """The PCA keeping ``n_components`` (clipped to ``D``) axes, signs as scikit-learn's
        ``svd_flip`` (largest-magnitude loading positive)."""
        r = min(int(n_components), self.evecs.shape[0])
        if r < 1:
            raise ValueError(f"n_components must be >= 1, got {n_components}")
        comps = self.evecs[:, :r].T.float()  # [r, D]
        signs = torch.sign(comps.gather(1, comps.abs().argmax(dim=1, keepdim=True)))
        return PCAResult(
            mean=self.centre.float() + (self.shift.float() if self.shift is not None else 0.0),
            components=comps * signs,
            explained_variance=self.evals[:r].clamp_min(0).float(),
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
    if int(n_components) < 1:
        raise ValueError(f"n_components must be >= 1, got {n_components}")
    return PCASpectrum.from_moments(second, first, n, shift).top(n_components)


@dataclass
class KMeansResult:
    """A fitted k-means.

    Attributes:
        centroids: ``[k, D]``.
        labels: ``[N]`` index of the nearest centroid of every point.
        inertia: sum of squared distances of points to their centroid (scalar tensor).
        n_iter: Lloyd iterations run.
        sq_dists: ``[N, k]`` squared Euclidean distances of every point to every final
            centroid (the matrix the final assignment was taken from, so callers that need
            the distances do not recompute them); ``None`` only when built by hand.
        dist_rows: point-to-all-centroids distance rows Lloyd computed (``N`` per full
            assignment; the distance bounds skip most rows after the first iterations).
            Each row costs ``2 k D`` FLOPs of matrix product.
    """

    centroids: Tensor
    labels: Tensor
    inertia: Tensor
    n_iter: int
    sq_dists: Tensor | None = None
    dist_rows: int = 0


def sq_distances(x: Tensor, c: Tensor, x_sq: Tensor | None = None) -> Tensor:
    """Squared Euclidean distances ``[N, k]`` between ``x`` ``[N, D]`` and ``c`` ``[k, D]``.

    Uses the ``|x|^2 - 2 x.c + |c|^2`` expansion (one matrix product), clamped at zero;
    ``x_sq`` ``[N, 1]`` may pass precomputed ``|x|^2``.
    """
    x_sq = (x * x).sum(1, keepdim=True) if x_sq is None else x_sq
    return torch.addmm(x_sq, x, c.T, alpha=-2.0).add_((c * c).sum(1)).clamp_min_(0.0)


def gram(y: Tensor, blocks: int = 4, out: Tensor | None = None) -> Tensor:
    """``y^T y`` ``[D, D]`` of ``y`` ``[P, D]``, computing only its upper block triangle.

    The product is symmetric, so with the columns cut into ``blocks`` slabs, slab ``i`` is
    multiplied by the columns from its own start on (one product per slab) and the part
    right of its diagonal block mirrored: ``(1 + 1 / blocks) / 2`` of the full product's
    multiply-adds (5/8 for 4 slabs), the BLAS ``syrk`` that torch does not expose. Narrow
    inputs (``D < 32 * blocks``) take one plain product. With ``out`` (a symmetric
    ``[D, D]``, e.g. zeros or an earlier result), ``y^T y`` is added to it in place, so row
    chunks of a tall ``y`` can be accumulated without ever forming ``y`` whole.
    """
    d = y.shape[1]
    if out is None:
        out = y.new_zeros(d, d)
    # addmm(..., out=) rather than addmm_: the same kernel, but FlopCounterMode counts it.
    if blocks <= 1 or d < 32 * blocks:
        return torch.addmm(out, y.T, y, out=out)
    edges = [d * i // blocks for i in range(blocks + 1)]
    for start, stop in zip(edges[:-1], edges[1:], strict=True):
        slab = out[start:stop, start:]
        torch.addmm(slab, y[:, start:stop].T, y[:, start:], out=slab)
        if stop < d:
            out[stop:, start:stop] = out[start:stop, stop:].T
    return out


def _generator(device: torch.device, seed: int) -> torch.Generator:
    gen = torch.Generator(device=device)
    gen.manual_seed(int(seed))
    return gen


def _tolerance(x: Tensor, tol: float) -> float:
    """scikit-learn's absolute k-means tolerance: ``tol`` times the mean per-feature variance.

    ``np.mean(np.var(x, axis=0)) * tol`` (population variance, ``ddof=0``), exactly as
    ``sklearn.cluster._kmeans._tolerance``; 0 when ``tol`` is 0. Computed as the mean of the
    squared deviations from the column means (one pass, no cancellation).
    """
    if tol == 0:
        return 0.0
    x = x.float()
    return float(tol * (x - x.mean(dim=0)).square_().mean())


def kmeans_plusplus(
    x: Tensor, k: int, generator: torch.Generator, n_local_trials: int | None = None
) -> Tensor:
    """Greedy k-means++ seeding (Arthur & Vassilvitskii, 2007; greedy variant as in scikit-learn).

    The first centre is a uniformly drawn point. Each further centre is the best (lowest
    resulting potential) of ``n_local_trials`` (default ``2 + floor(ln k)``) candidates drawn
    with probability proportional to the squared distance to the nearest chosen centre, by
    inverse-CDF sampling (``cumsum`` + ``searchsorted``). The loop runs over the ``k``
    seeding steps (inherently sequential); every step is one ``[t, D] x [D, N]`` matrix
    product plus a few vectorised passes over ``[t, N]``.

    Returns:
        ``[k, D]`` initial centroids.
    """
    return _kmeans_plusplus(x, x.T.contiguous(), (x * x).sum(1), k, generator, n_local_trials)


def _kmeans_plusplus(
    x: Tensor,
    x_t: Tensor | None,
    x_sq: Tensor,
    k: int,
    generator: torch.Generator,
    n_local_trials: int | None,
    dots: Callable[[Tensor], Tensor] | None = None,
) -> Tensor:
    """:func:`kmeans_plusplus` with ``x_t = x.T.contiguous()`` and ``x_sq = |x|^2`` given;
    with ``dots`` (see :func:`kmeans`), candidate products come from it and ``x_t`` is unused."""
    if n_local_trials is None:
        n_local_trials = 2 + int(math.log(k))
    steps = _plusplus_steps(x, x_t, x_sq, generator, n_local_trials, dots)
    centers = x.new_empty(k, x.shape[1])
    for i in range(k):
        centers[i] = next(steps)
    return centers


def _plusplus_steps(
    x: Tensor,
    x_t: Tensor | None,
    x_sq: Tensor,
    generator: torch.Generator,
    n_local_trials: int,
    dots: Callable[[Tensor], Tensor] | None = None,
) -> Iterator[Tensor]:
    """The greedy k-means++ centres one at a time (``[D]`` each, without end): the first
    ``k`` are :func:`_kmeans_plusplus`' ``k`` centres for the same ``n_local_trials``, since
    each step depends only on the centres before it. Lazy, so a caller that needs seedings
    of several sizes (:func:`elbo_fits`) runs the steps of the largest once."""
    n = x.shape[0]
    row_sq = x_sq.unsqueeze(0)  # [1, N]; candidate distances are [t, N] rows (fast reductions)

    def sq_dists(c: Tensor) -> Tensor:  # [t, N] = |x|^2 - 2 c.x + |c|^2, not clamped
        c_sq = (c * c).sum(1, keepdim=True)
        if dots is None:
            return torch.addmm(row_sq, c, x_t, alpha=-2.0).add_(c_sq)
        return torch.add(row_sq, dots(c), alpha=-2.0).add_(c_sq)

    zero = x.new_zeros(())
    first = torch.randint(n, (1,), generator=generator, device=x.device)
    yield x[first[0]]
    closest = sq_dists(x[first]).clamp_min_(0.0).squeeze(0)  # [N] to the nearest centre
    while True:
        # Inverse-CDF sampling proportional to the current potential (all points equally
        # likely once every point coincides with a centre).
        cdf = torch.cumsum(closest, 0)
        if not bool(cdf[-1] > 0):
            cdf = torch.cumsum(torch.ones_like(closest), 0)
        draws = torch.rand(n_local_trials, generator=generator, device=x.device) * cdf[-1]
        cand = torch.searchsorted(cdf, draws).clamp_max_(n - 1)
        c = x[cand]
        dist = sq_dists(c)
        # min(closest, max(dist, 0)) in one pass: each candidate's new nearest distances.
        dist.clamp_(min=zero, max=closest)
        best = int(dist.sum(1).argmin())
        closest = dist[best]
        yield c[best]


def kmeans(
    x: Tensor,
    n_clusters: int,
    *,
    seed: int = 0,
    max_iter: int = 100,
    tol: float = 1e-4,
    n_init: int = 1,
    dots: Callable[[Tensor], Tensor] | None = None,
) -> KMeansResult:
    """Lloyd's k-means on ``x`` ``[N, D]`` with greedy k-means++ seeding.

    Each iteration assigns every point to its nearest centroid and moves every centroid to
    the mean of its points (``index_add_`` / ``bincount``, no Python loop over clusters);
    empty clusters are re-seeded with the points farthest from their current centroid.
    Stops, as scikit-learn's ``KMeans`` does, once the squared Frobenius norm of the
    centroid shift between two iterations is ``<= tol`` times the mean per-feature variance
    of ``x`` (:func:`_tolerance`; this also covers strict convergence, where the labels and
    hence the centroids stop changing), or after ``max_iter`` iterations. A final assignment
    to the last centroids gives the labels, the inertia and :attr:`KMeansResult.sq_dists`.

    The assignments are exact but skip points whose nearest centroid provably did not
    change (Hamerly's bounds, see :func:`_lloyd`), so later iterations touch only the few
    points near a cluster boundary. Deterministic for a fixed ``seed`` on a given device.
    The best of ``n_init`` runs (lowest inertia) is returned.

    ``dots``, optional: ``c -> c @ x.T`` (``[t, D] -> [t, N]``, equal up to rounding) for
    points whose structure makes these products cheaper than a matrix product with ``x``
    (ReSiReg Full's points are normalised bilinear upsamplings of a grid ``s^2`` times
    smaller, so the products are taken on the grid and upsampled). The k-means++ seeding,
    ``k (2 + ln k)`` such products over all points, then uses it.
    """
    if x.ndim != 2:
        raise ValueError(f"kmeans expects x of shape [N, D], got shape {tuple(x.shape)}")
    n, _ = x.shape
    if n_clusters < 1:
        raise ValueError(f"n_clusters must be >= 1, got {n_clusters}")
    if n_clusters > n:
        raise ValueError(f"n_clusters={n_clusters} exceeds the number of points N={n}")
    x = x.float().contiguous()
    gen = _generator(x.device, seed)
    # Computed once, shared by the seeding and every Lloyd iteration of every run.
    x_sq = (x * x).sum(1)
    x_t = x.T.contiguous() if dots is None else None
    tol_abs = _tolerance(x, tol)
    best: KMeansResult | None = None
    for _ in range(max(1, n_init)):
        init = _kmeans_plusplus(x, x_t, x_sq, n_clusters, gen, None, dots=dots)
        result = _lloyd(x, init, max_iter, tol_abs, x_sq=x_sq)
        if best is None or result.inertia < best.inertia:
            best = result
    assert best is not None
    return best


def _sq_error(x_sq: Tensor, c_sq_max: float, d: int) -> Tensor:
    """Per point ``[N]``, a bound on the rounding error of its squared distances computed by
    the ``|x|^2 - 2 x.c + |c|^2`` expansion in ``x``'s dtype.

    A dot product of length ``d`` errs by at most ``gamma_d |x| |c|`` (``gamma_d ~ d eps``),
    each squared norm by ``gamma_d`` times itself, and the three additions by ``eps`` each,
    so the sum errs by at most ``2 (d + 3) eps (|x|^2 + |c|^2)``.
    """
    return x_sq.add(c_sq_max).mul_(2.0 * (d + 3) * torch.finfo(x_sq.dtype).eps)


# Centroids per group of the grouped lower bounds (see _lloyd). On ReSiReg Full's points
# (55,296 x 132, k = 132, 33 iterations), distance rows per point besides the final assignment:
# groups of 4: 9.3, one group (Hamerly): 20.5, single centroids (Elkan): 6.8 but with 33x the
# bookkeeping of groups of 4, which were the fastest. With near centroids grouped
# (_proximity_order; the 25M model's points at k = 132, 42 iterations, all rows counted): groups
# of 2: 8.1 rows, 4: 9.0, 8: 11.1, and 4 the fastest (0.71 s against 0.89 and 0.81).
_GROUP = 4


def _group_max(values: Tensor, groups: int) -> Tensor:
    """``[k] -> [groups]``: the maximum over each run of ``_GROUP`` consecutive entries of the
    non-negative ``values`` (padding with 0)."""
    return F.pad(values, (0, groups * _GROUP - values.shape[0])).view(groups, _GROUP).amax(1)


def _first_min(values: Tensor, minimum: Tensor) -> Tensor:
    """``[m, M] -> [M]``: per column, the first row where ``values`` equals the column's
    ``minimum`` (``values.min(dim=0).indices`` for the column minima, ties to the lowest
    row). Written as a compare and a maximum over rows because torch's CPU ``min`` with
    indices is ~15x slower than ``amin`` over the same rows (measured on [36, 8000])."""
    rows = values.shape[0]
    desc = torch.arange(rows, 0, -1, dtype=values.dtype, device=values.device).unsqueeze(1)
    return (rows - torch.where(values == minimum, desc, 0.0).amax(dim=0)).long()


def _assign_rows(
    x: Tensor, x_sq: Tensor, c: Tensor, c_sq: Tensor, err: Tensor, groups: int
) -> tuple[Tensor, Tensor, Tensor]:
    """For the rows ``x`` ``[M, D]``: nearest centroid ``[M]`` (the lowest index among ties),
    an upper bound on the exact distance to it ``[M]``, and per group of ``_GROUP``
    consecutive centroids a lower bound on the exact distance to the group's centroids other
    than the nearest, group-major ``[groups, M]`` (``inf`` for none), from the computed
    squared distances and their error ``err`` ``[M]`` (:func:`_sq_error`), so that the
    bounds hold for the exact distances.

    The distances are computed centroid-major, ``[k, M]``, so every reduction runs over the
    leading axis of contiguous rows (torch's CPU reductions over short inner rows, e.g. the
    groups of 4, are ~7x slower): the group minima first, the nearest distance from them,
    then the nearest centroid found within its group only.
    """
    m = x.shape[0]
    # |c|^2 - 2 c.x, centroid-major; |x|^2 is added per point below. The rows past k
    # (padding of the last group) stay inf.
    part = torch.empty(groups * _GROUP, m, dtype=x.dtype, device=x.device)
    part[c.shape[0] :] = float("inf")
    torch.addmm(c_sq.unsqueeze(1), c, x.T, alpha=-2.0, out=part[: c.shape[0]])
    cube = part.view(groups, _GROUP, m)
    lower = cube.amin(dim=1)  # [G, M] group minima
    nearest = lower.amin(dim=0)  # [M]
    group = _first_min(lower, nearest)  # [M] the first group holding the minimum
    cols = torch.arange(m, device=x.device)
    # The nearest group's _GROUP distances [_GROUP, M], the nearest among them, and the
    # group's bound recomputed without it.
    own = part.view(-1).take(
        group.mul(_GROUP * m).add_(cols) + (torch.arange(_GROUP, device=x.device) * m).unsqueeze(1)
    )
    within = _first_min(own, nearest)
    labels = group * _GROUP + within
    own.view(-1).index_fill_(0, within * m + cols, float("inf"))
    lower.view(-1).index_copy_(0, group * m + cols, own.amin(dim=0))
    eps = torch.finfo(x.dtype).eps
    # +-4 eps (relative) covers the rounding of the additions and of sqrt itself.
    upper = nearest.add_(x_sq).add_(err).clamp_min_(0.0).sqrt_().mul_(1.0 + 4.0 * eps)
    lower = lower.add_(x_sq - err).clamp_min_(0.0).sqrt_().mul_(1.0 - 4.0 * eps)
    return labels, upper, lower


def _separation(c: Tensor) -> Tensor:
    """A lower bound on the distance of every centroid to its nearest other centroid ``[k]``
    (``inf`` for ``k = 1``). By the triangle inequality a point at distance at most ``u``
    from its centroid ``a`` is at least ``separation[a] - u`` from every other. Computed in
    float64, less that computation's own rounding bound."""
    c64 = c.double()
    c_sq = (c64 * c64).sum(1)
    err = (c_sq.unsqueeze(1) + c_sq.unsqueeze(0)) * (2.0 * (c.shape[1] + 3) * 2.0**-52)
    dist_sq = c_sq.unsqueeze(1) + c_sq.unsqueeze(0) - 2.0 * c64 @ c64.T
    dist = dist_sq.sub_(err).clamp_min_(0.0).sqrt_()
    dist.fill_diagonal_(float("inf"))
    return dist.amin(dim=1).to(c.dtype).mul_(1.0 - 4.0 * torch.finfo(c.dtype).eps)


def _stale(c: Tensor, labels: Tensor, upper: Tensor, lower: Tensor, err: Tensor) -> Tensor:
    """Indices of the points whose bounds cannot prove that their label is the argmin of a
    computed distance row.

    With ``U`` the upper bound on the exact distance to the own centroid, ``L`` the lower
    bound on the exact distance to any other (the larger of the smallest group bound in
    ``lower`` ``[N, groups]`` and ``separation - U``, :func:`_separation`) and ``E`` the
    bound on a computed squared distance's error, ``L^2 - U^2 > 2 E`` guarantees that every
    other centroid's computed squared distance exceeds the own one's (also in the rounding
    of ``(L - U)(L + U)``, which ``1 - 4 eps`` covers).
    """
    eps = torch.finfo(upper.dtype).eps
    apart = (_separation(c).index_select(0, labels) - upper).mul_(1.0 - 2.0 * eps)  # its rounding
    bound = torch.maximum(lower.amin(dim=0), apart)
    gap = (bound - upper).mul_(bound + upper).mul_(1.0 - 4.0 * eps)
    return (gap <= 2.0 * err).nonzero().squeeze(1)


def _lloyd(
    x: Tensor,
    centroids: Tensor,
    max_iter: int,
    tol_abs: Tensor | float,
    x_sq: Tensor | None = None,
) -> KMeansResult:
    """Lloyd iterations from ``centroids`` until the shift is ``<= tol_abs`` (absolute).

    Exact Lloyd that skips the distance rows it can prove unnecessary, with Hamerly's (2010)
    upper bound and Yinyang k-means' grouped lower bounds (Ding et al., 2015): every point
    keeps an upper bound ``u`` on the distance to its centroid and, per group of
    ``_GROUP`` near centroids, a lower bound on the distance to the group's centroids
    other than its own. When the centroids move by ``delta``, ``u += delta[label]`` and each
    group's bound drops by the group's largest drift (Hamerly's single bound drops by the
    largest drift of all, so one far-moving centroid voids every bound; the groups confine
    that to its own group). A point whose bounds prove that its label is
    still the argmin of its distance row (:func:`_stale`; the distance from its centroid to
    the nearest other, less ``u``, also bounds from below) keeps its label without a row;
    only the remaining points get a row of distances (one matrix product over those rows),
    which resets their bounds. Ding et al.'s second filter (rows restricted to the groups a
    point cannot rule out) is left out: a vectorised row over all ``k`` centroids costs less
    than gathering the groups per point.

    The bounds are rigorous for the exact distances, not only for the computed ones: they
    are taken from the computed squared distances widened by their rounding error
    (:func:`_sq_error`), and the drifts are widened by theirs. A point is skipped only when
    the gap its bounds prove exceeds twice the error of a computed squared distance, so a
    skipped point's computed row would have had the same argmin: labels, centroids,
    iteration count and stopping are those of plain Lloyd. (The error bound is per point and
    enters as ``2 E / (L + U)`` on distances, about 1e-4 for unit-norm points at D = 132 in
    float32; a bound on the distance error itself, ``sqrt(E)``, is 100x wider.) The cluster
    sums are updated with the points that changed cluster only.

    Groups are made of near centroids (:func:`_proximity_order`): a group's bound then
    excludes only centroids about as far as each other, and fewer points need rows (on Full's
    points at k = 132, 9.0 rows per point against 13.1 for groups of consecutive indices).
    The centroids are reordered for the iterations and put back before the final assignment,
    whose ties go to the lowest index of the caller's order. The reordering moves each
    centroid's products to another position of the BLAS kernel, which can round them
    differently: a point whose two nearest centroids are within that rounding may get the
    other one than with groups of consecutive indices (and Lloyd's path then drifts), as any
    change of the products' evaluation order would.
    """
    n, d = x.shape
    x_sq = (x * x).sum(1) if x_sq is None else x_sq  # [N]
    order = _proximity_order(centroids)
    centroids, labels, upper, lower, n_iter, rows = _lloyd_state(
        x, centroids.index_select(0, order), max_iter, tol_abs, x_sq
    )
    # Final assignment to the last centroids: the full distance matrix (returned), labels of
    # the points whose bounds cannot vouch for them taken from its rows.
    err = _sq_error(x_sq, float((centroids * centroids).sum(1).max()), d)
    stale = _stale(centroids, labels, upper, lower, err)
    centroids = torch.empty_like(centroids).index_copy_(0, order, centroids)  # caller's order
    labels = order.index_select(0, labels)
    sq = sq_distances(x, centroids, x_sq.unsqueeze(1))
    rows += n
    if stale.numel():
        labels[stale] = sq[stale].min(dim=1).indices
    inertia = sq.gather(1, labels.unsqueeze(1)).sum()
    return KMeansResult(
        centroids=centroids,
        labels=labels,
        inertia=inertia,
        n_iter=n_iter,
        sq_dists=sq,
        dist_rows=rows,
    )


def _proximity_order(c: Tensor) -> Tensor:
    """``[k]``: an order of the centroids ``c`` ``[k, D]`` whose runs of ``_GROUP`` are near
    centroids (greedily: the first centroid not yet grouped and its ``_GROUP - 1`` nearest
    ungrouped ones; Yinyang k-means groups its centroids by a k-means of them instead, to the
    same end). Deterministic: ties go to the lower index."""
    k = c.shape[0]
    if k <= _GROUP:
        return torch.arange(k, device=c.device)
    c64 = c.double()
    dist = torch.cdist(c64, c64)
    free = torch.ones(k, dtype=torch.bool, device=c.device)
    runs = []
    for _ in range(-(-k // _GROUP)):
        first = int(free.nonzero()[0])
        row = dist[first].masked_fill(~free, float("inf"))
        run = torch.sort(row, stable=True).indices[: min(_GROUP, int(free.sum()))]
        free[run] = False
        runs.append(run)
    return torch.cat(runs)


def _lloyd_state(
    x: Tensor,
    centroids: Tensor,
    max_iter: int,
    tol_abs: Tensor | float,
    x_sq: Tensor,
) -> tuple[Tensor, Tensor, Tensor, Tensor, int, int]:
    """The iterations of :func:`_lloyd` on centroids whose groups are runs of ``_GROUP``
    consecutive rows, ``x_sq`` ``[N]`` the points' squared norms. Returns ``(centroids,
    labels, upper, lower, n_iter, rows)``: the last centroids and the state of the bounds, for
    the final assignment."""
    n, d = x.shape
    k = centroids.shape[0]
    tol = float(tol_abs)
    eps = torch.finfo(x.dtype).eps
    # A drift computed as sqrt(sum((new - c)^2)) errs by less than (d + 4) eps relative.
    drift_widen = 1.0 + 2.0 * (d + 3) * eps
    groups = -(-k // _GROUP)
    c_sq = (centroids * centroids).sum(1)
    err = _sq_error(x_sq, float(c_sq.max()), d)
    labels, upper, lower = _assign_rows(x, x_sq, centroids, c_sq, err, groups)  # lower [G, N]
    rows = n
    counts = torch.bincount(labels, minlength=k)
    sums = torch.zeros_like(centroids).index_add_(0, labels, x)
    n_iter = 0
    for n_iter in range(1, max_iter + 1):  # noqa: B007 - n_iter is reported
        if n_iter > 1:
            c_sq = (centroids * centroids).sum(1)
            err = _sq_error(x_sq, float(c_sq.max()), d)
            stale = _stale(centroids, labels, upper, lower, err)
            if stale.numel():
                rows += stale.numel()
                # index_select / index_copy_ rather than [] indexing: the same gathers and
                # scatters, 3x faster on the CPU (no advanced-indexing machinery).
                new_labels, up_rows, low_rows = _assign_rows(
                    x.index_select(0, stale),
                    x_sq.index_select(0, stale),
                    centroids,
                    c_sq,
                    err.index_select(0, stale),
                    groups,
                )
                upper.index_copy_(0, stale, up_rows)
                lower.index_copy_(1, stale, low_rows)
                old_labels = labels.index_select(0, stale)
                moved = (new_labels != old_labels).nonzero().squeeze(1)
                idx = stale.index_select(0, moved)
                to, frm = new_labels.index_select(0, moved), old_labels.index_select(0, moved)
                labels.index_copy_(0, idx, to)
                if 4 * idx.numel() > n:  # many moves: recount from scratch
                    counts = torch.bincount(labels, minlength=k)
                    sums = torch.zeros_like(centroids).index_add_(0, labels, x)
                elif idx.numel():
                    xm = x.index_select(0, idx)
                    sums.index_add_(0, to, xm).index_add_(0, frm, xm, alpha=-1)
                    counts += torch.bincount(to, minlength=k) - torch.bincount(frm, minlength=k)
        new = sums / counts.clamp_min(1).unsqueeze(1).to(x.dtype)
        empty = counts == 0
        if bool(empty.any()):
            # Re-seed empty clusters with the points worst served by the current solution.
            part = torch.addmm((centroids * centroids).sum(1), x, centroids.T, alpha=-2.0)
            rows += n
            new[empty] = x[part.amin(dim=1).add_(x_sq).topk(int(empty.sum())).indices]
        delta_sq = ((new - centroids) ** 2).sum(1)
        shift = float(delta_sq.sum())
        delta = delta_sq.sqrt().mul_(drift_widen)
        # (1 +- 4 eps): the rounding of the bound updates themselves.
        upper.add_(delta.index_select(0, labels)).mul_(1.0 + 4.0 * eps)
        # Group-major [G, N] bounds: this and the minimum over groups in _stale run along
        # contiguous rows, ~10x faster than over the 9-wide rows of an [N, G] layout.
        lower.sub_(_group_max(delta, groups).unsqueeze(1)).mul_(1.0 - 4.0 * eps)
        centroids = new
        if shift <= tol:
            break
    return centroids, labels, upper, lower, n_iter, rows


# ------------------------------------------------------------------ variational mixture
@dataclass
class VBGMMResult:
    """A fitted variational Bayesian Gaussian mixture (diagonal covariances).

    Attributes:
        elbo: the evidence lower bound ``L(q)`` of the fit, all terms included (comparable
            across component counts, see :func:`vb_gmm`), as a Python float.
        lower_bound: scikit-learn's ``lower_bound_``: the bound less the terms that are
            constant for a fixed component count (``elbo = lower_bound + constant``).
        n_iter: EM iterations run.
        converged: whether the bound changed by less than ``tol`` before ``max_iter``.
        weights: ``[k]`` expected mixing weights ``E[pi]``.
        means: ``[k, r]`` posterior means of the components.
    """

    elbo: float
    lower_bound: float
    n_iter: int
    converged: bool
    weights: Tensor
    means: Tensor


def _vb_e_step(xx: Tensor, p: dict[str, Tensor]) -> tuple[Tensor, Tensor]:
    """``([N, k] log responsibilities, [N, k] responsibilities)`` (scikit-learn's
    ``_estimate_log_prob`` plus ``_estimate_log_weights`` of the diagonal
    ``BayesianGaussianMixture``, normalised), from ``xx = [x, x^2]`` ``[N, 2r]``: both products
    of the quadratic form in one, every per-component term folded into one ``[k]`` offset, so
    that the ``[N, k]`` work is one product and a few in-place passes."""
    r = xx.shape[1] // 2
    prec = 1.0 / p["cov"]  # [k, r]: precisions_cholesky_ ** 2
    log_det = -0.5 * torch.log(p["cov"]).sum(1)  # sum(log precisions_cholesky_)
    i = torch.arange(r, dtype=xx.dtype, device=xx.device).unsqueeze(1)
    log_lambda = r * math.log(2.0) + torch.digamma(0.5 * (p["dof"] - i)).sum(0)
    alpha = p["alpha"]
    offset = (  # [k]: log N's constant and mean term, E[ln|Lambda|], E[ln pi]
        -0.5 * (r * math.log(2 * math.pi) + (p["means"].square() * prec).sum(1))
        + log_det - 0.5 * r * torch.log(p["dof"])
        + 0.5 * (log_lambda - r / p["beta"])
        + (torch.digamma(alpha) - torch.digamma(alpha.sum()))
    )  # fmt: skip
    log_prob = xx @ torch.cat([p["means"] * prec, -0.5 * prec], 1).T  # -quad/2 less its constant
    log_prob += offset
    # Normalised by hand rather than with logsumexp, to take one exp, not two; and the log
    # weights far below a point's largest are kept at e times the smallest normal number: their
    # exp would be subnormal (x86 computes those several times slower) and weighs nothing.
    log_prob -= log_prob.amax(1, keepdim=True)
    log_prob.clamp_(min=math.log(torch.finfo(log_prob.dtype).tiny) + 1.0)
    resp = log_prob.exp()
    total = resp.sum(1, keepdim=True)
    resp /= total
    return log_prob.sub_(total.log_()), resp


def _vb_m_step(xx: Tensor, resp: Tensor, prior: dict[str, Tensor | float],
               reg_covar: float, weight: float = 1.0) -> dict[str, Tensor]:  # fmt: skip
    """Posterior parameters from responsibilities ``[N, k]`` and ``xx = [x, x^2]`` (scikit-
    learn's ``_estimate_gaussian_parameters`` then ``_estimate_weights`` / ``_estimate_means``
    / ``_estimate_wishart_diag``, Dirichlet-distribution weight prior), every point counted
    ``weight`` times."""
    r = xx.shape[1] // 2
    nk = weight * resp.sum(0) + 10 * torch.finfo(resp.dtype).eps
    moments = (weight * (resp.T @ xx)) / nk.unsqueeze(1)  # [k, 2r]: E[x], E[x^2] per component
    xk = moments[:, :r]
    sk = moments[:, r:] - xk.square() + reg_covar
    beta = prior["beta"] + nk
    dof = prior["dof"] + nk
    diff = xk - prior["mean"]
    cov = prior["cov"] + nk.unsqueeze(1) * (
        sk + (prior["beta"] / beta).unsqueeze(1) * diff.square()
    )
    return {
        "alpha": prior["alpha"] + nk,
        "beta": beta,
        "means": (prior["beta"] * prior["mean"] + nk.unsqueeze(1) * xk) / beta.unsqueeze(1),
        "dof": dof,
        "cov": cov / dof.unsqueeze(1),  # normalised as scikit-learn does (the expected covariance)
    }


def _log_wishart_norm(dof: Tensor, half_log_det_w: Tensor, r: int) -> Tensor:
    """``-ln B(W, nu)`` per component, less ``r (r - 1) / 4 ln pi`` (scikit-learn's
    ``_log_wishart_norm``): ``nu/2 ln|W| + nu r/2 ln 2 + sum_i lgamma((nu - i) / 2)``
    with ``half_log_det_w = ln|W| / 2`` (the log-determinant of W's Cholesky factor)."""
    i = torch.arange(r, dtype=dof.dtype, device=dof.device).unsqueeze(1)
    return (
        dof * half_log_det_w + dof * r * 0.5 * math.log(2.0) + torch.lgamma(0.5 * (dof - i)).sum(0)
    )


def _vb_lower_bound(
    log_resp: Tensor, resp: Tensor, p: dict[str, Tensor], weight: float = 1.0
) -> Tensor:
    """scikit-learn's ``_compute_lower_bound`` (diagonal covariances, Dirichlet distribution),
    every point counted ``weight`` times; ``resp = exp(log_resp)``."""
    r = p["means"].shape[1]
    # ln|W_k| / 2 with W_k = (dof_k cov_k)^-1, as scikit-learn's normalised precision factor.
    half_log_det_w = -0.5 * torch.log(p["cov"]).sum(1) - 0.5 * r * torch.log(p["dof"])
    log_wishart = -_log_wishart_norm(p["dof"], half_log_det_w, r).sum()
    alpha = p["alpha"]
    log_dirichlet_norm = torch.lgamma(alpha.sum()) - torch.lgamma(alpha).sum()
    entropy = -weight * torch.dot(resp.view(-1), log_resp.view(-1))
    return entropy - log_wishart - log_dirichlet_norm - 0.5 * r * torch.log(p["beta"]).sum()


def _vb_constant(n: float, k: int, prior: dict[str, Tensor | float]) -> float:
    """The terms scikit-learn's bound leaves out because they are constant for a fixed ``k``.

    At the M-step's optimum the bound collapses to ``H[q(Z)] + ln Z_post / Z_prior - N r/2
    ln 2 pi`` (a conjugate model: Bishop, PRML eqs. 10.70-10.77): scikit-learn keeps the
    entropy and the posterior normalisers ``Z_post``. Left out are, per component, the
    Normal-Wishart prior's normaliser (its ``r/2 ln 2 pi`` and ``r (r - 1) / 4 ln pi`` cancel
    against the posterior's, which scikit-learn also omits), the Dirichlet prior's
    ``ln C(alpha_0) = lgamma(k alpha_0) - k lgamma(alpha_0)``, and the data's ``- N r/2 ln 2 pi``.
    """
    cov0 = torch.as_tensor(prior["cov"], dtype=torch.float64)
    r = cov0.shape[0]
    dof0 = torch.tensor([float(prior["dof"])], dtype=torch.float64)
    half_log_det_w0 = -0.5 * torch.log(cov0).sum()  # W_0 = covariance_prior^-1
    prior_wishart = float(_log_wishart_norm(dof0, half_log_det_w0.reshape(1), r)[0])
    alpha0 = float(prior["alpha"])
    log_c0 = math.lgamma(k * alpha0) - k * math.lgamma(alpha0)
    return (
        k * (0.5 * r * math.log(float(prior["beta"])) - prior_wishart)
        + log_c0
        - 0.5 * n * r * math.log(2 * math.pi)
    )


def vb_gmm(
    x: Tensor,
    labels: Tensor,
    n_components: int,
    *,
    weight_concentration_prior: float | None = None,
    mean_precision_prior: float = 1.0,
    degrees_of_freedom_prior: float | None = None,
    reg_covar: float = 1e-6,
    tol: float = 1e-3,
    max_iter: int = 100,
    point_weight: float = 1.0,
    dtype: torch.dtype = torch.float64,
) -> VBGMMResult:
    """Variational Bayesian Gaussian mixture with diagonal covariances, from hard labels.

    The model and the updates are scikit-learn's ``BayesianGaussianMixture(covariance_type=
    "diag", weight_concentration_prior_type="dirichlet_distribution")`` with its default
    priors (``weight_concentration_prior = 1 / k``, ``mean_precision_prior = 1``, the data's
    mean as ``mean_prior``, ``degrees_of_freedom_prior = r``, the data's per-feature variance
    (``ddof=1``) as ``covariance_prior``), initialised, as its ``init_params="kmeans"``, by
    an M-step on the one-hot responsibilities of ``labels``, then EM until the bound changes
    by less than ``tol``. Written in torch (matrix products over points and components) so it
    runs where ReSiReg Full's points are; computed in float64 unless ``dtype`` says otherwise.

    Args:
        x: ``[N, r]`` points.
        labels: ``[N]`` initial component of every point (e.g. :func:`kmeans`' labels).
        n_components: ``k``.
        point_weight: how many points each row of ``x`` stands for (a frequency weight: the
            fit equals scikit-learn's on ``x`` with every row repeated that many times, for an
            integer weight). A uniform subsample of ``M`` of ``N`` points with weight ``N / M``
            estimates the whole set's bound, whose data terms grow with ``N`` while the
            prior's do not (the stochastic-variational scaling of Hoffman et al., 2013);
            unweighted, a subsample's bound weighs the prior ``N / M`` times too much and
            favours too few components.
        dtype: of the EM arithmetic; float64 as scikit-learn (the bound is a sum over all
            points), float32 where only the comparison of bounds matters (their differences
            between counts are thousands of nats, float32's rounding of the sum a few).

    Returns:
        :class:`VBGMMResult`; ``elbo`` is the whole bound (scikit-learn's ``lower_bound_``
        plus the prior normalisers it drops as constant for one ``k``, :func:`_vb_constant`),
        which is what makes bounds of different ``k`` comparable.
    """
    if x.ndim != 2 or x.shape[0] < 2:
        raise ValueError(f"vb_gmm expects x of shape [N >= 2, r], got shape {tuple(x.shape)}")
    if not (math.isfinite(point_weight) and point_weight > 0):
        raise ValueError(f"point_weight={point_weight!r}: expected a finite number > 0")
    x = x.to(dtype)
    n, r = x.shape
    k = int(n_components)
    w = float(point_weight)
    xx = torch.cat([x, x.square()], 1)
    mean = x.mean(0)
    prior: dict[str, Tensor | float] = {
        "alpha": 1.0 / k
        if weight_concentration_prior is None
        else float(weight_concentration_prior),
        "beta": float(mean_precision_prior),
        "mean": mean,
        "dof": float(r if degrees_of_freedom_prior is None else degrees_of_freedom_prior),
        # the per-feature variance (ddof = 1) of the weighted set: sum w (x - m)^2 / (n w - 1)
        "cov": (x - mean).square().sum(0) * (w / (n * w - 1.0)),
    }
    resp = F.one_hot(labels.long().to(x.device), k).to(x.dtype)
    params = _vb_m_step(xx, resp, prior, reg_covar, w)
    bound = -math.inf
    converged, n_iter = False, 0
    for n_iter in range(1, max_iter + 1):  # noqa: B007 - n_iter is reported
        previous = bound
        log_resp, resp = _vb_e_step(xx, params)
        params = _vb_m_step(xx, resp, prior, reg_covar, w)
        bound = float(_vb_lower_bound(log_resp, resp, params, w))
        if abs(bound - previous) < tol:
            converged = True
            break
    alpha = params["alpha"]
    return VBGMMResult(
        elbo=bound + _vb_constant(n * w, k, prior),
        lower_bound=bound,
        n_iter=n_iter,
        converged=converged,
        weights=(alpha / alpha.sum()).float(),
        means=params["means"].float(),
    )


#: the default subsample size of :func:`elbo_fits` (its ``max_points``) and of ReSiReg Full's
#: chooser (``full.elbo_max_points`` of conf/resireg/default.yaml, which sets it for runs)
ELBO_MAX_POINTS = 4096


def elbo_subsample(n: int, max_points: int, seed: int = 0) -> Tensor | None:
    """The rows of ``n`` points that :func:`elbo_fits` fits: ``None`` (all) for ``n <=
    max_points``, else ``max_points`` indices drawn uniformly without replacement (a CPU
    ``randperm`` seeded ``seed``, so the same on every device)."""
    if n <= max_points:
        return None
    return torch.randperm(n, generator=_generator(torch.device("cpu"), seed))[:max_points]


def elbo_fits(
    points: Tensor,
    candidates: Sequence[int],
    seed: int = 0,
    *,
    max_points: int = ELBO_MAX_POINTS,
    max_iter: int = 100,
    tol: float = 1e-3,
    kmeans_iter: int = 0,
    dtype: torch.dtype = torch.float32,
    stop_after: int | None = None,
    n_points: int | None = None,
) -> dict[int, VBGMMResult]:
    """The variational mixtures of the candidate counts, fitted for
    :func:`elbo_prototype_count` (docs/design.md section 4.4b).

    For the candidates ``k`` in increasing order (all, or until ``stop_after`` ends the scan): a
    greedy k-means++ seeding (seed ``seed``), ``kmeans_iter`` Lloyd iterations from it (none by
    default: every point is labelled by its nearest seed), then :func:`vb_gmm` from those
    labels. The seedings are the first ``k`` centres of one greedy k-means++ run (``2 + ln(max
    candidate)`` trials per centre for every ``k``): each centre depends only on those before
    it, so one run seeds every candidate. Above ``max_points`` points the mixtures are fitted on
    a uniform subsample of ``M = max_points`` (:func:`elbo_subsample`), each point standing for
    ``N / M`` (``vb_gmm``'s ``point_weight``), so that every :attr:`VBGMMResult.elbo` estimates
    the bound of all ``N`` points. Unweighted, the subsample's bound would weigh the priors
    ``N / M`` times too heavily and favour too few prototypes.

    Args:
        points: ``[N, r]`` (ReSiReg Full's normalised PCA points), or, with ``n_points``,
            the subsample of ``n_points`` such points that :func:`elbo_subsample` draws.
        candidates: prototype counts (each ``>= 1`` and ``<=`` the points fitted).
        seed: seed of the subsample and of k-means++.
        max_points: the subsample's size ``M``.
        max_iter: EM iterations at most per candidate.
        tol: EM stops once the bound changes by less than ``tol`` nats per point (of ``N``):
            on the benchmark's features the bounds at ``1e-3`` are within 0.15 (regions) and
            0.6 (soft mixtures) nats per point of those at ``1e-4``, lower for the larger,
            slower-converging counts, while the chosen count beats its neighbours by 0.9 and
            more (docs/benchmarks.md).
        kmeans_iter: Lloyd iterations at most of the k-means that starts each fit; ``0``
            starts EM from every point's nearest seed (EM, a soft k-means, refines the start:
            Lloyd first did not change the choice or the EM iterations, only the cost).
        dtype: of the EM arithmetic (see :func:`vb_gmm`).
        stop_after: ``None`` fits every candidate; a number ``p`` stops the scan once ``p``
            consecutive candidates have a bound below the largest so far (the bound rises
            with the count, then falls; see :func:`elbo_prototype_count`).
        n_points: ``points`` are ``elbo_subsample(n_points, max_points, seed)``'s rows of a
            set of ``n_points`` (what the caller drew to skip computing the rest); ``None``:
            ``points`` are the whole set.

    Returns:
        ``{k: fit}`` of the candidates fitted, in increasing ``k``.
    """
    if points.ndim != 2:
        raise ValueError(f"elbo_prototype_count expects points [N, r], got {tuple(points.shape)}")
    counts = sorted({int(c) for c in candidates})
    if not counts or counts[0] < 1:
        raise ValueError(f"candidates={list(candidates)}: give at least one count >= 1")
    if stop_after is not None and stop_after < 1:
        raise ValueError(f"stop_after={stop_after!r}: expected None or a number >= 1")
    x = points.float()
    if n_points is None:
        n = x.shape[0]
        rows = elbo_subsample(n, max_points, seed)
        if rows is not None:
            x = x[rows.to(x.device)]
    else:
        n = int(n_points)
        if x.shape[0] != min(n, max_points):
            raise ValueError(
                f"n_points={n} with max_points={max_points}: expected the {min(n, max_points)} "
                f"subsampled points, got {x.shape[0]}"
            )
    if counts[-1] > x.shape[0]:
        raise ValueError(
            f"candidates={counts}: {counts[-1]} prototypes exceed the {x.shape[0]} points fitted"
        )
    weight = n / x.shape[0]  # each subsampled point stands for N / M (see vb_gmm)
    x = x.contiguous()
    x_sq = (x * x).sum(1)
    tol_abs = _tolerance(x, 1e-4)  # kmeans' default
    steps = _plusplus_steps(x, x.T.contiguous(), x_sq, _generator(x.device, seed),
                            2 + int(math.log(counts[-1])))  # fmt: skip
    centres: list[Tensor] = []
    fits: dict[int, VBGMMResult] = {}
    best, below = -math.inf, 0
    for k in counts:
        centres.extend(next(steps) for _ in range(k - len(centres)))
        seeds = torch.stack(centres)
        if kmeans_iter > 0:
            labels = _lloyd(x, seeds, kmeans_iter, tol_abs, x_sq=x_sq).labels
        else:  # each point's nearest seed
            labels = sq_distances(x, seeds, x_sq.unsqueeze(1)).argmin(1)
        fit = vb_gmm(x, labels, k, max_iter=max_iter, tol=tol * n, point_weight=weight,
                     dtype=dtype)  # fmt: skip
        fits[k] = fit
        if fit.elbo > best:
            best, below = fit.elbo, 0
        else:
            below += 1
            if stop_after is not None and below >= stop_after:
                break
    return fits


def elbo_prototype_count(
    points: Tensor,
    candidates: Sequence[int],
    seed: int = 0,
    *,
    stop_after: int | None = 2,
    **options: Any,
) -> int:
    """The prototype count among ``candidates`` whose mixture has the largest evidence lower
    bound (the smaller count on a tie; docs/design.md section 4.4b).

    The candidates are fitted in increasing order and the scan stops once ``stop_after``
    consecutive candidates fall below the largest bound so far (the bound rises with the
    count while components separate real clusters and then falls by the prior's price of
    every further component); ``stop_after=None`` fits them all.

    Args:
        points: ``[N, r]`` (ReSiReg Full's normalised PCA points).
        candidates: prototype counts to choose from (each ``>= 1`` and ``<=`` the points used).
        seed: seed of the subsample and of k-means++.
        stop_after: see above and :func:`elbo_fits`.
        options: :func:`elbo_fits`' other keywords (subsample size, EM and k-means
            iterations, tolerance, dtype, ``n_points``).

    Returns:
        The chosen count (a member of ``candidates``).
    """
    fits = elbo_fits(points, candidates, seed, stop_after=stop_after, **options)
    best = max(fits.values(), key=lambda fit: fit.elbo)
    return min(k for k, fit in fits.items() if fit.elbo == best.elbo)
