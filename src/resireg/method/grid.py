"""What ReSiReg Full (:mod:`resireg.method.full`) and Lite (:mod:`resireg.method.lite`) both do
to a feature grid: the bilinear and nearest resizes, the flattening to points, the in-place
normalisation, the normalised mean per group, and a segmentation prior's instances enumerated
across the batch. Torch only; nothing here knows either variant.
"""

from __future__ import annotations

import torch
import torch.nn.functional as F
from torch import Tensor

__all__ = [
    "Instances",
    "masked_mean_normalised",
    "nearest",
    "normalise_",
    "to_points",
    "upsample",
]


def upsample(x: Tensor, scale: int) -> Tensor:
    """Bilinear upsampling of ``[B, D, H, W]`` by an integer factor."""
    if scale == 1:
        return x
    return F.interpolate(x, scale_factor=scale, mode="bilinear", align_corners=False)


def nearest(x: Tensor, size: tuple[int, int]) -> Tensor:
    """Nearest-neighbour resize of ``[B, D, H, W]`` (any dtype) to ``size``."""
    if tuple(x.shape[-2:]) == tuple(size):
        return x
    return F.interpolate(x, size=size, mode="nearest")


def to_points(x: Tensor) -> Tensor:
    """``[B, D, H, W]`` -> ``[B*H*W, D]`` (row-major over batch, then space)."""
    return x.permute(0, 2, 3, 1).reshape(-1, x.shape[1])


def normalise_(x: Tensor, dim: int) -> Tensor:
    """``F.normalize(x, dim=dim)`` in place (the same arithmetic, equal results). On the CPU a
    fresh tensor of the size of a batch's features (e.g. 55,296 x 512 floats) costs more in
    page faults than the division itself: 40 ms against 5 ms measured."""
    return x.div_(torch.linalg.vector_norm(x, dim=dim, keepdim=True).clamp_min_(1e-12))


def masked_mean_normalised(values: Tensor, index: Tensor, n_groups: int) -> Tensor:
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


class Instances:
    """Instances of a segmentation prior, enumerated across the batch.

    Attributes:
        index: ``[B*H*W]`` global instance index of every point, -1 where the prior is 0.
        owner: ``[m]`` image index of each instance.
        local: ``[m]`` index of each instance within its image (0..m_b-1).
        count: number of instances ``m`` across the batch.
        max_per_image: largest ``m_b``.
    """

    def __init__(self, prior: Tensor, size: tuple[int, int]) -> None:
        grid = nearest(prior.unsqueeze(1).float(), size).squeeze(1).long()  # [B, H, W]
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
