"""Torch k-means: cluster points into ``k`` centroids, as scikit-learn's ``KMeans`` does.

The one job of this module is the k-means that groups ReSiReg Full's projected points into
prototypes (docs/method.md#pca-and-k-means). :func:`kmeans` is scikit-learn's
``KMeans(init="k-means++", n_init=1)``: greedy k-means++ seeding (:func:`kmeans_plusplus`),
then Lloyd iterations stopped by scikit-learn's tolerance rule, with distance bounds
(Hamerly's upper bound, Yinyang's grouped lower bounds, both widened by a rigorous float
rounding bound) so that an iteration computes distances only for the points whose nearest
centroid might have changed (same labels, centroids and iteration count as plain Lloyd).
:func:`nested_kmeans` labels points for several increasing counts from one seeding (what the
ELBO chooser of :mod:`resireg.method.elbo` starts its mixtures from); :func:`sq_distances` is the
squared-distance matrix all of them use.

Everything runs on the input's device with matrix products and scatter ops only: the
clustering sits inside a GPU forward pass, and moving tens of thousands of points to the host
per batch would cost more than the clustering itself (``benchmarks/bench_reconstruct.py``).

One idea: k-means. The seeding, the bounded Lloyd iterations and the nested counts are one
algorithm whose parts share private state and invariants (the bounds that let an iteration skip
a point hold only with this module's tolerance rule, rounding bound and assignment order), so
they stay in one module rather than leak those internals across several.
"""

from __future__ import annotations

import itertools
import math
from collections.abc import Callable, Iterator, Sequence
from dataclasses import dataclass

import torch
import torch.nn.functional as F
from torch import Tensor

__all__ = ["KMeansResult", "kmeans", "kmeans_plusplus", "nested_kmeans", "sq_distances"]


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
    of several sizes (:func:`nested_kmeans`) runs the steps of the largest once."""
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


def nested_kmeans(
    x: Tensor,
    counts: Sequence[int],
    *,
    seed: int = 0,
    max_iter: int = 0,
    tol: float = 1e-4,
) -> Iterator[tuple[int, Tensor]]:
    """K-means labels of ``x`` ``[N, D]`` for each of the increasing ``counts``, from one seeding.

    The seeding of count ``k`` is the first ``k`` centres of one greedy k-means++ run (seed
    ``seed``, ``2 + floor(ln(max count))`` candidates per centre for every ``k``): each centre
    depends only on those before it, so one run seeds every count. From it, ``max_iter`` Lloyd
    iterations (stopped as :func:`kmeans` stops them, ``tol`` relative); with ``max_iter=0``
    (the default) every point is labelled by its nearest seed.

    Lazy: yields ``(k, labels [N])`` per count in the order given, and a caller that stops
    early (the ELBO chooser of :mod:`resireg.method.elbo`, once the bound falls) computes no seeding
    step or label beyond the counts it took.

    Args:
        x: ``[N, D]`` points.
        counts: strictly increasing counts, each ``>= 1`` and ``<= N``.
        seed: seed of k-means++.
        max_iter: Lloyd iterations at most per count.
        tol: Lloyd's relative tolerance (see :func:`kmeans`).
    """
    counts = [int(c) for c in counts]
    if x.ndim != 2:
        raise ValueError(f"nested_kmeans expects x of shape [N, D], got shape {tuple(x.shape)}")
    if not counts or counts[0] < 1 or counts[-1] > x.shape[0]:
        raise ValueError(f"counts={counts}: expected counts in 1..N (N={x.shape[0]})")
    if any(b <= a for a, b in itertools.pairwise(counts)):
        raise ValueError(f"counts={counts}: expected strictly increasing counts")
    return _nested_kmeans(x.float().contiguous(), counts, seed, max_iter, tol)


def _nested_kmeans(
    x: Tensor, counts: list[int], seed: int, max_iter: int, tol: float
) -> Iterator[tuple[int, Tensor]]:
    """The generator behind :func:`nested_kmeans` (whose checks run at the call, not at the
    first ``next``)."""
    x_sq = (x * x).sum(1)
    tol_abs = _tolerance(x, tol)
    steps = _plusplus_steps(x, x.T.contiguous(), x_sq, _generator(x.device, seed),
                            2 + int(math.log(counts[-1])))  # fmt: skip
    centres: list[Tensor] = []
    for k in counts:
        centres.extend(next(steps) for _ in range(k - len(centres)))
        seeds = torch.stack(centres)
        if max_iter > 0:
            labels = _lloyd(x, seeds, max_iter, tol_abs, x_sq=x_sq).labels
        else:  # each point's nearest seed
            labels = sq_distances(x, seeds, x_sq.unsqueeze(1)).argmin(1)
        yield k, labels


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
