"""The ELBO prototype-count chooser (resireg.method.elbo.vb_gmm / elbo_prototype_count) against
scikit-learn's BayesianGaussianMixture and the closed-form evidence of a conjugate model."""

from __future__ import annotations

import numpy as np
import pytest
import torch
from scipy import stats
from sklearn.mixture import BayesianGaussianMixture

from resireg.method.elbo import elbo_fits, elbo_prototype_count, elbo_subsample, vb_gmm
from resireg.method.kmeans import kmeans


def _blobs(n_clusters: int, dim: int, seed: int, per: int = 150, spread: float = 0.15):
    rng = np.random.default_rng(seed)
    centres = rng.normal(0.0, 4.0, size=(n_clusters, dim))
    x = np.concatenate([rng.normal(c, spread, size=(per, dim)) for c in centres])
    return x[rng.permutation(len(x))]


class _FromLabels(BayesianGaussianMixture):
    """scikit-learn's mixture started from given one-hot responsibilities (its kmeans init
    with our k-means' labels), so that both fits run the same EM."""

    def __init__(self, resp=None, **kwargs):
        super().__init__(**kwargs)
        self.resp = resp

    def _initialize_parameters(self, X, random_state, xp=None):
        self._initialize(X, self.resp)

    @classmethod
    def _get_param_names(cls):
        return sorted({"resp", *BayesianGaussianMixture._get_param_names()})


@pytest.mark.parametrize(
    "k,alpha,beta", [(2, None, 1.0), (4, None, 1.0), (6, 0.5, 0.1), (9, 2.0, 3.0)]
)
def test_lower_bound_matches_scikit_learn(k, alpha, beta):
    """Same data, same priors, same start: the bound after every EM run, the iteration count
    and the mixing weights agree with BayesianGaussianMixture(covariance_type="diag",
    weight_concentration_prior_type="dirichlet_distribution") to 1e-9 relative (float64 on
    both sides; the updates are the same formulas, only summation order differs)."""
    x_np = _blobs(5, 7, seed=k, spread=0.6)
    x = torch.tensor(x_np)
    labels = kmeans(x.float(), k, seed=0).labels
    resp = np.eye(k)[labels.numpy()]
    ref = _FromLabels(
        resp=resp, n_components=k, covariance_type="diag",
        weight_concentration_prior_type="dirichlet_distribution",
        weight_concentration_prior=alpha, mean_precision_prior=beta, tol=1e-3, max_iter=100,
    ).fit(x_np)  # fmt: skip
    ours = vb_gmm(x, labels, k, weight_concentration_prior=alpha, mean_precision_prior=beta)
    assert ours.n_iter == ref.n_iter_
    assert ours.converged == ref.converged_
    assert ours.lower_bound == pytest.approx(ref.lower_bound_, rel=1e-9)
    np.testing.assert_allclose(ours.weights.numpy(), ref.weights_, rtol=1e-5, atol=1e-7)
    np.testing.assert_allclose(ours.means.numpy(), ref.means_, rtol=1e-5, atol=1e-5)


@pytest.mark.parametrize("k,weight", [(4, 3), (6, 2)])
def test_point_weight_is_repetition(k, weight):
    """``point_weight=w`` is scikit-learn's fit of the data with every row repeated ``w``
    times (the same start repeated): bound, iterations, weights and means; and the whole
    bound equals the unweighted fit's on the repeated rows."""
    x_np = _blobs(5, 7, seed=k, spread=0.6)
    labels = kmeans(torch.tensor(x_np).float(), k, seed=0).labels
    rows, rep_labels = np.repeat(x_np, weight, axis=0), labels.repeat_interleave(weight)
    ref = _FromLabels(
        resp=np.eye(k)[rep_labels.numpy()], n_components=k, covariance_type="diag",
        weight_concentration_prior_type="dirichlet_distribution", tol=1e-3, max_iter=100,
    ).fit(rows)  # fmt: skip
    ours = vb_gmm(torch.tensor(x_np), labels, k, point_weight=weight)
    assert ours.n_iter == ref.n_iter_
    assert ours.lower_bound == pytest.approx(ref.lower_bound_, rel=1e-9)
    np.testing.assert_allclose(ours.weights.numpy(), ref.weights_, rtol=1e-5, atol=1e-7)
    np.testing.assert_allclose(ours.means.numpy(), ref.means_, rtol=1e-5, atol=1e-5)
    repeated = vb_gmm(torch.tensor(rows), rep_labels, k)
    assert ours.elbo == pytest.approx(repeated.elbo, rel=1e-9)
    with pytest.raises(ValueError, match="point_weight=0"):
        vb_gmm(torch.tensor(x_np), labels, k, point_weight=0)


