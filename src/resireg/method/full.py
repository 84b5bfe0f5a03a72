"""ReSiReg Full and Lite: parameter-free reconstruction of dense language features.

Notation (docs/method.md#resireg): intermediates ``F_v`` ``[B, Dv, Hv, Wv]`` carry the
backbone's spatial structure, language tokens ``F_vl`` ``[B, Dl, Hl, Wl]`` carry the
language-aligned (but spatially noisy) features, and an optional segmentation prior
``S`` ``[B, H', W']`` holds instance ids (0 = none). Both modules return
``[B, Dl, Hv*s, Wv*s]`` features of unit L2 norm over ``Dl``.

The module reads top to bottom: the helpers both variants use; the PCA of ReSiReg Full's
upsampled points, computed from the small grid (:func:`upsampled_moments`); then
:class:`ReSiRegFull`, whose ``forward`` (first among its steps) runs:

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

Last, :class:`ReSiRegLite` and its helpers. The clustering modules (:mod:`resireg.method.pca`,
:mod:`resireg.method.kmeans`, :mod:`resireg.method.elbo`) know nothing of this one; it calls them.

Resolved ambiguity: the paper calls the Lite normalisation "column-wise"; we normalise
over the prototype (key) axis, the same axis as Full, so every output patch is a convex
combination of language tokens (before the optional tau gate).
"""

from __future__ import annotations

import math
from collections.abc import Callable, Sequence

import torch
import torch.nn.functional as F
from torch import Tensor, nn

from resireg.method.checks import check_positive_int, check_variant_inputs
from resireg.method.elbo import ELBO_MAX_POINTS, elbo_prototype_count, elbo_subsample
from resireg.method.kmeans import kmeans
from resireg.method.pca import PCAResult, PCASpectrum, gram
from resireg.specs.variants import check_variant_kwargs

__all__ = [
    "FullShared",
    "factorised_blocks",
    "ReSiRegFull",
    "ReSiRegLite",
    "upsampled_moments",
    "upsampled_pca",
    "upsampled_spectrum",
]


# ------------------------------------------------------------------------ shared by Full and Lite
def _upsample(x: Tensor, scale: int) -> Tensor:
    """Bilinear upsampling of ``[B, D, H, W]`` by an integer factor."""
    if scale == 1:
        return x
    return F.interpolate(x, scale_factor=scale, mode="bilinear", align_corners=False)


def _nearest(x: Tensor, size: tuple[int, int]) -> Tensor:
    """Nearest-neighbour resize of ``[B, D, H, W]`` (any dtype) to ``size``."""
    if tuple(x.shape[-2:]) == tuple(size):
        return x
    return F.interpolate(x, size=size, mode="nearest")


def _to_points(x: Tensor) -> Tensor:
    """``[B, D, H, W]`` -> ``[B*H*W, D]`` (row-major over batch, then space)."""
    return x.permute(0, 2, 3, 1).reshape(-1, x.shape[1])


def _normalise_(x: Tensor, dim: int) -> Tensor:
    """``F.normalize(x, dim=dim)`` in place (the same arithmetic, equal results). On the CPU a
    fresh tensor of the size of a batch's features (e.g. 55,296 x 512 floats) costs more in
    page faults than the division itself: 40 ms against 5 ms measured."""
    return x.div_(torch.linalg.vector_norm(x, dim=dim, keepdim=True).clamp_min_(1e-12))


def _masked_mean_normalised(values: Tensor, index: Tensor, n_groups: int) -> Tensor:
    """L2-normalised mean of ``values`` ``[N, D]`` per group of ``index`` ``[N]``.

    Points with ``index < 0`` belong to no group; an empty group yields a zero vector.
    Returns ``[n_groups, D]``.
    """
    sums = values.new_zeros(n_groups, values.shape[1])
    keep = index >= 0
    if bool(keep.all()):  # every point in a group (k-means masks): no masked copy of values
        sums.index_add_(0, index, values)
    else:
        sums.index_add_(0, index[keep], values[keep])
    # The mean and the sum have the same direction; normalising the sum is enough and a
    # zero sum (empty group) stays zero.
    return F.normalize(sums, dim=1)


