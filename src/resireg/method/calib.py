"""Calib: SC-CLIP's self-calibration, backbone-generic, as a post-hoc variant.

SC-CLIP (Bai et al., "Self-Calibrated CLIP for Training-Free Open-Vocabulary
Segmentation", github.com/SuleBai/SC-CLIP) calibrates CLIP in two steps that need no
CLIP internals beyond an intermediate token map. :class:`Calib` keeps exactly these two,
applied to the ``intermediates`` ``F_v`` ``[B, Dv, Hv, Wv]`` and ``language`` tokens
``F_vl`` ``[B, Dl, Hl, Wl]`` of any :class:`~resireg.models.interface.DenseEncoder`:

1. **Anomaly resolution.** Per image, the local outlier factor (LOF) of the ``N = Hv*Wv``
   intermediate patch tokens is computed exactly as scikit-learn's
   ``LocalOutlierFactor(n_neighbors=k, contamination=c)`` does (see
   :func:`negative_outlier_factor`, :func:`lof_outliers`): Euclidean distances, the token
   itself excluded from its ``k`` nearest neighbours, reachability distance
   ``max(d(p, o), k-distance(o))``, ``lrd(p) = 1 / (mean_o reach(p, o) + 1e-10)``,
   ``LOF(p) = mean_o lrd(o) / lrd(p)``; with ``nof = -LOF``, the anomalous tokens are those
   with ``nof < offset``, ``offset = numpy.percentile(nof, 100 * c)`` (linear
   interpolation). With distinct scores that flags exactly ``ceil((N - 1) * c)`` tokens (29
   of 576 on a 24 x 24 grid at c = 0.05). Each anomalous position is then replaced, in
   BOTH maps, by the mean of its non-anomalous 8-neighbours inside the image (original
   values, all positions at once); a position whose in-bounds neighbours are all
   anomalous keeps its token (as SC-CLIP's ``mean_interpolation`` does). The language
   tokens must share the intermediates' grid for this: a language map on another grid is
   first resized bilinearly (``align_corners=False``) to ``Hv x Wv``, so the output is
   always on the intermediates' grid.
2. **Aggregation.** ``A_pq = cos(F_v[p], F_v[q])`` of the resolved intermediates of one
   image, entries ``< threshold`` (0.4) set to 0, rows normalised to sum 1, and
   ``f_p = normalise(sum_q A_pq L_q)`` over the resolved language tokens ``L``. The
   diagonal (``cos = 1``) keeps every row non-empty; a row with nothing left (a zero
   intermediate token, or ``threshold = 1`` with rounding) keeps its own language token.
   SC-CLIP's ``adaptively_aggregate`` normalises rows by ``sum + 1e-6`` rather than by the
   sum (no softmax); a positive per-row factor cancels in the final L2 normalisation, so
   the two agree up to rounding.

Edge rules: with fewer tokens than ``k + 1`` (small grids) the neighbour count is
``min(k, N - 1)`` as in scikit-learn, with a :class:`UserWarning` (scikit-learn warns only
when ``k > N``); a single-token image has no anomalies. ``contamination = 0`` flags
nothing (the aggregation alone). Distinct tokens tied at exactly the k-th neighbour
distance are ordered by :func:`torch.topk`, scikit-learn's order among exact ties is its
own, so only then can the scores differ. Everything runs in float32 (float64 when an input
is float64) with autocast off, and the result is float32, like the ``bb`` variant. The
whole batch is processed at once (``[B, N, N]`` distance and affinity matrices, no loop
over images or tokens); images never interact. ``prior`` is validated and ignored: SC-CLIP
has no segmentation prior.

What of SC-CLIP is left out (``clip/model.py``, ``VisionTransformer.forward``, defaults of
``scclip_segmentor.py`` for ViT-B/16), and why: all of it reaches into CLIP's forward pass,
which a post-hoc module on two given token maps cannot do.

- **Where LOF looks.** SC-CLIP runs LOF on the output of the penultimate block (block 11
  of 12, the last block's input) and uses those outlier positions to resolve both that
  hidden state and the block-9 output (``pre_adjust_idx = 8``) it takes affinities from.
  Here LOF runs on the intermediates themselves (``ClipEncoder``'s default is that same
  block 9), and the resolved maps are the intermediates and the language tokens.
- **Its LOF.** SC-CLIP's ``lof_pytorch`` is a simplified LOF, not scikit-learn's: squared
  distances, the point's own k-distance instead of the neighbour's in the reachability
  distance (which makes it constant, ``lrd = k / k-distance``), self excluded by dropping
  the first column of ``topk`` and outliers as ``score > quantile(score, 1 - c)``. We
  follow scikit-learn's definition instead, as specified. (Its row/column split of the
  outlier index also assumes a square grid, true for its 224 x 224 crops.)
- **Two aggregations and a self-adjusted last block.** SC-CLIP aggregates the last
  block's input with the thresholded affinities of the resolved block-9 tokens, then
  replaces the last block by ``custom_attn``: attention only (no residual, no MLP), its
  weights the average of ``softmax(3 (S - mean S))`` over the *unthresholded* block-9
  similarity ``S`` (entries below the mean masked out) and the key-key attention
  ``softmax(k k^T / sqrt(d))``, plus ``res_cls = 0.3`` times the class token; the result
  is aggregated again with the thresholded affinities of the *unresolved* block-4 tokens
  (``post_adjust_idx = 3``). This needs the last block's q/k/v projections and the class
  token; here the language tokens are the backbone's given output and are aggregated
  once, with the resolved intermediates' affinities.
- **Multi-level fusion.** SC-CLIP sums the hidden states of blocks 4 to 10
  (``feats_list[3:10]``), passes the sum through the self-adjusted last block, aggregates
  it with the block-4 affinities and adds it to the output before ``ln_post`` and
  ``proj``. It needs specific CLIP layers and the text projection; left out.
- **Its pipeline.** 224 x 224 sliding windows (stride 112), ``logit_scale``, ``prob_thd``,
  ``area_thd`` and optional PAMR belong to its evaluation, not to the calibration.
"""