def test_subsample_stands_for_the_whole_set():
    """24 noisy regions in 64 dimensions, 12,000 points, fitted on 768: weighted by N / M
    (what elbo_prototype_count does) the subsample's bound chooses the 24; unweighted (each
    of the 768 counted once, the priors as heavy as for all 12,000) it chooses too few."""
    gen = torch.Generator().manual_seed(0)
    codes = torch.randn(24, 64, generator=gen)
    region = torch.randint(24, (12_000,), generator=gen)
    x = torch.nn.functional.normalize(codes[region] + 0.5 * torch.randn(12_000, 64, generator=gen))
    candidates = [12, 24, 48]
    assert elbo_prototype_count(x, candidates, max_points=768) == 24
    sub = x[torch.randperm(12_000, generator=torch.Generator().manual_seed(0))[:768]]
    unweighted = {k: vb_gmm(sub, kmeans(sub, k, seed=0).labels, k).elbo for k in candidates}
    assert max(unweighted, key=unweighted.get) < 24


@pytest.mark.parametrize("seed", [0, 1])
def test_elbo_is_the_evidence_of_a_single_gaussian(seed):
    """With one component the variational posterior is exact, so the whole bound (the terms
    scikit-learn drops included) equals the log evidence of the conjugate Normal-Gamma model,
    computed independently as the chain of its Student-t predictive densities (scipy)."""
    rng = np.random.default_rng(seed)
    x = rng.normal(1.5, 0.7, size=(60, 1))
    fit = vb_gmm(torch.tensor(x), torch.zeros(60, dtype=torch.long), 1, reg_covar=0.0, tol=1e-12)
    # sklearn's defaults: mean_prior = mean, mean_precision 1, dof = r = 1, covariance = var
    m, beta, a, b = float(x.mean()), 1.0, 0.5, float(x.var(ddof=1)) / 2
    evidence = 0.0
    for xi in x[:, 0]:
        scale = np.sqrt(b * (beta + 1) / (a * beta))
        evidence += stats.t.logpdf(xi, df=2 * a, loc=m, scale=scale)
        b += beta * (xi - m) ** 2 / (2 * (beta + 1))
        m, beta, a = (beta * m + xi) / (beta + 1), beta + 1, a + 0.5
    assert fit.elbo == pytest.approx(evidence, rel=1e-10)


@pytest.mark.slow
@pytest.mark.parametrize("true", [3, 5, 8, 12])
@pytest.mark.parametrize("seed", [0, 1])
def test_chooses_the_number_of_separated_clusters(true, seed):
    """Well-separated clusters of known count: the count of the largest ELBO is that count,
    whatever the data's and the k-means' seeds."""
    x = torch.tensor(_blobs(true, 8, seed=100 * true + seed), dtype=torch.float32)
    candidates = [2, 3, 5, 8, 12, 16]
    assert elbo_prototype_count(x, candidates, seed=seed) == true


def test_subsample_and_bad_candidates():
    """Above max_points the bound is fitted on a seeded subsample (same answer on the whole
    set here); bad candidate lists name the value."""
    x = torch.tensor(_blobs(4, 6, seed=3, per=400), dtype=torch.float32)
    assert elbo_prototype_count(x, [2, 4, 6], max_points=500) == 4
    assert elbo_prototype_count(x, [2, 4, 6], max_points=10_000) == 4
    with pytest.raises(ValueError, match=r"candidates=\[0"):
        elbo_prototype_count(x, [0, 4])
    with pytest.raises(ValueError, match="exceed"):
        elbo_prototype_count(x[:10], [4, 20])
    with pytest.raises(ValueError, match="stop_after=0"):
        elbo_prototype_count(x, [2, 4], stop_after=0)
    with pytest.raises(ValueError, match="n_points=5000"):  # not the subsample's size
        elbo_prototype_count(x[:100], [2, 4], n_points=5000, max_points=500)


