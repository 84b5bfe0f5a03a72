import numpy as np
import pytest
import torch
from sklearn.cluster import KMeans
from sklearn.decomposition import PCA

from resireg.cluster import _lloyd, kmeans, pca, sq_distances


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
