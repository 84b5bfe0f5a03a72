"""Calib (SC-CLIP's self-calibration) against scikit-learn's LOF and numpy references."""

import math
import warnings

import numpy as np
import pytest
import torch
import torch.nn.functional as F
from sklearn.neighbors import LocalOutlierFactor

from resireg.method.calib import Calib, lof_outliers, negative_outlier_factor, resolve_anomalies
from resireg.method.variants import VARIANTS, build_variant


def _sklearn_lof(points, n_neighbors=30, contamination=0.05):
    """(outlier mask, negative_outlier_factor_) of scikit-learn on ``[N, D]`` numpy points."""
    lof = LocalOutlierFactor(n_neighbors=n_neighbors, contamination=contamination)
    with warnings.catch_warnings():
        warnings.simplefilter("ignore")  # its n_neighbors > n_samples warning
        pred = lof.fit_predict(points)
    return pred == -1, lof.negative_outlier_factor_


def _grid_scene(b=1, h=10, w=12, dv=16, dl=8, seed=0):
    """Intermediates with a smooth structure plus noise, random language tokens."""
    g = torch.Generator().manual_seed(seed)
    coarse = torch.randn(b, dv, 3, 3, generator=g, dtype=torch.float64)
    smooth = F.interpolate(coarse, size=(h, w), mode="bilinear", align_corners=False)
    inter = 3 * smooth + 0.3 * torch.randn(b, dv, h, w, generator=g, dtype=torch.float64)
    lang = torch.randn(b, dl, h, w, generator=g, dtype=torch.float64)
    return inter, lang


def _np_resolve(x, mask):
    """Plain-loop 3 x 3 inlier-neighbour mean of ``x`` ``[C, H, W]`` at ``mask`` ``[H, W]``."""
    out = x.copy()
    _, h, w = x.shape
    for i, j in zip(*np.nonzero(mask), strict=True):
        nb = [
            x[:, i + di, j + dj]
            for di in (-1, 0, 1)
            for dj in (-1, 0, 1)
            if (di, dj) != (0, 0)
            and 0 <= i + di < h
            and 0 <= j + dj < w
            and not mask[i + di, j + dj]
        ]
        if nb:
            out[:, i, j] = np.mean(nb, axis=0)
    return out


def _np_aggregate(inter, lang, threshold):
    """numpy Calib aggregation of one image: ``[Dv, H, W]``, ``[Dl, H, W]`` -> ``[Dl, H, W]``."""
    dv, h, w = inter.shape
    fv = inter.reshape(dv, -1).T
    fv = fv / np.linalg.norm(fv, axis=1, keepdims=True)
    a = fv @ fv.T
    a[a < threshold] = 0.0
    a = a / a.sum(axis=1, keepdims=True)
    out = a @ lang.reshape(lang.shape[0], -1).T
    out = out / np.linalg.norm(out, axis=1, keepdims=True)
    return out.T.reshape(-1, h, w)


def _np_calib(inter, lang, n_neighbors=30, contamination=0.05, threshold=0.4):
    """Whole Calib of one image from scikit-learn's outliers and the numpy references."""
    dv, h, w = inter.shape
    mask, _ = _sklearn_lof(inter.reshape(dv, -1).T, n_neighbors, contamination)
    mask = mask.reshape(h, w)
    return _np_aggregate(_np_resolve(inter, mask), _np_resolve(lang, mask), threshold), mask