@pytest.mark.slow
@pytest.mark.parametrize("true,seed", [(3, 0), (5, 1), (8, 0), (12, 1)])
def test_scan_stops_on_the_full_scans_fits(true, seed):
    """The scan that stops after ``stop_after`` candidates below the best fits the first
    candidates of the full scan (``stop_after=None``), with the same bounds (one k-means++ run
    seeds every count, so a fit does not depend on where the scan stops), stops only after that
    many, and chooses the full scan's count: the known one here."""
    x = torch.tensor(_blobs(true, 8, seed=100 * true + seed), dtype=torch.float32)
    candidates = [2, 3, 5, 8, 12, 16, 20]
    full = elbo_fits(x, candidates, seed=seed)
    assert list(full) == candidates
    best_full = max(full.values(), key=lambda fit: fit.elbo).elbo
    assert min(k for k, fit in full.items() if fit.elbo == best_full) == true
    for stop in (1, 2):
        part = elbo_fits(x, candidates, seed=seed, stop_after=stop)
        fitted = list(part)
        assert fitted == candidates[: len(fitted)]
        assert all(part[k].elbo == full[k].elbo for k in fitted)
        best = max(fit.elbo for fit in part.values())
        if len(fitted) < len(candidates):
            assert all(part[k].elbo < best for k in fitted[-stop:])
    assert elbo_prototype_count(x, candidates, seed=seed) == true


def _scene(n_regions: int, seed: int) -> torch.Tensor:
    """``[2, 32, 12, 16]`` intermediates whose points carry one of ``n_regions`` features
    (plus small noise), region per point drawn at random."""
    gen = torch.Generator().manual_seed(seed)
    feats = torch.randn(n_regions, 32, generator=gen) * 3
    region = torch.randint(n_regions, (2, 12, 16), generator=gen)
    x = feats[region] + 0.05 * torch.randn(2, 12, 16, 32, generator=gen)
    return x.permute(0, 3, 1, 2).contiguous()


@pytest.mark.slow
@pytest.mark.parametrize("n_components", [None, 12])
def test_full_with_elbo_is_full_with_the_chosen_count(n_components):
    """ReSiRegFull(n_prototypes="elbo") chooses the scene's region count and then gives
    exactly what Full with that count gives; the counts of every batch are kept."""
    from resireg.method.full import ReSiRegFull

    x = _scene(5, seed=0)
    language = torch.randn(2, 16, 12, 16, generator=torch.Generator().manual_seed(1))
    elbo = ReSiRegFull(
        n_prototypes="elbo", elbo_candidates=[3, 5, 8, 12], n_components=n_components, upscale=1
    )
    out = elbo(x, language)
    assert elbo.chosen == [5]
    fixed = ReSiRegFull(n_prototypes=5, n_components=n_components, upscale=1)
    torch.testing.assert_close(out, fixed(x, language), rtol=0, atol=0)
    elbo(_scene(8, seed=2), language)
    assert elbo.chosen == [5, 8]
    assert elbo.check_grid(2, 12, 16) == 12  # the grid must hold the largest candidate
    with pytest.raises(ValueError, match="elbo_candidates"):
        ReSiRegFull(n_prototypes="elbo", elbo_candidates=None)
    # the Python default is conf/'s candidate set (conf/resireg/default.yaml)
    assert ReSiRegFull(n_prototypes="elbo").elbo_candidates == tuple(range(24, 133, 12))