from __future__ import annotations

import math
import warnings

import torch
import torch.nn.functional as F
from torch import Tensor, nn

from resireg.method.checks import check_positive_int, check_variant_inputs
from resireg.specs.rules import checked
from resireg.specs.variants import VARIANT_SPECS, check_variant_kwargs

__all__ = ["Calib", "lof_outliers", "negative_outlier_factor", "resolve_anomalies"]

# 8-neighbourhood offsets into a 1-padded map, the centre (1, 1) excluded.
_NEIGHBOURS = tuple((dy, dx) for dy in range(3) for dx in range(3) if (dy, dx) != (1, 1))


def _effective_neighbors(n_neighbors: int, n_points: int) -> int:
    """``min(n_neighbors, n_points - 1)``, warning when clipped; 0 for a single point."""
    if n_points - 1 < n_neighbors:
        warnings.warn(
            f"n_neighbors={n_neighbors} needs more than the {n_points} tokens per image; "
            f"LOF uses {max(n_points - 1, 0)} neighbours (n_tokens - 1), as scikit-learn does",
            UserWarning,
            stacklevel=3,
        )
    return max(0, min(n_neighbors, n_points - 1))


def negative_outlier_factor(points: Tensor, n_neighbors: int = 30) -> Tensor:
    """scikit-learn's ``negative_outlier_factor_`` of each set of points, batched.

    Args:
        points: ``[B, N, D]``, ``B`` independent point sets (floating point).
        n_neighbors: ``k``; ``min(k, N - 1)`` neighbours are used (with a warning when
            clipped).

    Returns:
        ``[B, N]`` ``-LOF`` in ``points.dtype`` (around -1 for inliers, lower = more
        anomalous); all ``-1`` when ``N == 1``.
    """
    check_positive_int("n_neighbors", n_neighbors)
    if points.ndim != 3 or not points.is_floating_point():
        raise ValueError(
            f"points must be a floating [B, N, D] tensor, got {points.dtype} {tuple(points.shape)}"
        )
    b, n, _ = points.shape
    k = _effective_neighbors(n_neighbors, n)
    if k == 0:
        return -points.new_ones(b, n)
    # Distances are translation invariant; centring first reduces the cancellation of the
    # |x|^2 + |y|^2 - 2 x.y form cdist uses.
    x = points - points.mean(dim=1, keepdim=True)
    dist = torch.cdist(x, x, compute_mode="use_mm_for_euclid_dist")
    dist.diagonal(dim1=1, dim2=2).fill_(math.inf)  # a point is not its own neighbour
    knn_dist, knn_idx = dist.topk(k, dim=2, largest=False, sorted=True)  # [B, N, k]
    flat_idx = knn_idx.reshape(b, n * k)
    k_distance = knn_dist[:, :, -1]  # [B, N]
    reach = torch.maximum(knn_dist, k_distance.gather(1, flat_idx).reshape(b, n, k))
    lrd = 1.0 / (reach.mean(dim=2) + 1e-10)  # scikit-learn's guard against duplicates
    return -(lrd.gather(1, flat_idx).reshape(b, n, k) / lrd.unsqueeze(2)).mean(dim=2)


