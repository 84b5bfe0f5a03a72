"""ReSiReg Full: parameter-free reconstruction of dense language features by prototypes.

Notation (docs/method.md#resireg): intermediates ``F_v`` ``[B, Dv, Hv, Wv]`` carry the
backbone's spatial structure, language tokens ``F_vl`` ``[B, Dl, Hl, Wl]`` carry the
language-aligned (but spatially noisy) features, and an optional segmentation prior
``S`` ``[B, H', W']`` holds instance ids (0 = none). The module returns
``[B, Dl, Hv*s, Wv*s]`` features of unit L2 norm over ``Dl``.

The module reads top to bottom: the PCA of ReSiReg Full's upsampled points, computed from the
small grid (:func:`upsampled_moments`); then :class:`ReSiRegFull`, whose ``forward`` (first
among its steps) runs:

1. the input check, :func:`resireg.method.checks.check_variant_inputs`;
2. the covariance spectrum of the bilinearly upsampled intermediates, from the grid
   (:meth:`FullShared.spectrum`, :func:`upsampled_spectrum`, :class:`resireg.method.pca.PCASpectrum`);
3. :meth:`ReSiRegFull.assign`: with ``n_prototypes="elbo"`` the count
   (:meth:`ReSiRegFull._elbo_count`: the subsample of :func:`resireg.method.elbo.elbo_subsample`,
   only its points computed, then :func:`resireg.method.elbo.elbo_prototype_count`); the projection
   on the grid, its upsampling and normalisation; :func:`resireg.method.kmeans.kmeans` of the
   points (its products with the points taken on the grid);
4. the prototypes (the mean language token of every cluster, and one per prior instance),
   the softmax of the distances to them and the mix.

The grid helpers it shares with ReSiReg Lite (:mod:`resireg.method.lite`) are in
:mod:`resireg.method.grid`. The clustering modules (:mod:`resireg.method.pca`,
:mod:`resireg.method.kmeans`, :mod:`resireg.method.elbo`) know nothing of this one; it calls them.
"""

from __future__ import annotations

from collections.abc import Callable, Sequence

import torch
import torch.nn.functional as F
from torch import Tensor, nn

from resireg.method.checks import check_positive_int, check_variant_inputs
from resireg.method.elbo import ELBO_MAX_POINTS, elbo_prototype_count, elbo_subsample
from resireg.method.grid import (
    Instances,
    masked_mean_normalised,
    nearest,
    normalise_,
    to_points,
    upsample,
)
from resireg.method.kmeans import kmeans
from resireg.method.pca import PCAResult, PCASpectrum, gram
from resireg.specs.variants import check_variant_kwargs

__all__ = [
    "FullShared",
    "ReSiRegFull",
    "upsampled_moments",
    "upsampled_pca",
    "upsampled_spectrum",
]


# ------------------------------------------------ the PCA of the upsampled points, from the grid
def _linear_interp_matrix(size: int, scale: int, device: torch.device) -> Tensor:
    """``[size*scale, size]`` matrix of 1-D linear upsampling as ``F.interpolate`` does it."""
    eye = torch.eye(size, device=device).unsqueeze(0)  # channel i holds the unit impulse e_i
    return F.interpolate(eye, scale_factor=scale, mode="linear", align_corners=False)[0].T


# Points per chunk of the moment and projection passes. Chunks hold whole images (the
# bilinear factor couples neighbouring rows and columns of an image); their temporaries are
# allocated once and stay in cache instead of being batch-sized fresh allocations.
_CHUNK_POINTS = 4096