@pytest.mark.parametrize(
    ("seed", "n", "d", "k", "c"),
    [
        (0, 200, 24, 30, 0.05),
        (1, 300, 7, 30, 0.05),  # low dimension: scikit-learn's tree search
        (2, 150, 64, 30, 0.05),
        (3, 41, 16, 30, 0.05),  # (N - 1) c = 2 exactly: the offset is a score itself
        (4, 120, 12, 10, 0.12),
        (5, 20, 8, 30, 0.05),  # N < k + 1: k clipped to N - 1
    ],
)
def test_lof_matches_sklearn(seed, n, d, k, c):
    rng = np.random.default_rng(seed)
    x = rng.standard_normal((n, d)) * rng.uniform(0.5, 2.0, size=(n, 1))  # varied densities
    ref_mask, ref_nof = _sklearn_lof(x, k, c)
    with warnings.catch_warnings(record=True) as caught:
        warnings.simplefilter("always")
        nof = negative_outlier_factor(torch.from_numpy(x)[None], k)[0].numpy()
        mask = lof_outliers(torch.from_numpy(x)[None], k, c)[0].numpy()
    assert any("n_neighbors" in str(w.message) for w in caught) == (n - 1 < k)
    np.testing.assert_allclose(nof, ref_nof, rtol=1e-10, atol=0)
    np.testing.assert_array_equal(mask, ref_mask)
    assert mask.sum() == math.ceil((n - 1) * c)  # distinct scores


@pytest.mark.parametrize("seed", [0, 1, 2, 3])
def test_module_outliers_match_sklearn_float32(seed):
    """The module's own path (float32, grid layout, a batch) flags sklearn's outliers."""
    inter, _ = _grid_scene(b=2, h=12, w=14, dv=32, seed=seed)
    inter = inter.float()
    flagged = Calib().outliers(inter)
    for i in range(2):
        pts = inter[i].reshape(32, -1).T.double().numpy()
        ref, _ = _sklearn_lof(pts)
        np.testing.assert_array_equal(flagged[i].reshape(-1).numpy(), ref)


def test_planted_outliers_found_like_sklearn():
    inter, _ = _grid_scene(h=12, w=12, dv=20, seed=7)
    planted = [(0, 0), (3, 7), (6, 6), (11, 5), (8, 11)]
    g = torch.Generator().manual_seed(1)
    for i, j in planted:
        inter[0, :, i, j] += 15 * torch.randn(20, generator=g, dtype=torch.float64)
    pts = inter[0].reshape(20, -1).T.numpy()
    ref, ref_nof = _sklearn_lof(pts)
    mask = lof_outliers(inter[0].reshape(20, -1).T[None])[0]
    np.testing.assert_array_equal(mask.numpy(), ref)
    np.testing.assert_allclose(
        negative_outlier_factor(inter[0].reshape(20, -1).T[None])[0], ref_nof, rtol=1e-10
    )
    flagged = Calib().outliers(inter)[0]
    assert all(bool(flagged[i, j]) for i, j in planted)
    assert int(flagged.sum()) == math.ceil((144 - 1) * 0.05)


def test_planted_anomaly_is_resolved_in_both_maps():
    inter, lang = _grid_scene(h=9, w=11, dv=16, dl=8, seed=3)
    spots = [(4, 5), (0, 0), (8, 10)]  # interior, two corners
    for i, j in spots:
        inter[0, :, i, j] = 1e3  # huge-norm token
        lang[0, :, i, j] = 50.0  # a distinct language token there
    calib = Calib()
    fv, tokens, mask = calib.resolve(inter, lang)
    ref_mask, _ = _sklearn_lof(inter[0].reshape(16, -1).T.numpy())
    np.testing.assert_array_equal(mask[0].reshape(-1).numpy(), ref_mask)
    m = mask[0].numpy()
    for i, j in spots:
        assert m[i, j]
        for x, y in ((inter, fv), (lang, tokens)):
            c = x.shape[1]
            nb = [
                x[0, :, a, b].numpy()
                for a in range(max(i - 1, 0), min(i + 2, x.shape[2]))
                for b in range(max(j - 1, 0), min(j + 2, x.shape[3]))
                if (a, b) != (i, j) and not m[a, b]
            ]
            assert nb
            np.testing.assert_allclose(y[0, :, i, j].numpy(), np.mean(nb, axis=0), rtol=1e-12)
            assert y[0, :, i, j].abs().max() < 10 and c == y.shape[1]
    # every map equals the plain-loop reference everywhere (untouched where not anomalous)
    np.testing.assert_allclose(fv[0].numpy(), _np_resolve(inter[0].numpy(), m), rtol=1e-12)
    np.testing.assert_allclose(tokens[0].numpy(), _np_resolve(lang[0].numpy(), m), rtol=1e-12)