class _Instances:
    """Instances of a segmentation prior, enumerated across the batch.

    Attributes:
        index: ``[B*H*W]`` global instance index of every point, -1 where the prior is 0.
        owner: ``[m]`` image index of each instance.
        local: ``[m]`` index of each instance within its image (0..m_b-1).
        count: number of instances ``m`` across the batch.
        max_per_image: largest ``m_b``.
    """

    def __init__(self, prior: Tensor, size: tuple[int, int]) -> None:
        grid = _nearest(prior.unsqueeze(1).float(), size).squeeze(1).long()  # [B, H, W]
        b = grid.shape[0]
        ids = grid.reshape(b, -1)
        span = int(ids.max().item()) + 1 if ids.numel() else 1
        image = torch.arange(b, device=ids.device).unsqueeze(1).expand_as(ids)
        key = torch.where(ids > 0, image * span + ids, torch.full_like(ids, -1)).reshape(-1)
        valid = key >= 0
        uniq, inverse = torch.unique(key[valid], return_inverse=True)
        self.index = torch.full_like(key, -1)
        self.index[valid] = inverse
        self.owner = torch.div(uniq, span, rounding_mode="floor")
        per_image = torch.bincount(self.owner, minlength=b)
        first = torch.cumsum(per_image, 0) - per_image
        self.local = torch.arange(uniq.numel(), device=ids.device) - first[self.owner]
        self.count = int(uniq.numel())
        self.max_per_image = int(per_image.max().item()) if b else 0


# ------------------------------------------- Full: the PCA of the upsampled points, from the grid
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
            self._tokens = _to_points(_nearest(self.language.float(), size))
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
            protos = _masked_mean_normalised(tokens, masks, dist.shape[1])
            if prior is not None:
                inst = _Instances(prior, (h, w))
                prior_dist = torch.ones(dist.shape[0], inst.count, device=dist.device)
                has = inst.index >= 0
                prior_dist[has.nonzero().squeeze(1), inst.index[has]] = 0.0
                dist = torch.cat([dist, prior_dist], dim=1)
                protos = torch.cat(
                    [protos, _masked_mean_normalised(tokens, inst.index, inst.count)]
                )
            weights = torch.softmax(dist.mul_(-self.alpha), dim=1)  # dist is ours: in place
            if self.tau > 0:
                weights = weights * (weights >= self.tau)
            out = _normalise_(weights @ protos, dim=1)
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
        up = _upsample(low.view(b, hv, wv, r).permute(0, 3, 1, 2), s)
        up = up.permute(0, 2, 3, 1).reshape(-1, r)
        norms = torch.linalg.vector_norm(up, dim=1).clamp_min_(1e-12)  # as F.normalize
        z = up / norms.unsqueeze(1)
        low_t = low.T.contiguous()  # [r', B*Hv*Wv]

        def dots(c: Tensor) -> Tensor:
            """``c @ z.T`` on the small grid: z_p.c = up(low.c)_p / |up(low)_p|."""
            grid_dots = (c @ low_t).view(-1, 1, hv, wv)  # [t*B, 1, Hv, Wv]
            return _upsample(grid_dots, s).view(c.shape[0], -1).div_(norms)

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
            up = _upsample(low.view(b, hv, wv, -1).permute(0, 3, 1, 2), s)
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


