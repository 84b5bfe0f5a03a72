import numpy as np
import pytest
import torch
from sklearn.cluster import KMeans
from sklearn.cluster._kmeans import _tolerance as sk_tolerance
from sklearn.decomposition import PCA

from resireg.method.kmeans import _lloyd, _tolerance, kmeans, kmeans_plusplus, sq_distances
from resireg.method.pca import gram, pca


def _mixture(n=3000, d=24, k=8, seed=0, spread=1.0):
    g = torch.Generator().manual_seed(seed)
    centers = torch.randn(k, d, generator=g) * 3
    labels = torch.randint(k, (n,), generator=g)
    return centers[labels] + spread * torch.randn(n, d, generator=g)


def test_pca_matches_sklearn():
    x = _mixture(d=40) @ torch.randn(40, 40, generator=torch.Generator().manual_seed(1))
    ours = pca(x, 10)
    ref = PCA(n_components=10, svd_solver="full").fit(x.double().numpy())
    np.testing.assert_allclose(ours.explained_variance.numpy(), ref.explained_variance_, rtol=1e-3)
    # Same subspace: projectors onto the components agree.
    p_ours = ours.components.T.double() @ ours.components.double()
    p_ref = torch.from_numpy(ref.components_.T @ ref.components_)
    assert torch.allclose(p_ours, p_ref, atol=1e-3)
    # Same transform up to the sign of each axis (and with the svd_flip convention, equal).
    z_ref = torch.from_numpy(ref.transform(x.double().numpy())).float()
    assert torch.allclose(ours.transform(x).abs(), z_ref.abs(), atol=2e-2)


def test_pca_clips_components_to_dim():
    x = torch.randn(100, 5)
    assert pca(x, 36).components.shape == (5, 5)


def test_kmeans_inertia_close_to_sklearn():
    x = torch.nn.functional.normalize(_mixture(n=6000, d=16, k=20, spread=2.0), dim=1)
    # Single runs land in different local minima, so compare means over seeds.
    runs = [kmeans(x, 20, seed=s) for s in range(6)]
    ours_mean = float(np.mean([r.inertia.item() for r in runs]))
    ref_mean = float(
        np.mean([KMeans(20, n_init=1, random_state=s).fit(x.numpy()).inertia_ for s in range(6)])
    )
    assert ours_mean <= 1.02 * ref_mean
    ours = runs[0]
    # Inertia is consistent with labels and centroids.
    recomputed = ((x - ours.centroids[ours.labels]) ** 2).sum()
    assert torch.allclose(ours.inertia, recomputed, rtol=1e-4)


def test_kmeans_deterministic_for_seed():
    x = _mixture(n=2000, d=8, k=6)
    a, b = kmeans(x, 6, seed=3), kmeans(x, 6, seed=3)
    assert torch.equal(a.labels, b.labels)
    assert torch.equal(a.centroids, b.centroids)
    assert torch.equal(a.sq_dists, b.sq_dists)
    assert (a.n_iter, a.dist_rows) == (b.n_iter, b.dist_rows)
    assert not torch.equal(kmeans(x, 6, seed=4).centroids, a.centroids)


def test_kmeans_reseeds_empty_clusters():
    x = _mixture(n=500, d=4, k=3)
    centroids = torch.cat([x[:2], torch.full((1, 4), 1e6)])  # the third attracts nobody
    result = _lloyd(x, centroids, max_iter=50, tol_abs=torch.tensor(0.0))
    assert torch.bincount(result.labels, minlength=3).min() > 0


def test_kmeans_rejects_too_many_clusters():
    with pytest.raises(ValueError, match="n_clusters=11"):
        kmeans(torch.randn(10, 2), 11)


def test_sq_distances_matches_cdist():
    x, c = torch.randn(50, 7), torch.randn(4, 7)
    assert torch.allclose(sq_distances(x, c), torch.cdist(x, c) ** 2, atol=1e-4)


# --- tolerance stopping, seeding and the bounded Lloyd against independent references ---


def _blobs(n=5000, d=32, k=6, spread=2.0, seed=0):
    """Overlapping gaussian blobs: every seed reaches the same optimum after ~10 iterations."""
    g = torch.Generator().manual_seed(seed)
    centers = torch.randn(k, d, generator=g)
    labels = torch.randint(k, (n,), generator=g)
    return centers[labels] + spread * torch.randn(n, d, generator=g)