def _percentile(values: Tensor, q: float) -> Tensor:
    """``numpy.percentile(values, q, axis=-1)`` (method "linear"), batched, exactly."""
    n = values.shape[-1]
    ordered = values.sort(dim=-1).values
    virtual = (n - 1) * (q / 100.0)  # numpy: (n - 1) * (q / 100)
    if virtual >= n - 1:
        return ordered[..., -1]
    lo = math.floor(virtual)
    gamma = virtual - lo
    a, b = ordered[..., lo], ordered[..., lo + 1]
    diff = b - a
    # numpy's _lerp: the form whose error vanishes at the nearer end point.
    return b - diff * (1.0 - gamma) if gamma >= 0.5 else a + diff * gamma


def lof_outliers(points: Tensor, n_neighbors: int = 30, contamination: float = 0.05) -> Tensor:
    """Outliers of each point set as ``LocalOutlierFactor(...).fit_predict(points) == -1``.

    Args:
        points: ``[B, N, D]``.
        n_neighbors: ``k`` of LOF (see :func:`negative_outlier_factor`).
        contamination: ``c`` in ``[0, 0.5]``; ``offset = percentile(nof, 100 c)`` and the
            points with ``nof < offset`` are outliers (0 flags none).

    Returns:
        ``[B, N]`` bool.
    """
    contamination = _check_contamination(contamination)
    nof = negative_outlier_factor(points, n_neighbors)
    offset = _percentile(nof, 100.0 * contamination)
    return nof < offset.unsqueeze(-1)


def resolve_anomalies(x: Tensor, anomalous: Tensor) -> Tensor:
    """Replace anomalous tokens by the mean of their non-anomalous 3 x 3 neighbours.

    Args:
        x: ``[B, C, H, W]`` token map.
        anomalous: ``[B, H, W]`` bool.

    Returns:
        ``[B, C, H, W]``: at anomalous positions, the mean of the non-anomalous tokens among
        the (up to) 8 in-bounds neighbours, taken from ``x`` as given; every other token,
        and an anomalous one without a non-anomalous neighbour, unchanged.
    """
    b, _, h, w = x.shape
    if anomalous.shape != (b, h, w) or anomalous.dtype != torch.bool:
        raise ValueError(
            f"anomalous must be a bool [B, H, W] = {[b, h, w]} tensor, got {anomalous.dtype} "
            f"{tuple(anomalous.shape)}"
        )
    bad = anomalous.unsqueeze(1)
    keep = (~bad).to(x.dtype)
    padded = F.pad(torch.where(bad, torch.zeros_like(x), x), (1, 1, 1, 1))
    padded_keep = F.pad(keep, (1, 1, 1, 1))
    total = torch.zeros_like(x)
    count = torch.zeros_like(keep)
    for dy, dx in _NEIGHBOURS:
        total += padded[:, :, dy : dy + h, dx : dx + w]
        count += padded_keep[:, :, dy : dy + h, dx : dx + w]
    return torch.where(bad & (count > 0), total / count.clamp(min=1), x)


def _check_contamination(contamination: float) -> float:
    """The ``calib.contamination`` rule of the variant table, for :func:`lof_outliers`."""
    rule = VARIANT_SPECS["calib"].params["contamination"]
    return float(checked("contamination", contamination, rule))