@pytest.mark.parametrize("upscale,n_components", [(1, None), (2, None), (3, 6)])
def test_full_computes_only_the_subsample(upscale, n_components):
    """ReSiRegFull's chooser computes only the subsampled points, each from its four grid
    neighbours: they equal those rows of all upsampled points (F.interpolate's) to float
    rounding, and the count equals the chooser's given all the points."""
    from resireg.method.full import ReSiRegFull, upsampled_spectrum

    x = _scene(5, seed=3)
    full = ReSiRegFull(n_prototypes="elbo", elbo_candidates=[3, 5, 8], upscale=upscale,
                       n_components=n_components)  # fmt: skip
    spectrum = upsampled_spectrum(x, upscale)
    every = full._elbo_points(x, spectrum)
    rows = elbo_subsample(every.shape[0], 300, seed=0)
    assert rows is not None and every.shape[0] == 384 * upscale**2
    # grid_sample takes each tap's coordinate back from a normalised one in float32 (~1e-6 px off
    # F.interpolate's), hence a few 1e-6 here; a wrong tap or weight is off by ~0.1.
    torch.testing.assert_close(full._elbo_points(x, spectrum, rows), every[rows], rtol=0, atol=6e-6)
    small = ReSiRegFull(n_prototypes="elbo", elbo_candidates=[3, 5, 8], upscale=upscale,
                        n_components=n_components, elbo_max_points=300)  # fmt: skip
    chosen = small._elbo_count(x, spectrum)
    assert chosen == elbo_prototype_count(every, [3, 5, 8], max_points=300)
    assert small.chosen == [chosen]


def test_ablation_report_places_the_elbo_count_beside_the_heuristic(tmp_path):
    """The report's ELBO table reads, per batch size, the grid's best cell, the heuristic's
    n(B) and the grid's score there, and the elbo configuration's counts and score."""
    import math

    from resireg_train.report.jobs import Job
    from resireg_train.report.prototype_batch import elbo_table, fit_heuristic, prototype_grid

    metric = "val/ovss/synthetic/miou_full"
    variants = ["full@n_prototypes:4", "full@n_prototypes:8", "full@n_prototypes:elbo"]
    jobs = []
    for i, (batch, scores, counts) in enumerate(
        [(2, (0.3, 0.5, 0.45), {"4": 3, "8": 1}), (4, (0.6, 0.2, 0.55), {"8": 2})]
    ):
        final = {
            f"{metric}@n_prototypes:{n}": v for n, v in zip((4, 8, "elbo"), scores, strict=True)
        }
        results = {"status": "completed", "params": {"variants": variants}, "final": final,
                   "elbo_prototypes": {"full@n_prototypes:elbo": counts}}  # fmt: skip
        jobs.append(Job(tmp_path / str(i), i, {"batch_size": str(batch)}, results))
    grid = prototype_grid(jobs, metric)
    heuristic, best = fit_heuristic(grid)
    assert best == {2: 8, 4: 4}
    table = elbo_table(jobs, metric, grid, heuristic).set_index("batch_size")
    assert list(table["best n (grid)"]) == [8, 4]
    assert list(table["best mIoU (grid)"]) == [0.5, 0.6]
    assert list(table["ELBO n (x batches)"]) == ["4 x3, 8 x1", "8 x2"]
    assert list(table["ELBO mIoU"]) == [0.45, 0.55]
    for batch in (2, 4):
        n = heuristic(batch)
        expected = grid.loc[batch].get(n, math.nan)
        assert table.loc[batch, "heuristic n(B)"] == n
        assert table.loc[batch, "heuristic mIoU (grid)"] == pytest.approx(expected, nan_ok=True)


def test_full_passes_its_clustering_and_elbo_settings_on(monkeypatch):
    """``full.tol`` reaches k-means and ``full.elbo_max_points`` / ``elbo_stop_after`` /
    ``elbo_tol`` reach the chooser (conf/resireg/default.yaml's keys, not constants): each
    call is recorded and compared with the values given, and the subsample's size follows
    ``elbo_max_points``."""
    import resireg.method.full as full_module
    from resireg.method.full import ReSiRegFull

    seen: dict[str, dict] = {}
    for name in ("kmeans", "elbo_prototype_count"):
        original = getattr(full_module, name)

        def record(*args, _name=name, _original=original, **kwargs):
            seen[_name] = {"points": args[0].shape[0], **kwargs}
            return _original(*args, **kwargs)

        monkeypatch.setattr(full_module, name, record)
    x = _scene(5, seed=3)
    full = ReSiRegFull(n_prototypes="elbo", elbo_candidates=[3, 5, 8], tol=0.0,
                       elbo_max_points=200, elbo_stop_after=None, elbo_tol=0.5)  # fmt: skip
    full.assign(x)
    assert seen["kmeans"]["tol"] == 0.0
    choice = seen["elbo_prototype_count"]
    assert (choice["max_points"], choice["stop_after"], choice["tol"]) == (200, None, 0.5)
    assert choice["points"] == 200 < choice["n_points"]