def _numpy_lloyd(x, init, max_iter, tol):
    """Plain float64 Lloyd with scikit-learn's stopping rule, from ``init``."""
    x, c = x.astype(np.float64), init.astype(np.float64)
    tol_abs = np.mean(np.var(x, axis=0)) * tol
    for it in range(1, max_iter + 1):  # noqa: B007 - the count is returned
        labels = ((x[:, None, :] - c[None]) ** 2).sum(-1).argmin(1)
        new = np.stack([x[labels == j].mean(0) for j in range(len(c))])
        shift = ((new - c) ** 2).sum()
        c = new
        if shift <= tol_abs:
            break
    d2 = ((x[:, None, :] - c[None]) ** 2).sum(-1)
    return c, d2.argmin(1), it, d2


def test_gram_matches_matmul_and_accumulates():
    g = torch.Generator().manual_seed(0)
    for d in (5, 127, 128, 130):  # one plain product below 128 columns, 4 slabs from 128 on
        y = torch.randn(200, d, generator=g, dtype=torch.float64)
        assert torch.allclose(gram(y), y.T @ y, rtol=1e-12, atol=1e-10)
        acc = gram(y[:70])
        assert gram(y[70:], out=acc) is acc  # in place
        assert torch.allclose(acc, y.T @ y, rtol=1e-12, atol=1e-10)


def test_tolerance_is_sklearns():
    x = _blobs(n=1000, d=7) * torch.linspace(0.5, 3.0, 7) + 10.0
    assert _tolerance(x, 1e-4) == pytest.approx(float(sk_tolerance(x.numpy(), 1e-4)), rel=1e-5)
    assert _tolerance(x, 1e-4) == pytest.approx(1e-4 * float(np.var(x.numpy(), axis=0).mean()))
    assert _tolerance(x, 0.0) == 0.0


def test_kmeans_plusplus_is_greedy_kmeanspp():
    """Same draws as the torch generator gives, replayed in float64 numpy: the same centres."""
    x = _mixture(n=2000, d=8, k=6)
    k, trials = 6, 2 + int(np.log(6))
    ours = kmeans_plusplus(x, k, torch.Generator().manual_seed(5))
    g = torch.Generator().manual_seed(5)
    xs = x.double().numpy()
    chosen = [int(torch.randint(len(xs), (1,), generator=g)[0])]
    closest = ((xs - xs[chosen[0]]) ** 2).sum(1)
    for _ in range(1, k):
        cdf = np.cumsum(closest)
        draws = torch.rand(trials, generator=g).double().numpy() * cdf[-1]
        cand = np.minimum(np.searchsorted(cdf, draws), len(xs) - 1)
        pots = [np.minimum(closest, ((xs - xs[i]) ** 2).sum(1)) for i in cand]
        best = int(np.argmin([p.sum() for p in pots]))
        chosen.append(int(cand[best]))
        closest = pots[best]
    assert torch.equal(ours, x[chosen])


def test_kmeans_mean_inertia_over_20_seeds_within_1pct_of_sklearn():
    x = _blobs()
    seeds = range(20)
    ours = np.mean([kmeans(x, 6, seed=s).inertia.item() for s in seeds])
    ref = np.mean(
        [
            KMeans(n_clusters=6, n_init=1, init="k-means++", tol=1e-4, random_state=s)
            .fit(x.numpy())
            .inertia_
            for s in seeds
        ]
    )
    assert abs(ours / ref - 1) < 0.01
    # The criterion is sharp enough to see an unconverged Lloyd.
    early = np.mean([kmeans(x, 6, seed=s, max_iter=2).inertia.item() for s in seeds])
    assert early > 1.01 * ref


@pytest.mark.parametrize("seed", [1, 2])
def test_kmeans_stops_on_sklearns_tolerance_rule(seed):
    """Iterations, labels, centroids and distances as a float64 numpy Lloyd with the same
    init and rule, and as scikit-learn's KMeans from that init; a looser tol stops earlier."""
    x = _blobs()
    init = kmeans_plusplus(x, 6, torch.Generator().manual_seed(seed))  # what kmeans(seed) uses
    iters = {}
    for tol in (1e-2, 1e-4, 0.0):
        ours = kmeans(x, 6, seed=seed, tol=tol, max_iter=300)
        c, labels, n_iter, d2 = _numpy_lloyd(x.numpy(), init.numpy(), 300, tol)
        assert ours.n_iter == n_iter < 300
        assert np.array_equal(ours.labels.numpy(), labels)
        np.testing.assert_allclose(ours.centroids.numpy(), c, atol=1e-4)
        np.testing.assert_allclose(ours.sq_dists.numpy(), d2, rtol=1e-5, atol=1e-3)
        assert torch.equal(ours.labels, ours.sq_dists.argmin(1))
        sk = KMeans(6, init=init.numpy(), n_init=1, tol=tol, max_iter=300).fit(x.numpy())
        assert sk.n_iter_ == ours.n_iter
        iters[tol] = ours.n_iter
    assert iters[1e-2] < iters[1e-4] <= iters[0.0]


