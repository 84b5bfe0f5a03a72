"""The exact storage (``storage=exact``): running feature sums per voxel and a mean colour map.

:class:`ExactStorage` keeps a :class:`~resireg.mapping.voxels.VoxelMap` of ``sum_dtype`` sums
(float64 by default: a voxel's mean does not depend on how its points were split or ordered,
up to float64 rounding) and, with ``colour=True``, a second one of colour sums. Queries score
the unit means in float64 (exact).

Memory bound (``exact``): the map holds, per occupied voxel, ``s D + 8`` bytes of accumulators
(``s`` = 8 for float64 sums, 4 for ``sum_dtype="float32"``), 8 bytes of key and 5.7 to 11.4 of
hash slot, and, with ``colour=True``, ``8 x 3 + 8`` bytes of colour sums and their own key and
slot; the accumulators' last block holds fewer than :data:`~resireg.mapping.blocks.BLOCK_ROWS`
spare rows (:attr:`MapStorage.nbytes` counts them). ``max_voxels`` caps the occupied voxels:
a window that would exceed it raises :class:`MapFullError` *before* anything of it is added, so
the map stays as it was and can be saved. At 5 cm and D = 512 one million voxels (a large
building floor) take ~4.2 GB with float64 sums, ~2.1 GB with float32 ones and ~0.3 GB
``compact`` (docs/benchmarks.md).
"""

from __future__ import annotations

from typing import Any

import torch
from torch import Tensor

from resireg.mapping.lifting import LiftedPoints
from resireg.mapping.query import classify as classify_features
from resireg.mapping.storage.base import MapStorage
from resireg.mapping.voxels import SUM_DTYPES, VoxelMap

__all__ = ["ExactStorage"]


class ExactStorage(MapStorage):
    """Feature sums of ``sum_dtype`` and colour sums (:class:`MapStorage`'s arguments;
    ``compact`` is not read)."""

    def __init__(self, voxel_size: float, lattice: str, device: torch.device, colour: bool,
                 sum_dtype: str, compact: Any = None) -> None:  # fmt: skip
        super().__init__(voxel_size, lattice, device, colour, sum_dtype, compact)
        self.sum_dtype = sum_dtype
        if self.keeps_colour:
            self.colours = VoxelMap(self.voxel_size, 3, self.device, self.lattice)

    def make_voxels(self) -> VoxelMap:
        return VoxelMap(self.voxel_size, self.dim, self.device, self.lattice,
                        SUM_DTYPES[self.sum_dtype])  # fmt: skip

    def add(self, window: LiftedPoints, probe: Tensor | None) -> None:
        window.add_to(self.voxels, window.features)
        if window.colours is not None and self.colours is not None:
            window.add_to(self.colours, window.colours)

    def bytes_per_voxel(self, dim: int | None = None) -> int:
        d = dim or self.stored_dim or 0
        size = 8 + 8 + d * SUM_DTYPES[self.sum_dtype].itemsize + 8
        return size + (8 + 8 + 3 * 8 + 8 if self.colours is not None else 0)

    def mean_colours(self) -> Tensor:
        n = len(self)
        if self.voxels is None or self.colours is None or not len(self.colours):
            return torch.zeros(n, 3, dtype=torch.uint8)
        at = self.colours.find(self.voxels.indices)
        mean = self.colours.means().float()
        out = torch.zeros(n, 3, device=mean.device)
        out[at >= 0] = mean[at[at >= 0]]
        return (out.clamp(0, 1) * 255).round().to(torch.uint8).cpu()

    def subsample(self, stride: int) -> tuple[Tensor, Tensor]:
        if stride == 1 and self.voxels is not None:
            return self.voxels.features()
        return super().subsample(stride)

    def similarities(self, queries: Tensor) -> Tensor:
        _, feats = self.features()
        return feats @ queries.to(feats.device).T

    def classify(self, prototypes: Tensor, threshold: float | None, denoise: float | None,
                 none: int) -> Tensor:  # fmt: skip
        _, feats = self.features()
        return classify_features(feats, prototypes.to(feats.device), threshold, denoise,
                                 none=none)  # fmt: skip

    def candidates(
        self, q: Tensor, k: int, approx: tuple[Tensor, Tensor] | None
    ) -> tuple[Tensor, Tensor]:
        """Every row, scored in float64 in chunks (:meth:`VoxelMap.all_scores`)."""
        rows = torch.arange(len(self.voxels), device=self.device)
        return rows, self.voxels.all_scores(q)[:, 0]
