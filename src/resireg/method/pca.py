"""Torch PCA: fit a principal-component basis to points, from the points or their moments.

The one job of this module is the PCA that ReSiReg Full projects its intermediates with
before clustering them (docs/method.md#pca-and-k-means): :func:`pca` of ``[N, D]`` points,
:func:`pca_from_moments` and :class:`PCASpectrum` of points known only by their first and
second moments (ReSiReg Full's upsampled points, whose moments
:func:`resireg.method.full.upsampled_moments` takes from the small grid), and :func:`gram`,
the symmetric product ``Y^T Y`` of the covariance at 5/8 of a matrix product. Everything runs
on the input's device with matrix products only (the PCA sits inside a GPU forward pass, see
``benchmarks/bench_reconstruct.py``).
"""

from __future__ import annotations

from dataclasses import dataclass

import torch
from torch import Tensor

__all__ = ["PCAResult", "PCASpectrum", "pca", "pca_from_moments", "gram"]


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
    smaller grid, see :func:`resireg.method.full.upsampled_moments`) fit the exact PCA of
    points they never materialise.
    """
    if int(n_components) < 1:
        raise ValueError(f"n_components must be >= 1, got {n_components}")
    return PCASpectrum.from_moments(second, first, n, shift).top(n_components)


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