def test_resolve_keeps_token_without_inlier_neighbour():
    x = torch.arange(2 * 3 * 5 * 5, dtype=torch.float64).reshape(1, 6, 5, 5) ** 1.5
    mask = torch.zeros(1, 5, 5, dtype=torch.bool)
    mask[0, 1:4, 1:4] = True  # the centre (2, 2) has only anomalous neighbours
    mask[0, 4, 4] = True
    out = resolve_anomalies(x, mask)
    np.testing.assert_allclose(out[0].numpy(), _np_resolve(x[0].numpy(), mask[0].numpy()))
    assert torch.equal(out[0, :, 2, 2], x[0, :, 2, 2])
    assert not torch.equal(out[0, :, 1, 1], x[0, :, 1, 1])
    with pytest.raises(ValueError, match="anomalous"):
        resolve_anomalies(x, mask.float())


@pytest.mark.parametrize("threshold", [0.4, 0.0, 0.7])
def test_aggregation_matches_numpy(threshold):
    g = torch.Generator().manual_seed(5)
    # low-dimensional intermediates with a shared component: cosines spread over [-1, 1]
    inter = torch.randn(1, 4, 7, 8, generator=g, dtype=torch.float64) + 0.5
    lang = torch.randn(1, 6, 7, 8, generator=g, dtype=torch.float64)
    calib = Calib(contamination=0.0, threshold=threshold)
    out = calib(inter, lang)
    assert out.shape == (1, 6, 7, 8) and out.dtype == torch.float32
    ref = _np_aggregate(inter[0].numpy(), lang[0].numpy(), threshold)
    np.testing.assert_allclose(out[0].numpy(), ref, atol=1e-6)
    np.testing.assert_allclose(out.norm(dim=1).numpy(), 1.0, atol=1e-6)
    fv = F.normalize(inter[0].reshape(4, -1), dim=0)
    kept = ((fv.T @ fv) >= 0.4).double().mean()
    assert 0.2 < kept < 0.8  # the default threshold really cuts


@pytest.mark.parametrize("seed", [0, 1])
def test_full_calib_matches_numpy(seed):
    inter, lang = _grid_scene(b=1, h=12, w=12, dv=12, dl=10, seed=seed)
    inter[0, :, 5, 5] += 30.0
    out = Calib()(inter.float(), lang.float())
    ref, mask = _np_calib(inter[0].float().double().numpy(), lang[0].float().double().numpy())
    assert mask.sum() == 8
    assert out.shape == (1, 10, 12, 12) and out.dtype == torch.float32
    np.testing.assert_allclose(out[0].numpy(), ref, atol=2e-5)
    np.testing.assert_allclose(out.norm(dim=1).numpy(), 1.0, atol=1e-5)


def test_language_on_another_grid_is_resized_bilinearly():
    inter, _ = _grid_scene(b=2, h=10, w=12, dv=16, seed=4)
    lang = torch.randn(2, 8, 5, 6, dtype=torch.float64)
    out = Calib()(inter, lang)
    assert out.shape == (2, 8, 10, 12)
    up = F.interpolate(lang, size=(10, 12), mode="bilinear", align_corners=False)
    for i in range(2):
        ref, _ = _np_calib(inter[i].numpy(), up[i].numpy())
        np.testing.assert_allclose(out[i].numpy(), ref, atol=1e-6)


def test_batched_equals_per_image():
    inter, lang = _grid_scene(b=3, h=9, w=10, dv=24, dl=16, seed=9)
    inter, lang = inter.float(), lang.float()
    inter[1] *= 5.0  # images of different scales never interact
    calib = Calib()
    batched = calib(inter, lang)
    single = torch.cat([calib(inter[i : i + 1], lang[i : i + 1]) for i in range(3)])
    torch.testing.assert_close(batched, single, atol=1e-6, rtol=1e-5)
    shuffled = calib(inter[[2, 0, 1]], lang[[2, 0, 1]])
    torch.testing.assert_close(shuffled, batched[[2, 0, 1]], atol=1e-6, rtol=1e-5)