def test_kmeans_bounds_skip_distance_rows():
    """Hamerly's bounds: far fewer distance rows than plain Lloyd's N per iteration (+ the
    final assignment), with the plain Lloyd result (checked above against numpy)."""
    x = torch.nn.functional.normalize(_mixture(n=6000, d=16, k=20, spread=1.0), dim=1)
    result = kmeans(x, 20, seed=0)
    assert result.n_iter >= 3
    assert result.dist_rows < 0.6 * (result.n_iter + 1) * x.shape[0]
    c, labels, n_iter, _ = _numpy_lloyd(
        x.numpy(), kmeans_plusplus(x, 20, torch.Generator().manual_seed(0)).numpy(), 100, 1e-4
    )
    assert result.n_iter == n_iter
    assert np.array_equal(result.labels.numpy(), labels)


def test_assign_rows_bounds_hold_for_exact_distances():
    """The float32 bounds of a computed row bound the float64 distances: the upper one the
    distance to the nearest centroid, each group's lower one the distance to the group's
    other centroids, also for points that sit nearly on a centroid or a boundary."""
    from resireg.method.kmeans import _GROUP, _assign_rows, _sq_error

    g = torch.Generator().manual_seed(3)
    c = torch.randn(10, 16, generator=g)  # 10 centroids: groups of 4, 4 and 2 (padded)
    near = c[torch.arange(200) % 10] + 1e-4 * torch.randn(200, 16, generator=g)
    between = 0.5 * (c[:100:1][torch.arange(100) % 10] + c[(torch.arange(100) + 1) % 10])
    x = torch.cat([near, between, torch.randn(200, 16, generator=g) * 3])
    x_sq, c_sq = (x * x).sum(1), (c * c).sum(1)
    groups = -(-10 // _GROUP)
    err = _sq_error(x_sq, float(c_sq.max()), 16)
    labels, upper, lower = _assign_rows(x, x_sq, c, c_sq, err, groups)
    exact = torch.cdist(x.double(), c.double())  # [N, 10]
    assert (upper.double() >= exact.gather(1, labels[:, None]).squeeze(1)).all()
    others = exact.scatter(1, labels[:, None], float("inf"))
    slack = err.double().sqrt() * 1.01  # not vacuous: within the rounding bound of exact
    own = exact.gather(1, labels[:, None]).squeeze(1)
    assert (upper.double() - own <= slack).all()
    for j in range(groups):
        cols = others[:, j * _GROUP : (j + 1) * _GROUP].amin(1)
        assert (lower[j].double() <= cols).all()
        finite = cols.isfinite()
        assert (cols[finite] - lower[j, finite].double() <= slack[finite]).all()
    clear = torch.cat([torch.arange(200), torch.arange(300, 500)])  # not the midpoints (ties)
    assert torch.equal(labels[clear], exact.argmin(1)[clear])


def test_grouped_bounds_skip_more_rows_than_hamerly_with_the_same_result(monkeypatch):
    """Groups of centroids (Yinyang) vs one group of all centroids (Hamerly's single lower
    bound): the same labels, centroids and iterations, fewer distance rows."""
    import resireg.method.kmeans as kmeans_module

    x = torch.nn.functional.normalize(_mixture(n=6000, d=32, k=40, spread=2.0), dim=1)
    grouped = kmeans(x, 40, seed=1)
    monkeypatch.setattr(kmeans_module, "_GROUP", 40)
    hamerly = kmeans(x, 40, seed=1)
    assert grouped.n_iter == hamerly.n_iter >= 5
    assert torch.equal(grouped.labels, hamerly.labels)
    assert torch.equal(grouped.centroids, hamerly.centroids)
    both = 2 * x.shape[0]  # the first and the final assignment compute every row
    assert grouped.dist_rows - both < 0.8 * (hamerly.dist_rows - both)


def test_near_centroid_groups_skip_rows_and_change_nothing(monkeypatch):
    """Groups of near centroids (the default) against groups of consecutive indices: a
    permutation whose groups are the planted quadruples, then (on points without near-ties,
    where only rounding could decide) the same labels, centroids, iterations and distances,
    with fewer distance rows."""
    import resireg.method.kmeans as kmeans_module

    g = torch.Generator().manual_seed(4)
    # 12 quadruples of near centroids, listed in a shuffled order.
    hubs = torch.randn(12, 16, generator=g) * 4
    centroids = hubs.repeat_interleave(4, 0) + 0.2 * torch.randn(48, 16, generator=g)
    shuffle = torch.randperm(48, generator=g)
    order = kmeans_module._proximity_order(centroids[shuffle])
    assert torch.equal(order.sort().values, torch.arange(48))
    quadruple = (shuffle // 4)[order].view(12, 4)  # planted quadruple of each grouped centroid
    assert (quadruple == quadruple[:, :1]).all()

    # 60 centroids on 15 blobs: several centroids share a blob, as Full's 24-132 prototypes do.
    x = torch.nn.functional.normalize(_mixture(n=8000, d=32, k=15, spread=1.0, seed=5), dim=1)
    near = kmeans(x, 60, seed=2)
    monkeypatch.setattr(kmeans_module, "_proximity_order", lambda c: torch.arange(c.shape[0]))
    consecutive = kmeans(x, 60, seed=2)
    assert near.n_iter == consecutive.n_iter >= 5
    assert torch.equal(near.labels, consecutive.labels)
    assert torch.equal(near.centroids, consecutive.centroids)
    assert torch.equal(near.sq_dists, consecutive.sq_dists)
    both = 2 * x.shape[0]  # 0.84 measured
    assert near.dist_rows - both < 0.9 * (consecutive.dist_rows - both)


def test_assign_rows_ties_go_to_the_lowest_index():
    """Exact ties (duplicated centroids, also across groups) give the lowest index, as
    numpy's argmin of the same computed row; the group bound of the nearest's group then
    holds its duplicate (distance equal to the nearest), not inf."""
    from resireg.method.kmeans import _GROUP, _assign_rows, _sq_error

    g = torch.Generator().manual_seed(6)
    c = torch.randn(10, 8, generator=g)
    c[7] = c[2]  # same group as nothing: groups {0-3}, {4-7}, {8, 9}: a tie across groups
    c[3] = c[1]  # a tie within group 0
    x = torch.cat(
        [c[[2, 1, 7, 3]] + 1e-3 * torch.randn(4, 8, generator=g), torch.randn(50, 8, generator=g)]
    )
    x_sq, c_sq = (x * x).sum(1), (c * c).sum(1)
    groups = -(-10 // _GROUP)
    labels, upper, lower = _assign_rows(
        x, x_sq, c, c_sq, _sq_error(x_sq, float(c_sq.max()), 8), groups
    )
    part = (c_sq[:, None] - 2.0 * (c @ x.T)).numpy()  # the same expansion, centroid-major
    assert np.array_equal(labels.numpy(), part.argmin(0))
    assert labels[:4].tolist() == [2, 1, 2, 1]
    # point 1's nearest is centroid 1; centroid 3 (same group, same distance) bounds group 0
    assert lower[0, 1] <= upper[1] * (1 + 1e-5)


def test_nested_kmeans_is_one_seeding_cut_at_each_count():
    """Count k's labels come from the first k centres of one greedy k-means++ run with the
    largest count's trials (the nearest seed, or Lloyd from those seeds), so they equal
    kmeans_plusplus of k centres with those trials; the scan is lazy and checks its counts."""
    import math

    from resireg.method.kmeans import nested_kmeans

    x = _mixture(n=800, d=6, k=5, seed=7)
    counts = [2, 3, 7]
    trials = 2 + int(math.log(counts[-1]))
    nearest = dict(nested_kmeans(x, counts, seed=4))
    lloyd = dict(nested_kmeans(x, counts, seed=4, max_iter=5))
    assert list(nearest) == counts
    for k in counts:
        seeds = kmeans_plusplus(x, k, torch.Generator().manual_seed(4), n_local_trials=trials)
        assert torch.equal(nearest[k], sq_distances(x, seeds).argmin(1))
        assert torch.equal(lloyd[k], _lloyd(x, seeds, 5, _tolerance(x, 1e-4)).labels)
    scan = nested_kmeans(x, counts, seed=4)
    assert next(scan)[0] == 2  # lazy: the later counts are not computed
    for bad in ([], [0, 2], [3, 2], [2, 2], [801]):
        with pytest.raises(ValueError, match="counts="):
            nested_kmeans(x, bad)
