"""The prototype count by the evidence lower bound: which of several counts fits the points best.

The one job of this module is ReSiReg Full's ``n_prototypes="elbo"`` (docs/method.md#the-prototype-count-by-the-evidence-lower-bound): :func:`elbo_prototype_count` fits, for each candidate count, a variational Bayesian
Gaussian mixture (:func:`vb_gmm`, scikit-learn's ``BayesianGaussianMixture`` with diagonal
covariances, in torch) started from k-means labels (:func:`resireg.method.kmeans.nested_kmeans`), on
a uniform subsample of the points (:func:`elbo_subsample`), and returns the count of the
largest bound. :func:`elbo_fits` returns the fits themselves (for reports and benchmarks).
"""

from __future__ import annotations

import math
from collections.abc import Sequence
from dataclasses import dataclass
from typing import Any

import torch
import torch.nn.functional as F
from torch import Tensor

from resireg.method.kmeans import nested_kmeans

__all__ = [
    "ELBO_MAX_POINTS",
    "VBGMMResult",
    "vb_gmm",
    "elbo_subsample",
    "elbo_fits",
    "elbo_prototype_count",
]


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
        labels: ``[N]`` initial component of every point (e.g. k-means labels,
            :func:`resireg.method.kmeans.kmeans`).
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
    generator = torch.Generator(device="cpu")
    generator.manual_seed(int(seed))
    return torch.randperm(n, generator=generator)[:max_points]


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
    :func:`elbo_prototype_count` (docs/method.md#the-prototype-count-by-the-evidence-lower-bound).

    For the candidates ``k`` in increasing order (all, or until ``stop_after`` ends the scan): a
    greedy k-means++ seeding (seed ``seed``), ``kmeans_iter`` Lloyd iterations from it (none by
    default: every point is labelled by its nearest seed), then :func:`vb_gmm` from those
    labels. The seedings are the first ``k`` centres of one greedy k-means++ run (``2 + ln(max
    candidate)`` trials per centre for every ``k``): each centre depends only on those before
    it, so one run seeds every candidate (:func:`resireg.method.kmeans.nested_kmeans`). Above
    ``max_points`` points the mixtures are fitted on a uniform subsample of ``M = max_points``
    (:func:`elbo_subsample`), each point standing for ``N / M`` (``vb_gmm``'s
    ``point_weight``), so that every :attr:`VBGMMResult.elbo` estimates the bound of all ``N``
    points. Unweighted, the subsample's bound would weigh the priors ``N / M`` times too
    heavily and favour too few prototypes.

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
    fits: dict[int, VBGMMResult] = {}
    best, below = -math.inf, 0
    for k, labels in nested_kmeans(x, counts, seed=seed, max_iter=kmeans_iter):
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
    bound (the smaller count on a tie; docs/method.md#the-prototype-count-by-the-evidence-lower-bound).

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