def test_registered_variant():
    assert VARIANTS == ("bb", "calib", "lite", "full")
    inter, lang = _grid_scene(b=2, h=8, w=8, dv=16, seed=2)
    v = build_variant("calib", threshold=0.5, n_neighbors=12)
    assert isinstance(v, Calib)
    assert (v.threshold, v.n_neighbors, v.contamination) == (0.5, 12, 0.05)
    prior = torch.ones(2, 8, 8, dtype=torch.long)
    expected = Calib(n_neighbors=12, threshold=0.5)(inter, lang)
    torch.testing.assert_close(v(inter, lang, prior), expected)  # prior ignored
    assert not torch.allclose(build_variant("calib")(inter, lang), expected)


@pytest.mark.parametrize(
    ("kwargs", "name"),
    [
        ({"n_neighbors": 0}, "n_neighbors"),
        ({"n_neighbors": 2.5}, "n_neighbors"),
        ({"n_neighbors": True}, "n_neighbors"),
        ({"contamination": -0.01}, "contamination"),
        ({"contamination": 0.6}, "contamination"),
        ({"contamination": float("nan")}, "contamination"),
        ({"threshold": 1.5}, "threshold"),
        ({"threshold": -0.1}, "threshold"),
        ({"threshold": float("nan")}, "threshold"),
        ({"threshold": "0.4"}, "threshold"),
    ],
)
def test_bad_parameters_raise(kwargs, name):
    with pytest.raises(ValueError, match=name):
        Calib(**kwargs)
    with pytest.raises(ValueError, match=name):
        build_variant("calib", **kwargs)


def test_bad_inputs_raise():
    calib = Calib()
    with pytest.raises(ValueError, match="intermediates"):
        calib(torch.randn(8, 4, 4), torch.randn(1, 8, 4, 4))
    with pytest.raises(ValueError, match="batch size"):
        calib(torch.randn(2, 8, 4, 4), torch.randn(1, 8, 4, 4))
    with pytest.raises(ValueError, match="points"):
        negative_outlier_factor(torch.randn(5, 3))


def test_small_grids_and_degenerate_rows():
    calib = Calib()
    lang = torch.randn(1, 6, 1, 1)
    out = calib(torch.randn(1, 4, 1, 1), lang)  # one token: no LOF, itself
    torch.testing.assert_close(out, F.normalize(lang, dim=1))
    with pytest.warns(UserWarning, match="n_neighbors=30"):
        out = calib(torch.randn(1, 4, 3, 3), torch.randn(1, 6, 3, 3))
    assert out.shape == (1, 6, 3, 3)
    # a zero intermediate token has no affinity >= threshold: it keeps its own token
    inter, lang = _grid_scene(h=6, w=6, dv=8, seed=1)
    inter[0, :, 2, 3] = 0.0
    out = Calib(contamination=0.0)(inter, lang)
    torch.testing.assert_close(out[0, :, 2, 3], F.normalize(lang[0, :, 2, 3].float(), dim=0))
    assert torch.isfinite(out).all()


def test_autocast_bf16_inputs_give_float32():
    inter, lang = _grid_scene(b=2, h=8, w=9, dv=16, seed=6)
    inter, lang = inter.float(), lang.float()
    ref = Calib()(inter, lang)
    with torch.autocast("cpu", dtype=torch.bfloat16):
        out = Calib()(inter, lang)
    torch.testing.assert_close(out, ref)
    half = Calib()(inter.bfloat16(), lang.bfloat16())
    assert half.dtype == torch.float32 and half.shape == (2, 8, 8, 9)


def test_affinity_equal_to_threshold_is_kept():
    # cos((1, 0), (3, 4)) = 3/5 is exact in float32: only entries *below* it are zeroed
    inter = torch.tensor([[1.0, 3.0], [0.0, 4.0]]).reshape(1, 2, 1, 2)
    lang = torch.tensor([[1.0, 0.0], [0.0, 1.0]]).reshape(1, 2, 1, 2)
    out = Calib(contamination=0.0, threshold=0.6)(inter, lang)
    expected = F.normalize(torch.tensor([[1.0, 0.6], [0.6, 1.0]]), dim=1).T.reshape(1, 2, 1, 2)
    torch.testing.assert_close(out, expected)