def _image_chunks(b: int, h: int, w: int) -> list[tuple[int, int]]:
    """``(start, stop)`` image ranges of about ``_CHUNK_POINTS`` grid points (>= 1 image)."""
    per = max(1, _CHUNK_POINTS // max(1, h * w))
    return [(i, min(b, i + per)) for i in range(0, b, per)]


def _linear_gram_factor(size: int, scale: int, like: Tensor) -> tuple[Tensor, Tensor, Tensor]:
    """Cholesky factor of ``U^T U`` for the 1-D linear upsampling ``U`` of ``size`` samples.

    Every upsampled sample interpolates two neighbouring inputs, so ``U^T U`` is tridiagonal
    (and positive definite) and its Cholesky factor ``L`` is lower bidiagonal. Returns its
    diagonal ``[size]``, its subdiagonal ``[size - 1]`` (``L[i + 1, i]``) and ``U^T 1``
    ``[size]``, in ``like``'s dtype and device.
    """
    u = _linear_interp_matrix(size, scale, like.device)
    low = torch.linalg.cholesky((u.T @ u).double())
    return (
        low.diagonal().to(like.dtype),
        low.diagonal(-1).to(like.dtype),
        u.sum(0).to(like.dtype),
    )


def _apply_factor(t: Tensor, diag: Tensor, sub: Tensor, dim: int, out: Tensor) -> Tensor:
    """``L^T`` of a lower bidiagonal ``L`` applied along ``dim`` of ``t``, into ``out``:
    ``out_a = L[a, a] t_a + L[a + 1, a] t_(a + 1)`` (two vectorised passes)."""
    shape = [1] * t.ndim
    shape[dim] = -1
    torch.mul(t, diag.view(shape), out=out)
    size = t.shape[dim]
    if size > 1:
        out.narrow(dim, 0, size - 1).addcmul_(t.narrow(dim, 1, size - 1), sub.view(shape))
    return out


def upsampled_moments(x: Tensor, scale: int) -> tuple[Tensor, Tensor, int, Tensor]:
    """Moments of the bilinearly upsampled points of ``x`` ``[B, D, h, w]``, from the grid.

    Returns ``(second, first, n, shift)`` as :func:`resireg.method.pca.pca_from_moments` takes
    them: ``shift`` is the grid's mean, ``second = sum_p (u_p - shift)(u_p - shift)^T`` and
    ``first = sum_p (u_p - shift)`` over the ``n = B h w s^2`` upsampled points ``u_p``.

    Bilinear upsampling is a linear map ``U`` that is separable (``U = U_h (x) U_w``) with
    rows summing to one, so ``second = X^T (U^T U) X`` and ``first = (U^T 1)^T X`` for the
    centred grid points ``X``. Each ``U_a^T U_a`` is tridiagonal with a lower bidiagonal
    Cholesky factor ``L_a``, hence ``second = Y^T Y`` with ``Y = (L_h^T (x) L_w^T) X``: four
    vectorised passes for ``Y`` and a symmetric product (:func:`resireg.method.pca.gram`),
    accumulated over chunks of images so no batch-sized temporary is formed.
    """
    b, d, h, w = x.shape
    pts = x.permute(0, 2, 3, 1)  # [B, h, w, D]; a plain view for channels-last maps
    shift = pts.mean(dim=(0, 1, 2), dtype=torch.float32)  # centring avoids cancellation
    chunks = _image_chunks(b, h, w)
    size = (chunks[0][1], h, w, d)
    centred = torch.empty(size, dtype=shift.dtype, device=x.device)
    total = torch.zeros(size[1:], dtype=shift.dtype, device=x.device)  # sum over images
    second = torch.zeros(d, d, dtype=shift.dtype, device=x.device)
    if scale > 1:
        dh, sub_h, wh = _linear_gram_factor(h, scale, centred)
        dw, sub_w, ww = _linear_gram_factor(w, scale, centred)
        half, factored = torch.empty_like(centred), torch.empty_like(centred)
    for start, stop in chunks:
        m = stop - start
        c = torch.sub(pts[start:stop], shift, out=centred[:m])
        total += c.sum(0)
        if scale > 1:
            c = _apply_factor(c, dh, sub_h, 1, out=half[:m])
            c = _apply_factor(c, dw, sub_w, 2, out=factored[:m])
        gram(c.reshape(-1, d), out=second)
    if scale > 1:
        first = torch.outer(wh, ww).reshape(h * w) @ total.reshape(h * w, d)
    else:
        first = total.sum(dim=(0, 1))
    return second, first, b * h * w * scale * scale, shift


def upsampled_pca(x: Tensor, scale: int, n_components: int) -> PCAResult:
    """Exact PCA of the bilinearly upsampled points of ``x`` ``[B, D, h, w]``, cheaply.

    Upsampling by ``s`` multiplies the point count by ``s^2`` (55k points of dimension
    384 for a batch of 8 at 36 x 48 and s = 2) and the ``N x D x D`` covariance product
    dominated ReSiReg Full's run time. The moments of the upsampled points follow from the
    small grid (:func:`upsampled_moments`), so this is the same PCA, ``s^2`` times cheaper;
    the projection likewise commutes with upsampling (``upsample(X) W = upsample(X W)``).
    """
    return upsampled_spectrum(x, scale).top(n_components)


def upsampled_spectrum(x: Tensor, scale: int) -> PCASpectrum:
    """The covariance eigendecomposition behind :func:`upsampled_pca` (any component count
    is then a slice: :meth:`~resireg.method.pca.PCASpectrum.top`)."""
    second, first, n, shift = upsampled_moments(x, scale)
    return PCASpectrum.from_moments(second, first, n, shift=shift)


def _project_grid(x: Tensor, fit: PCAResult) -> Tensor:
    """``(x_p - mean) W^T`` for the grid points of ``x`` ``[B, D, h, w]`` -> ``[B*h*w, r]``
    (row-major over batch, then space), in chunks of images."""
    b, d, h, w = x.shape
    pts = x.permute(0, 2, 3, 1)
    chunks = _image_chunks(b, h, w)
    centred = torch.empty((chunks[0][1], h, w, d), dtype=fit.mean.dtype, device=x.device)
    comps_t = fit.components.T
    out = torch.empty(b * h * w, comps_t.shape[1], dtype=fit.mean.dtype, device=x.device)
    for start, stop in chunks:
        c = torch.sub(pts[start:stop], fit.mean, out=centred[: stop - start])
        torch.mm(c.reshape(-1, d), comps_t, out=out[start * h * w : stop * h * w])
    return out


# ------------------------------------------------------------------------------------------- Full
class FullShared:
    """What every ReSiReg Full configuration computes identically for one batch: the
    covariance spectrum of the upsampled intermediates (each configuration slices its own
    component count from it) and the language tokens at the mask grid.

    The evaluation scores many configurations (``full@n_prototypes:24``, ``:36``, ...) on one
    encoded batch; passing one ``FullShared`` to each (``full(..., shared=s)``) computes
    these once. Each result equals the configuration run alone (the same operations on the
    same inputs). Built lazily; tied to the ``intermediates`` and ``language`` tensors it was
    made for and to one ``upscale``.
    """

    def __init__(self, intermediates: Tensor, language: Tensor, upscale: int) -> None:
        self.intermediates, self.language, self.upscale = intermediates, language, upscale
        self._spectrum: PCASpectrum | None = None
        self._tokens: Tensor | None = None

    def check(self, intermediates: Tensor, language: Tensor, upscale: int) -> None:
        if intermediates is not self.intermediates or language is not self.language:
            raise ValueError("shared= was built for other intermediates/language tensors")
        if upscale != self.upscale:
            raise ValueError(f"shared= was built for upscale={self.upscale}, not {upscale}")

    def spectrum(self) -> PCASpectrum:
        if self._spectrum is None:
            self._spectrum = upsampled_spectrum(self.intermediates.float(), self.upscale)
        return self._spectrum

    def tokens(self, size: tuple[int, int]) -> Tensor:
        """``[N, Dl]`` language tokens nearest-resized to the mask grid ``size``."""
        if self._tokens is None:
            self._tokens = to_points(nearest(self.language.float(), size))
        return self._tokens


class ReSiRegFull(nn.Module):
    """ReSiReg Full: cluster intermediates into prototypes, ground them in language, mix.

    The whole batch is one scene: PCA and k-means run on the points of all images
    together, so prototypes are shared across the batch (batch size is a hyperparameter).

    Args:
        n_prototypes: k-means clusters ``n``, or ``"auto"`` to take it from a fitted
            prototype heuristic as a function of the batch size (see ``heuristic``), or
            ``"elbo"`` to choose it per batch among ``elbo_candidates`` by the evidence lower
            bound (:func:`resireg.method.elbo.elbo_prototype_count`, docs/method.md#the-prototype-count-by-the-evidence-lower-bound).
        n_components: PCA components ``r``; ``None`` (default): equal to the prototype
            count of the batch (tied, as in the paper's ablation and ``full.n_components:
            null`` of conf/resireg/default.yaml). Clipped to the intermediate dimension.
        alpha: softmax temperature on prototype distances.
        tau: gate; affinities below ``tau`` are zeroed (no renormalisation).
        upscale: integer bilinear upsampling factor ``s`` of the intermediates.
        seed: seed of k-means++ (the same input always gives the same output).
        max_iter: Lloyd iterations at most.
        tol: Lloyd stops once no centroid moves by more than ``tol`` times the points' mean
            per-feature variance (scikit-learn's relative ``tol`` of ``KMeans``, whose default
            it is).
        heuristic: with ``n_prototypes="auto"``, a callable ``batch_size -> n`` (e.g.
            :class:`resireg.method.heuristic.PrototypeHeuristic`) or a path to its JSON file;
            ``None`` reads the file named by ``$RESIREG_PROTOTYPE_HEURISTIC``.
        elbo_candidates: with ``n_prototypes="elbo"``, the counts to choose from. The bound
            is fitted on the normalised PCA points of ``n_components`` axes (tied: of as many
            axes as the largest candidate); Full then runs with the chosen count (tied: on
            that many axes). :attr:`chosen` lists the count of every batch.
        elbo_max_points: with ``"elbo"``, the bound is fitted on a uniform subsample of at
            most this many points (:func:`resireg.method.elbo.elbo_subsample`), each standing for
            ``N / M`` of the batch's ``N``.
        elbo_stop_after: with ``"elbo"``, the scan of the candidates (in increasing order)
            stops once this many consecutive ones fall below the largest bound so far;
            ``None`` fits them all (:func:`resireg.method.elbo.elbo_prototype_count`).
        elbo_tol: with ``"elbo"``, EM stops once the bound changes by less than this many
            nats per point (:func:`resireg.method.elbo.elbo_fits`).
    """

    def __init__(
        self,
        n_prototypes: int | str = 36,
        n_components: int | None = None,
        alpha: float = 5.0,
        tau: float = 0.0,
        upscale: int = 2,
        seed: int = 0,
        max_iter: int = 100,
        tol: float = 1e-4,
        heuristic: Callable[[int], int] | str | None = None,
        elbo_candidates: Sequence[int] | None = (24, 36, 48, 60, 72, 84, 96, 108, 120, 132),
        elbo_max_points: int = ELBO_MAX_POINTS,
        elbo_stop_after: int | None = 2,
        elbo_tol: float = 1e-3,
    ) -> None:
        super().__init__()
        # the rules of resireg.specs.variants (also those of the full.* config checks)
        check_variant_kwargs("full", {
            "n_prototypes": n_prototypes, "n_components": n_components, "alpha": alpha,
            "tau": tau, "upscale": upscale, "seed": seed, "max_iter": max_iter, "tol": tol,
            "heuristic": heuristic, "elbo_candidates": elbo_candidates,
            "elbo_max_points": elbo_max_points, "elbo_stop_after": elbo_stop_after,
            "elbo_tol": elbo_tol,
        })  # fmt: skip
        self.heuristic: Callable[[int], int] | None = None
        self.elbo_candidates: tuple[int, ...] | None = None
        #: with ``n_prototypes="elbo"``: the count chosen for every batch run, in order
        self.chosen: list[int] = []
        if n_prototypes == "elbo":
            if not elbo_candidates:
                raise ValueError(
                    f"n_prototypes='elbo' needs elbo_candidates (counts to choose from), "
                    f"got elbo_candidates={elbo_candidates!r}"
                )
            self.elbo_candidates = tuple(
                sorted({check_positive_int("elbo_candidates", c) for c in elbo_candidates})
            )
        elif n_prototypes == "auto":
            from resireg.method.heuristic import PrototypeHeuristic

            self.heuristic = PrototypeHeuristic.resolve(heuristic)
        self.n_prototypes = n_prototypes
        self.n_components = n_components
        self.alpha, self.tau = float(alpha), float(tau)
        self.upscale = upscale
        self.seed = seed
        self.max_iter = max_iter
        self.tol = float(tol)
        self.elbo_max_points = elbo_max_points
        self.elbo_stop_after = elbo_stop_after
        self.elbo_tol = float(elbo_tol)

    def extra_repr(self) -> str:
        return (
            f"n_prototypes={self.n_prototypes}, n_components={self.n_components}, "
            f"alpha={self.alpha}, tau={self.tau}, upscale={self.upscale}, seed={self.seed}"
        )

    def resolve_prototypes(self, batch_size: int) -> int:
        """Prototype count used for a batch of ``batch_size`` images."""
        if self.elbo_candidates is not None:  # the most "elbo" can choose
            return self.elbo_candidates[-1]
        if self.heuristic is not None:
            return check_positive_int(
                "n_prototypes (from heuristic)", int(self.heuristic(batch_size))
            )
        return int(self.n_prototypes)

    def check_grid(self, batch_size: int, height: int, width: int) -> int:
        """The prototype count for a batch of ``batch_size`` intermediates grids of
        ``height x width``; a ValueError if it exceeds the batch's upsampled points."""
        s = self.upscale
        n_points = batch_size * height * s * width * s
        n = self.resolve_prototypes(batch_size)
        if n > n_points:
            raise ValueError(
                f"n_prototypes={n} exceeds the number of points N={n_points} (B*Hv*s*Wv*s for "
                f"B={batch_size} intermediates of {height} x {width}, upscale={s})"
            )
        return n

    @torch.no_grad()
    def forward(
        self,
        intermediates: Tensor,
        language: Tensor,
        prior: Tensor | None = None,
        shared: FullShared | None = None,
    ) -> Tensor:
        """Reconstruct language features.

        ReSiReg has no parameters and its clustering (k-means' assignments) has no useful
        gradient, so it runs under :func:`torch.no_grad`: inputs that require grad are
        accepted and the result does not require grad (Lite and Calib alike).

        Args:
            intermediates: ``[B, Dv, Hv, Wv]`` backbone features used for clustering.
            language: ``[B, Dl, Hl, Wl]`` language-aligned patch tokens.
            prior: optional ``[B, H', W']`` integer instance ids (0 = none).
            shared: work shared with other configurations of this batch (:class:`FullShared`
                of these two tensors and this ``upscale``); ``None`` computes it here.

        Returns:
            ``[B, Dl, Hv*s, Wv*s]``, unit L2 norm over ``Dl``, in ``language.dtype``.

        Raises:
            TypeError: ``intermediates`` or ``language`` is not a floating-point tensor.
            ValueError: a shape is wrong or has an empty dimension, or the features hold NaN
                or inf (:class:`resireg.method.checks.NonFiniteError`); the message names the
                argument.
        """
        check_variant_inputs(intermediates, language, prior)
        if shared is None:
            shared = FullShared(intermediates, language, self.upscale)
        shared.check(intermediates, language, self.upscale)
        with torch.autocast(device_type=intermediates.device.type, enabled=False):
            dist, (b, h, w) = self.assign(intermediates, shared.spectrum())
            tokens = shared.tokens((h, w))  # [N, Dl]
            masks = dist.argmin(dim=1)
            protos = masked_mean_normalised(tokens, masks, dist.shape[1])
            if prior is not None:
                inst = Instances(prior, (h, w))
                prior_dist = torch.ones(dist.shape[0], inst.count, device=dist.device)
                has = inst.index >= 0
                prior_dist[has.nonzero().squeeze(1), inst.index[has]] = 0.0
                dist = torch.cat([dist, prior_dist], dim=1)
                protos = torch.cat([protos, masked_mean_normalised(tokens, inst.index, inst.count)])
            weights = torch.softmax(dist.mul_(-self.alpha), dim=1)  # dist is ours: in place
            if self.tau > 0:
                weights = weights * (weights >= self.tau)
            out = normalise_(weights @ protos, dim=1)
        return out.reshape(b, h, w, -1).permute(0, 3, 1, 2).to(language.dtype)

    @torch.no_grad()
    def assign(
        self, intermediates: Tensor, spectrum: PCASpectrum | None = None
    ) -> tuple[Tensor, Tensor]:
        """Cluster the batch's intermediates.

        Args:
            intermediates: ``[B, Dv, Hv, Wv]``.
            spectrum: the covariance spectrum of the upsampled intermediates, if already
                computed (:class:`FullShared`); else computed here.

        Returns:
            ``(distances, shape)``: ``distances`` ``[N, n]`` Euclidean distances of every
            upsampled point (``N = B*Hv*s*Wv*s``) to every centroid in the normalised PCA
            space, and the upsampled grid ``(B, Hv*s, Wv*s)``.
        """
        b, _, hv, wv = intermediates.shape
        s = self.upscale
        n = self.check_grid(b, hv, wv)
        x = intermediates.float()
        spectrum = spectrum if spectrum is not None else upsampled_spectrum(x, s)
        if self.elbo_candidates is not None:
            n = self._elbo_count(x, spectrum)
        fit = spectrum.top(self.n_components if self.n_components is not None else n)
        # Project on the small grid (projection commutes with upsampling). The [B*Hv*Wv, r']
        # result is the channels-last layout of the [B, r', Hv, Wv] map, which bilinear
        # upsampling keeps, so the upsampled map's points are a view, not a copy.
        low = _project_grid(x, fit)
        r = low.shape[1]
        up = upsample(low.view(b, hv, wv, r).permute(0, 3, 1, 2), s)
        up = up.permute(0, 2, 3, 1).reshape(-1, r)
        norms = torch.linalg.vector_norm(up, dim=1).clamp_min_(1e-12)  # as F.normalize
        z = up / norms.unsqueeze(1)
        low_t = low.T.contiguous()  # [r', B*Hv*Wv]

        def dots(c: Tensor) -> Tensor:
            """``c @ z.T`` on the small grid: z_p.c = up(low.c)_p / |up(low)_p|."""
            grid_dots = (c @ low_t).view(-1, 1, hv, wv)  # [t*B, 1, Hv, Wv]
            return upsample(grid_dots, s).view(c.shape[0], -1).div_(norms)

        result = kmeans(z, n, seed=self.seed, max_iter=self.max_iter, tol=self.tol, dots=dots)
        # The final assignment's distance matrix is the one returned (no second product).
        return result.sq_dists.sqrt_(), (b, hv * s, wv * s)

    def _elbo_count(self, x: Tensor, spectrum: PCASpectrum) -> int:
        """The count :func:`elbo_prototype_count` chooses for the batch ``x`` ``[B, Dv, Hv,
        Wv]``, on its normalised PCA points (``n_components`` axes, or the largest
        candidate's when tied), recorded in :attr:`chosen`. Only the subsample the chooser
        fits (:func:`elbo_subsample`) is computed, not all ``B Hv s Wv s`` points."""
        assert self.elbo_candidates is not None
        b, _, hv, wv = x.shape
        n_all = b * hv * wv * self.upscale**2
        rows = elbo_subsample(n_all, self.elbo_max_points, self.seed)
        n = elbo_prototype_count(
            self._elbo_points(x, spectrum, rows), self.elbo_candidates, seed=self.seed,
            stop_after=self.elbo_stop_after, max_points=self.elbo_max_points,
            tol=self.elbo_tol, n_points=n_all,
        )  # fmt: skip
        self.chosen.append(n)
        return n

    def _elbo_points(self, x: Tensor, spectrum: PCASpectrum, rows: Tensor | None = None) -> Tensor:
        """``[N, r]`` the normalised PCA points of ``x`` the count is chosen on (``n_components``
        axes, or the largest candidate's when tied), or only their ``rows`` (indices into the
        ``B Hv s Wv s`` upsampled points, row-major), each the bilinear blend of its four grid
        neighbours' projections (what the upsampling computes, up to rounding)."""
        b, _, hv, wv = x.shape
        assert self.elbo_candidates is not None
        fit = spectrum.top(self.n_components or self.elbo_candidates[-1])
        s = self.upscale
        if rows is None:
            low = _project_grid(x, fit)  # [B*Hv*Wv, r]
            up = upsample(low.view(b, hv, wv, -1).permute(0, 3, 1, 2), s)
            return F.normalize(up.permute(0, 2, 3, 1).reshape(-1, up.shape[1]), dim=1)
        # The rows' upsampled intermediates, then their projection (fewer rows to project than
        # the grid's; projection commutes with the blend, whose weights sum to 1). The blend is
        # F.grid_sample at the rows' pixel centres: with align_corners=False and border padding,
        # normalised coordinate (2 i + 1) / h - 1 is source coordinate (i + 1/2) / s - 1/2,
        # clamped at the borders, i.e. F.interpolate's bilinear taps.
        rows = rows.to(x.device)
        h, w = hv * s, wv * s
        image, i, j = rows // (h * w), rows // w % h, rows % w
        where = torch.stack([(2 * j + 1).double() / w - 1, (2 * i + 1).double() / h - 1], 1)
        where = where.to(x.dtype)
        up = x.new_empty(rows.numel(), x.shape[1])
        for one in image.unique().tolist():  # grid_sample takes as many rows from every image
            at = (image == one).nonzero().squeeze(1)
            grid = where[at].view(1, 1, -1, 2)
            taps = F.grid_sample(x[one : one + 1], grid, padding_mode="border", align_corners=False)
            up[at] = taps[0, :, 0].T
        return F.normalize((up - fit.mean) @ fit.components.T, dim=1)