class Calib(nn.Module):
    """Calib: LOF anomaly resolution, then thresholded-affinity aggregation (see module doc).

    Args:
        n_neighbors: ``k`` of the local outlier factor (``min(k, N - 1)`` on small grids).
        contamination: fraction of tokens per image flagged as anomalous, in ``[0, 0.5]``
            (scikit-learn's definition; 0 disables the anomaly resolution).
        threshold: affinities (cosines) below it are zeroed before the row normalisation,
            in ``[0, 1]``.
    """

    def __init__(
        self, n_neighbors: int = 30, contamination: float = 0.05, threshold: float = 0.4
    ) -> None:
        super().__init__()
        # the rules of resireg.specs.variants (also those of the calib.* config checks)
        check_variant_kwargs(
            "calib",
            {"n_neighbors": n_neighbors, "contamination": contamination, "threshold": threshold},
        )
        self.n_neighbors = n_neighbors
        self.contamination = float(contamination)
        self.threshold = float(threshold)

    def extra_repr(self) -> str:
        return (
            f"n_neighbors={self.n_neighbors}, contamination={self.contamination}, "
            f"threshold={self.threshold}"
        )

    def outliers(self, intermediates: Tensor) -> Tensor:
        """``[B, Hv, Wv]`` bool: the anomalous tokens of each image of ``[B, Dv, Hv, Wv]``."""
        b, d, h, w = intermediates.shape
        if self.contamination == 0 or h * w < 2:
            return torch.zeros(b, h, w, dtype=torch.bool, device=intermediates.device)
        points = intermediates.reshape(b, d, h * w).transpose(1, 2)
        return lof_outliers(points, self.n_neighbors, self.contamination).reshape(b, h, w)

    def resolve(self, intermediates: Tensor, language: Tensor) -> tuple[Tensor, Tensor, Tensor]:
        """Step 1: ``(intermediates, language, anomalous)`` with the anomalies resolved.

        ``language`` must already be on the intermediates' grid.
        """
        anomalous = self.outliers(intermediates)
        return (
            resolve_anomalies(intermediates, anomalous),
            resolve_anomalies(language, anomalous),
            anomalous,
        )

    def aggregate(self, intermediates: Tensor, language: Tensor) -> Tensor:
        """Step 2: ``[B, Dl, Hv, Wv]`` unit-norm aggregation of ``language`` (same grid)."""
        b, _, h, w = intermediates.shape
        q = F.normalize(intermediates.flatten(2), dim=1)  # [B, Dv, N]
        affinity = q.transpose(1, 2) @ q  # [B, N, N] cosines
        affinity = affinity.masked_fill(affinity < self.threshold, 0.0)
        row_sum = affinity.sum(dim=2, keepdim=True)  # [B, N, 1]
        tokens = language.flatten(2).transpose(1, 2)  # [B, N, Dl]
        # (A / rowsum) @ L computed as (A @ L) / rowsum: the same, with N*Dl divisions.
        mixed = torch.where(row_sum > 0, (affinity @ tokens) / row_sum.clamp(min=1e-30), tokens)
        return F.normalize(mixed, dim=2).transpose(1, 2).reshape(b, -1, h, w)

    @torch.no_grad()
    def forward(
        self, intermediates: Tensor, language: Tensor, prior: Tensor | None = None
    ) -> Tensor:
        """Calibrate the language tokens.

        The inputs follow ReSiReg's rules (the shared
        :func:`resireg.method.checks.check_variant_inputs`: floating-point, finite, no empty
        dimension; each error names the argument) and, like ReSiReg, Calib has no parameters
        and runs under :func:`torch.no_grad`.

        Args:
            intermediates: ``[B, Dv, Hv, Wv]`` backbone features (LOF and affinities).
            language: ``[B, Dl, Hl, Wl]`` language-aligned tokens; resized bilinearly to
                ``Hv x Wv`` first when the grids differ.
            prior: accepted for the variants' common signature and ignored.

        Returns:
            ``[B, Dl, Hv, Wv]`` float32, unit L2 norm over ``Dl`` (a zero token stays zero).
        """
        check_variant_inputs(intermediates, language, prior)
        wide = torch.float64 in (intermediates.dtype, language.dtype)
        dtype = torch.float64 if wide else torch.float32
        with torch.autocast(device_type=intermediates.device.type, enabled=False):
            fv = intermediates.to(dtype)
            tokens = language.to(dtype)
            size = tuple(fv.shape[-2:])
            if tuple(tokens.shape[-2:]) != size:
                tokens = F.interpolate(tokens, size=size, mode="bilinear", align_corners=False)
            fv, tokens, _ = self.resolve(fv, tokens)
            out = self.aggregate(fv, tokens)
        return out.float()