# ------------------------------------------------------------------------------------------- Lite
# Budget for one chunk of the explicit (tau > 0) Lite attention matrix, in elements.
_LITE_CHUNK_ELEMENTS = 16 * 1024 * 1024
# Factorised Lite (ReSiRegLite._factorised), in elements: a block of queries' Gram rows
# interpolated on the query side ([queries, h w]), and a tile of their similarities to every
# key ([N, queries]). Measured on 2 cores at the protocol's size (6,912 points, one image):
# tiles of 1M, 4M, 8M, 16M elements took 0.46, 0.50, 0.49, 0.81 s on one thread, and 2.3,
# 1.4, 1.3, 1.2 s on two threads while other processes shared the cores (each elementwise
# pass is a parallel region whose barrier waits for a descheduled thread, so fewer, larger
# passes win there): 8M (32 MB in float32) is the compromise.
_FACTORISED_BLOCK = 8 * 1024 * 1024
_FACTORISED_TILE = 8 * 1024 * 1024


def factorised_blocks(h: int, w: int, scale: int) -> list[tuple[int, int, int, int]]:
    """The query blocks of factorised Lite on an ``h x w`` grid upsampled by ``scale``:
    ``(r0, r1, c0, c1)``, coarse query rows ``r0:r1`` (their upsampled rows
    ``scale*r0:scale*r1``) and the coarse rows ``c0:c1`` their bilinear weights read (one
    above and one below), each block's ``[queries, h w]`` Gram rows within
    ``_FACTORISED_BLOCK`` elements (at least one coarse row)."""
    rows = max(1, _FACTORISED_BLOCK // max(1, scale * scale * w * h * w))
    return [
        (r0, min(h, r0 + rows), max(0, r0 - 1), min(h, r0 + rows + 1)) for r0 in range(0, h, rows)
    ]


def _token_index(
    lang_size: tuple[int, int], grid: tuple[int, int], scale: int, device: torch.device
) -> tuple[Tensor, bool]:
    """The language token of every point of the upsampled grid (``scale`` x ``grid``), as
    :func:`_nearest` picks it (the nearest resize of the token index map, so exactly
    ``F.interpolate``'s choice): ``([N] indices into the row-major token grid, whether token
    j is the s x s block j)``, the latter when the language grid is the intermediates'."""
    (hl, wl), (h, w) = lang_size, grid
    size = (h * scale, w * scale)
    index = torch.arange(hl * wl, dtype=torch.float64, device=device).view(1, 1, hl, wl)
    token = _nearest(index, size).view(-1).long()
    rows = torch.arange(size[0], device=device).div(scale, rounding_mode="floor")
    cols = torch.arange(size[1], device=device).div(scale, rounding_mode="floor")
    block = (rows.unsqueeze(1) * w + cols).view(-1)
    return token, (hl, wl) == (h, w) and torch.equal(token, block)


class ReSiRegLite(nn.Module):
    """ReSiReg Lite: every patch is its own prototype (one attention step, no clustering).

    Within each image, ``lambda_pq = softmax_q(alpha * cos(u_p, u_q))`` over the upsampled
    points (gated by ``tau``) and ``f_p = normalise(sum_q lambda_pq L_q)``, with ``u`` the
    bilinearly upsampled intermediates and ``L`` the nearest-upsampled language tokens.

    Two exact computations (docs/method.md#resireg-lite), chosen by ``attention``:

    - ``"sdpa"``: single-head attention with ``Q = K =`` the normalised upsampled points and
      ``V =`` the upsampled tokens, by ``scaled_dot_product_attention`` in O(N) memory
      (``tau = 0``; with ``tau > 0`` the gate needs explicit affinities, computed in row
      chunks so the batch's ``N x N`` never exists at once). ``4 N^2 W`` FLOP per image.
    - ``"factorised"``: both maps are linear maps of the coarse grid, so the similarities are
      the bilinear interpolation (on both sides) of the coarse Gram matrix scaled by the
      points' inverse norms, and the product with the values sums the weights of each
      nearest block and multiplies the coarse tokens (:meth:`_factorised`): about
      ``2 N h w Dl + 2 (h w)^2 Dv`` FLOP, 6.7x fewer at the protocol's size.
    - ``"auto"`` (default): ``"sdpa"`` on CUDA (fused tensor-core kernels), ``"factorised"``
      elsewhere (on the CPU it is 4-5x faster).

    A segmentation prior adds, per image, one prototype per instance (its language
    embedding is the normalised mean of the instance's tokens) with similarity 1 to the
    instance's own patches and 0 to all others, the Lite analogue of Full's prior channel
    ``d = 1 - 1[S_p = j]``: folded into the attention keys exactly in the SDPA path
    (:meth:`_with_prior`), added in closed form in the factorised one.

    Args:
        alpha: softmax temperature on cosine similarities.
        tau: gate; affinities below ``tau`` are zeroed (no renormalisation).
        upscale: integer bilinear upsampling factor ``s`` of the intermediates.
        attention: ``"auto"``, ``"sdpa"`` or ``"factorised"`` (see above).
    """

    def __init__(
        self, alpha: float = 10.0, tau: float = 0.0, upscale: int = 2, attention: str = "auto"
    ) -> None:
        super().__init__()
        # the rules of resireg.specs.variants (also those of the lite.* config checks)
        check_variant_kwargs(
            "lite", {"alpha": alpha, "tau": tau, "upscale": upscale, "attention": attention}
        )
        self.alpha, self.tau = float(alpha), float(tau)
        self.upscale = upscale
        self.attention = attention

    def extra_repr(self) -> str:
        return (
            f"alpha={self.alpha}, tau={self.tau}, upscale={self.upscale}, "
            f"attention={self.attention}"
        )

    def resolve_attention(self, device: torch.device) -> str:
        """The computation used on ``device``: ``"sdpa"`` or ``"factorised"``."""
        if self.attention != "auto":
            return self.attention
        return "sdpa" if torch.device(device).type == "cuda" else "factorised"

    @torch.no_grad()
    def forward(
        self, intermediates: Tensor, language: Tensor, prior: Tensor | None = None
    ) -> Tensor:
        """Reconstruct language features; arguments, result, errors and ``no_grad`` as
        :meth:`ReSiRegFull.forward`."""
        check_variant_inputs(intermediates, language, prior)
        dtype = torch.promote_types(intermediates.dtype, language.dtype)
        with torch.autocast(device_type=intermediates.device.type, enabled=False):
            if self.resolve_attention(intermediates.device) == "factorised":
                return self._factorised(intermediates, language, prior).to(language.dtype)
            fv = F.normalize(_upsample(intermediates.to(dtype), self.upscale), dim=1)
            b, _, h, w = fv.shape
            tokens = _nearest(language.to(dtype), (h, w))
            q = fv.flatten(2).transpose(1, 2)  # [B, N, Dv]
            v = tokens.flatten(2).transpose(1, 2)  # [B, N, Dl]
            k = q
            if prior is not None:
                q, k, v = self._with_prior(q, v, prior, (h, w))
            out = self._attend(q, k, v)
            out = _normalise_(out, dim=2)
        return out.transpose(1, 2).reshape(b, -1, h, w).to(language.dtype)

    def _factorised(self, intermediates: Tensor, language: Tensor, prior: Tensor | None) -> Tensor:
        """Lite from the coarse grid, exactly (docs/method.md#resireg-lite).

        Per image, with ``X`` the ``h w`` coarse points, ``U`` the bilinear upsampling and
        ``P`` the nearest one (``N x h_l w_l`` one-hot rows): the upsampled points are
        ``U X``, so their Gram matrix is ``U G U^T`` with ``G = X X^T`` (``h w x h w``), and
        ``cos(u_p, u_q) = (U G U^T)_pq r_p r_q`` with ``r = 1 / max(|U X|, 1e-12)`` per point
        (from ``up(F_v)`` itself, as ``F.normalize`` takes it). ``U G U^T`` is two bilinear
        interpolations of ``G``, one per side, so it costs a few operations per entry instead
        of a ``Dv``-long dot product. The values are ``P L``: ``E P L = (E P) L`` where
        ``E P`` sums each row's weights over the keys of one language token (an ``s x s``
        block when the grids match), so the product is with the ``h_l w_l`` coarse tokens,
        ``s^2`` times fewer rows. The softmax is taken as ``exp(alpha (cos - 1))`` (the
        largest logit is ``alpha``, the point with itself; the cosine is clamped at 1 so
        rounding cannot overflow it; computed as ``exp2``, twice as fast on the CPU) and its
        denominator is needed only for the gate, since the output is normalised.

        Work is split per image into blocks of coarse query rows (their Gram rows, from the
        rows above and below too, interpolated on the query side) and tiles of queries
        (interpolated on the key side, exponentiated, summed per block), so memory stays
        ``O(_FACTORISED_BLOCK + _FACTORISED_TILE)`` elements whatever the grid.
        Computed in at least float32 (bfloat16 and float16 inputs are promoted: on the CPU
        their products and ``exp`` are no faster). Returns ``[B, Dl, s h, s w]``.
        """
        dtype = torch.promote_types(
            torch.promote_types(intermediates.dtype, language.dtype), torch.float32
        )
        x = intermediates.to(dtype)
        lang = language.to(dtype)
        b, dv, hv, wv = x.shape
        dl, hl, wl = lang.shape[1:]
        s, alpha = self.upscale, self.alpha
        big_h, big_w = hv * s, wv * s
        n, hw = big_h * big_w, hv * wv
        dev = x.device
        token, blocks = _token_index((hl, wl), (hv, wv), s, dev)
        inst = _Instances(prior, (big_h, big_w)) if prior is not None else None
        fade = math.exp(-alpha)  # an instance key's weight for a patch outside it
        # exp(alpha (cos - 1)) is taken as exp2(scale (cos - 1)): CPU exp2 is twice as fast.
        scale = alpha * math.log2(math.e)
        out = x.new_empty(b, n, dl)
        tile = max(1, _FACTORISED_TILE // n)  # queries per key-side tile
        for i in range(b):
            pts = x[i].permute(1, 2, 0).reshape(hw, dv)  # [h w, Dv] coarse points
            inv = torch.linalg.vector_norm(_upsample(x[i : i + 1], s)[0], dim=0)
            inv = inv.clamp_min_(1e-12).reciprocal_().view(n, 1)  # [N, 1] r = 1 / |u_p|
            tokens = lang[i].permute(1, 2, 0).reshape(hl * wl, dl)
            extra = None
            if inst is not None:
                extra = self._prior_terms(inst, i, n, tokens[token], fade)
            for r0, r1, c0, c1 in factorised_blocks(hv, wv, s):
                gram_rows = pts[c0 * wv : c1 * wv] @ pts.T  # [(c1 - c0) w, h w]
                # Query side: U G restricted to this block's queries (channels-last, so the
                # result's rows are the queries, each a row of h w Gram entries).
                left = _upsample(gram_rows.view(1, c1 - c0, wv, hw).permute(0, 3, 1, 2), s)
                q0, q1 = r0 * s * big_w, r1 * s * big_w
                left = left[0, :, s * (r0 - c0) : s * (r1 - c0)].permute(1, 2, 0).reshape(-1, hw)
                left.mul_(inv[q0:q1].mul(scale))  # the query's factor folded in: log2(e) alpha r_p
                for t0 in range(q0, q1, tile):
                    t1 = min(q1, t0 + tile)
                    side = left[t0 - q0 : t1 - q0].T.contiguous().view(1, hv, wv, t1 - t0)
                    # Key side: (U G U^T) for these queries, [N keys, queries], channels-last.
                    sim = _upsample(side.permute(0, 3, 1, 2), s)[0].permute(1, 2, 0)
                    weights = sim.reshape(n, t1 - t0).mul_(inv).sub_(scale).clamp_max_(0.0).exp2_()
                    sums = self._token_sums(weights, token, blocks, (hv, wv, s), hl * wl)
                    norm = None
                    if self.tau > 0:  # gate: lambda = w / Z >= tau, then the sums again
                        norm = sums.sum(0)  # the softmax denominators [queries]
                        if extra is not None:
                            norm += extra["norm"][t0:t1]
                        weights.mul_(weights >= self.tau * norm)
                        sums = self._token_sums(weights, token, blocks, (hv, wv, s), hl * wl)
                    tile_out = out[i, t0:t1]
                    torch.mm(sums.T, tokens, out=tile_out)  # [queries, Dl]
                    if extra is not None:
                        self._add_prior(tile_out, extra, t0, t1, norm, fade)
        _normalise_(out, dim=2)
        return out.transpose(1, 2).reshape(b, dl, big_h, big_w)

    @staticmethod
    def _token_sums(
        weights: Tensor, token: Tensor, blocks: bool, grid: tuple[int, int, int], n_tokens: int
    ) -> Tensor:
        """``[n_tokens, P]``: ``sum_{q: token[q] = j} weights[q, p]`` for ``weights`` ``[N, P]``
        (keys row-major over the upsampled grid ``s h x s w``)."""
        h, w, s = grid
        p = weights.shape[1]
        if blocks:  # token j is the s x s block j: a sum pooling of the channels-last map
            grid_map = weights.view(1, h * s, w * s, p).permute(0, 3, 1, 2)
            return F.avg_pool2d(grid_map, s, divisor_override=1)[0].permute(1, 2, 0).reshape(-1, p)
        return weights.new_zeros(n_tokens, p).index_add_(0, token, weights)

    def _prior_terms(
        self, inst: _Instances, image: int, n: int, values: Tensor, fade: float
    ) -> dict[str, Tensor] | None:
        """Image ``image``'s instance keys in closed form. With the logits shifted by
        ``alpha`` (as the patch weights), an instance key weighs 1 for its own patches and
        ``fade = exp(-alpha)`` for every other patch of the image, so for patch ``p`` they add
        ``fade * sum_j e_j + (1 - fade) e_(S_p)`` to the numerator and
        ``fade * m + (1 - fade) 1[S_p > 0]`` to the softmax denominator. Returns ``None``
        when the image has no instance; else ``own`` ``[N]`` (the patch's instance, -1 for
        none), ``embed`` ``[m, Dl]``, ``total`` ``[Dl]`` and ``norm`` ``[N]`` (the added
        denominator)."""
        index = inst.index[image * n : (image + 1) * n]
        mine = (inst.owner == image).nonzero().squeeze(1)
        if mine.numel() == 0:
            return None
        local = torch.full_like(index, -1)
        has = index >= 0
        local[has] = inst.local[index[has]]
        embed = _masked_mean_normalised(values, local, mine.numel())  # [m, Dl]
        norm = torch.full((n,), fade * mine.numel(), dtype=values.dtype, device=values.device)
        norm[has] += 1.0 - fade
        return {"own": local, "embed": embed, "total": embed.sum(0), "norm": norm}

    def _add_prior(
        self,
        out: Tensor,
        extra: dict[str, Tensor],
        q0: int,
        q1: int,
        norm: Tensor | None,
        fade: float,
    ) -> None:
        """Add the instance keys' share (:meth:`_prior_terms`) to the numerators ``out``
        ``[q1 - q0, Dl]`` of queries ``q0:q1``, gated by ``tau`` against their softmax
        denominators ``norm``: an own instance weighs 1, the others ``fade`` each."""
        own = extra["own"][q0:q1]
        has = own >= 0
        own_embed = torch.zeros_like(out)
        own_embed[has] = extra["embed"][own[has]]
        if self.tau > 0:
            keep_own = (1.0 >= self.tau * norm).unsqueeze(1).to(out.dtype)
            keep_other = (fade >= self.tau * norm).unsqueeze(1).to(out.dtype)
        else:
            keep_own = keep_other = out.new_ones(())
        # other instances: fade * (total - own); own instance: 1 * own
        out.add_((extra["total"] - own_embed) * (fade * keep_other)).add_(own_embed * keep_own)

    def _with_prior(
        self, q: Tensor, v: Tensor, prior: Tensor, size: tuple[int, int]
    ) -> tuple[Tensor, Tensor, Tensor]:
        """Append instance prototypes as extra keys/values, exactly.

        With ``M`` the most instances in one image, queries gain ``M`` one-hot dims (the
        patch's instance slot) and one constant dim; instance keys are one-hot in the
        slot dims, so ``q.k`` is 1 for the patch's own instance and 0 otherwise. Padding
        slots (images with fewer than ``M`` instances) get ``-1e4 / alpha`` in the constant
        dim, so ``exp(alpha * q.k)`` is exactly zero for them.
        """
        b, n, dv = q.shape
        inst = _Instances(prior, size)
        m = inst.max_per_image
        if m == 0:
            return q, q, v
        dl = v.shape[2]
        embed = _masked_mean_normalised(v.reshape(-1, dl).float(), inst.index, inst.count).to(
            v.dtype
        )
        inst_v = v.new_zeros(b, m, dl)
        inst_v[inst.owner, inst.local] = embed
        slot = q.new_zeros(b * n, m)
        has = inst.index >= 0
        slot[has.nonzero().squeeze(1), inst.local[inst.index[has]]] = 1.0
        slot = slot.reshape(b, n, m)
        q_aug = torch.cat([q, slot, q.new_ones(b, n, 1)], dim=2)
        k_patch = torch.cat([q, q.new_zeros(b, n, m + 1)], dim=2)
        pad = q.new_full((b, m), -1e4 / self.alpha)
        pad[inst.owner, inst.local] = 0.0
        k_inst = torch.cat(
            [
                q.new_zeros(b, m, dv),
                torch.eye(m, dtype=q.dtype, device=q.device).expand(b, m, m),
                pad.unsqueeze(2),
            ],
            dim=2,
        )
        return q_aug, torch.cat([k_patch, k_inst], dim=1), torch.cat([v, inst_v], dim=1)

    def _attend(self, q: Tensor, k: Tensor, v: Tensor) -> Tensor:
        """``softmax(alpha q k^T)`` (gated) ``@ v`` for ``[B, Nq, D]``, ``[B, Nk, D]``, ``[B, Nk, Dl]``."""
        if self.tau == 0:
            # SDPA keeps to its fused O(N)-memory kernel only for contiguous [B, 1, N, D]
            # inputs with equal q/k and v widths; otherwise it falls back to the math kernel
            # and materialises N x N (measured: 3.4 GB instead of 89 MB for 8 x 6912 points
            # with 384-d keys and 512-d values). Zero-padding the narrower side to a common
            # width changes no dot product. The width is rounded up to a multiple of 8, the
            # alignment CUDA's fused kernels need: the prior's M + 1 slot dimensions make the
            # query width arbitrary (e.g. 384 + 150 + 1).
            dl = v.shape[2]
            width = -(-max(q.shape[2], dl) // 8) * 8
            out = F.scaled_dot_product_attention(
                F.pad(q, (0, width - q.shape[2])).unsqueeze(1).contiguous(),
                F.pad(k, (0, width - k.shape[2])).unsqueeze(1).contiguous(),
                F.pad(v, (0, width - dl)).unsqueeze(1).contiguous(),
                scale=self.alpha,
            )
            return out.squeeze(1)[..., :dl]
        b, nq, _ = q.shape
        rows = max(1, _LITE_CHUNK_ELEMENTS // max(1, b * k.shape[1]))
        kt = k.transpose(1, 2)
        chunks = []
        for start in range(0, nq, rows):
            a = torch.softmax(self.alpha * (q[:, start : start + rows] @ kt), dim=2)
            a = a * (a >= self.tau)
            chunks.append(a @ v)
        return torch.cat(chunks, dim=1)
