"""The compact storage (``storage=compact``): low-precision unit features, optionally projected.

:class:`CompactStorage` keeps a :class:`~resireg.mapping.compact.CompactVoxelMap` (its colours
included) and, with ``compact.dim`` below the features' dimension, a basis ``[D, k]``
(:mod:`resireg.mapping.basis`): given (``compact.basis``) or fitted once on the first
``compact.basis_rows`` features. Until it is fitted the windows wait (the map reads as empty);
a save fits it on what waits (:meth:`~CompactStorage.fit_pending`). Queries are projected by
the basis and renormalised (RayFronts' compressed query); top-k scores every voxel in low
precision and re-scores in float64 the candidates within the error bound. About 290 bytes per
voxel at 128 channels, against ~4,170 for float64 sums of 512 (docs/benchmarks.md).
"""

from __future__ import annotations

from collections.abc import Mapping
from typing import Any

import torch
import torch.nn.functional as F
from torch import Tensor

from resireg.mapping.basis import fit_basis, load_basis, tensor_sha256
from resireg.mapping.compact import STORED_DTYPES, CompactSettings, CompactVoxelMap
from resireg.mapping.keys import pack_keys
from resireg.mapping.lifting import LiftedPoints
from resireg.mapping.storage.base import MapStorage
from resireg.specs.mapping import map_errors

__all__ = ["CompactStorage"]


class CompactStorage(MapStorage):
    """Unit features in ``compact.dtype``, projected by a basis when ``compact.dim`` is below the
    features' dimension (:class:`MapStorage`'s arguments; ``sum_dtype`` is not read)."""

    def __init__(self, voxel_size: float, lattice: str, device: torch.device, colour: bool,
                 sum_dtype: str = "float64", compact: Any = None) -> None:  # fmt: skip
        self.compact = CompactSettings.of(compact)
        errors = map_errors({"compact": self.compact.as_dict()})
        if errors:
            raise ValueError("; ".join(errors))
        super().__init__(voxel_size, lattice, device, colour, sum_dtype, compact)
        self._pending: list[LiftedPoints] = []  # windows waiting for the basis
        self._pending_rows: list[Tensor] = []
        self._pending_keys: Tensor | None = None
        if self.compact.dim is not None and self.compact.basis:
            self.set_basis(load_basis(self.compact.basis))

    def make_voxels(self) -> CompactVoxelMap:
        c = self.compact
        return CompactVoxelMap(self.voxel_size, self.stored_dim, self.device, self.lattice,
                               STORED_DTYPES[c.dtype], self.keeps_colour, c.hot_voxels)  # fmt: skip

    # ------------------------------------------------------------------ the basis
    @property
    def stored_dim(self) -> int | None:
        if self.basis is not None:
            return int(self.basis.shape[1])
        if self.compact.dim is not None and self.dim is not None:
            return min(self.compact.dim, self.dim)
        return self.dim

    @property
    def waiting(self) -> bool:
        c = self.compact
        return (
            c.dim is not None and self.basis is None and self.dim is not None and c.dim < self.dim
        )

    @property
    def pending_voxels(self) -> int:
        return 0 if self._pending_keys is None else int(self._pending_keys.numel())

    def start(self, dim: int) -> None:
        if self.basis is not None and self.basis.shape[0] != dim:
            raise ValueError(f"features of {dim} channels: the basis projects "
                             f"{self.basis.shape[0]}")  # fmt: skip
        super().start(dim)

    def set_basis(self, basis: Tensor) -> None:
        if self.compact.dim is None:
            super().set_basis(basis)
        if len(self) or self._pending:
            raise ValueError("set_basis(): the map already holds features")
        if basis.ndim != 2 or basis.shape[1] != self.compact.dim:
            raise ValueError(f"basis of shape {tuple(basis.shape)}: expected [D, "
                             f"compact.dim={self.compact.dim}]")  # fmt: skip
        if self.dim is not None and basis.shape[0] != self.dim:
            raise ValueError(f"basis of shape {tuple(basis.shape)}: the map's features are "
                             f"{self.dim}-d")  # fmt: skip
        self.basis = basis.to(device=self.device, dtype=torch.float32).contiguous()
        self.basis_sha256 = tensor_sha256(self.basis)

    def adopt_basis(self, other: MapStorage) -> None:
        if self.voxels is None and other.voxels is not None:
            if self.basis is None and other.basis is not None:
                self.set_basis(other.basis)

    def fit_pending(self) -> None:
        """Fit the basis on the waiting windows' features (:func:`~resireg.mapping.basis.fit_basis`)
        and fuse them."""
        if not self._pending:
            return
        basis = fit_basis(torch.cat(self._pending_rows), self.compact.dim)
        pending = self._pending
        self._pending, self._pending_rows, self._pending_keys = [], [], None
        self.set_basis(basis)
        self.voxels = self.make_voxels()
        for window in pending:
            self._apply(window)

    def project(self, queries: Tensor) -> Tensor:
        """Queries in the basis's space, each renormalised (the cosine there, as RayFronts
        queries its compressed map); unchanged without a basis."""
        if self.basis is None:
            return queries
        return F.normalize(queries.to(self.basis.device).float() @ self.basis, dim=-1)

    def restore_basis(self, record: Mapping[str, Any], tensors: Mapping[str, Tensor]) -> None:
        if "basis" not in tensors:
            super().restore_basis(record, tensors)
            return
        basis, k = tensors["basis"], self.compact.dim
        if basis.ndim != 2 or tuple(basis.shape) != (self.dim, k):
            raise ValueError(f"basis of shape {list(basis.shape)}: expected [dim="
                             f"{self.dim}, settings.compact.dim={k}]")  # fmt: skip
        basis = basis.to(self.device, torch.float32)
        if tensor_sha256(basis) != record.get("basis_sha256"):
            raise ValueError("its basis does not match basis_sha256")
        self.basis, self.basis_sha256 = basis, record["basis_sha256"]

    # ------------------------------------------------------------------ building
    def count_new(self, probe: Tensor) -> int:
        if self.voxels is not None:
            return self.voxels.count_new(probe)
        keys = torch.unique(pack_keys(probe.to(torch.int64)))
        held = self._pending_keys
        if held is None or not held.numel():
            return int(keys.numel())
        pos = torch.searchsorted(held, keys).clamp_max(held.numel() - 1)
        return int((held[pos] != keys).sum())

    def add(self, window: LiftedPoints, probe: Tensor | None) -> None:
        if not self.waiting:
            self._apply(window)
            return
        # kept until the basis is fitted (now, once the waiting windows hold basis_rows features)
        self._pending.append(window)
        self._pending_rows.append(window.distinct_features())
        keys = torch.unique(pack_keys(probe.to(torch.int64)))
        held = self._pending_keys
        self._pending_keys = keys if held is None else torch.unique(torch.cat([held, keys]))
        if sum(r.shape[0] for r in self._pending_rows) >= self.compact.basis_rows:
            self.fit_pending()

    def _apply(self, window: LiftedPoints) -> None:
        window = window.projected(self.basis)
        window.add_to(self.voxels, window.features, window.colours)

    def bytes_per_voxel(self, dim: int | None = None) -> int:
        d = dim or self.stored_dim or 0
        if self.basis is None and self.compact.dim is not None:
            d = min(d, self.compact.dim)
        size = 8 + 8 + d * STORED_DTYPES[self.compact.dtype].itemsize + 4 + 4
        return size + (3 + 4 if self.keeps_colour else 0)

    # ------------------------------------------------------------------ reading
    def mean_colours(self) -> Tensor:
        if self.voxels is None:
            return torch.zeros(0, 3, dtype=torch.uint8)
        return self.voxels.mean_colours()

    def similarities(self, queries: Tensor) -> Tensor:
        """Accumulated in float32 from the stored features (:meth:`CompactVoxelMap.approx_scores`)."""
        scores, _ = self.voxels.approx_scores(queries, fast=False)
        return scores[self.voxels.sorted_rows]

    def classify(self, prototypes: Tensor, threshold: float | None, denoise: float | None,
                 none: int) -> Tensor:  # fmt: skip
        """The rule's labels in float64 over the stored features, from one float32 pass
        (:meth:`CompactVoxelMap.classify`): no float32 copy of the whole map."""
        if self.voxels is None:
            raise ValueError("the map is empty: add frames first")
        return self.voxels.classify(prototypes, threshold, denoise, none=none)

    def joint_scores(self, queries: Tensor) -> tuple[Tensor, Tensor] | None:
        if self.voxels is None or not len(self.voxels):
            return None
        return self.voxels.approx_scores(queries.to(self.device))

    def candidates(
        self, q: Tensor, k: int, approx: tuple[Tensor, Tensor] | None
    ) -> tuple[Tensor, Tensor]:
        """The voxels within ``2 e`` of the ``k``-th best low-precision score (``e``: its error
        bound), re-scored in float64: no voxel outside can be among the best."""
        if approx is None:
            scored, bounds = self.voxels.approx_scores(q)
            approx = (scored[:, 0], bounds[0])
        low, bound = approx
        kth = torch.topk(low, min(k, low.shape[0])).values[-1].double()
        rows = (low.double() >= kth - 2 * bound.double()).nonzero().squeeze(1)
        return rows, self.voxels.exact_scores(rows, q)[:, 0]
