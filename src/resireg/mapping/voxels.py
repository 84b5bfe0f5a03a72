"""The feature map: running feature sums per occupied voxel (:class:`VoxelMap`).

The voxels, their keys and rows are :class:`~resireg.mapping.sparse.SparseVoxels`' (the lattice:
:mod:`resireg.mapping.keys`); this module adds the float64 (or float32) feature sums and point
counts, fed by points (:meth:`VoxelMap.add`) or by pixel pairs (:meth:`VoxelMap.add_pairs`), and
read as unit means, scores against queries, and merged from another map.
"""

from __future__ import annotations

import torch
from torch import Tensor

from resireg.mapping.blocks import RowBlocks
from resireg.mapping.sparse import SparseVoxels, check_count
from resireg.specs.mapping import SUM_DTYPES as SUM_DTYPE_NAMES

__all__ = ["SUM_DTYPES", "VoxelMap"]

# Elements per float64 temporary in add, add_pairs and features (8 MB): glibc serves such blocks
# from its heap once freed, while one over its 32 MB mmap threshold is page-faulted afresh on
# every call, which on a 512-d frame costs more than the additions (docs/benchmarks.md).
_CHUNK_ELEMENTS = 1 << 20
# Elements per float64 chunk of add_pairs' gathered features (2 MB: 512 rows of 512; 1 MB chunks
# were 10-15% slower here, 4 MB ones 5-40% slower: docs/benchmarks.md).
_PAIR_CHUNK_ELEMENTS = 1 << 18


#: The dtypes of :class:`VoxelMap`'s feature sums, by name.
SUM_DTYPES = {name: getattr(torch, name) for name in SUM_DTYPE_NAMES}


class VoxelMap(SparseVoxels):
    """A sparse voxel map of running feature sums (a map that grows frame by frame).

    Per occupied voxel it keeps the float64 sum of the features of every point ever added and
    their count. Summing float32 features in float64 (the default ``dtype``) makes the mean
    independent of how points were split across :meth:`add` calls and of their order up to
    float64 rounding (relative ``~1e-16``, far below the float32 result's resolution).
    ``dtype=torch.float32`` halves the memory of a long recording at a relative rounding of
    ``~1e-7 x`` the points per voxel in the sums. Memory: ``(s D + 8)`` bytes per voxel for the
    accumulators (``s`` = 8 or 4 bytes by ``dtype``) plus 8 for its key and 5.7 to 11.4 for its
    slot in the key index, and the spare rows of the last block (fewer than
    :data:`BLOCK_ROWS`; :attr:`nbytes` counts them).

    Args:
        voxel_size: voxel edge in metres (> 0).
        dim: feature dimension ``D``.
        device: where the map's tensors live (points and features are moved there).
        lattice: ``"round"`` or ``"floor"`` (module docstring).
        dtype: ``torch.float64`` (default) or ``torch.float32``, the dtype of the sums.
    """

    def __init__(
        self,
        voxel_size: float,
        dim: int,
        device: torch.device | str = "cpu",
        lattice: str = "round",
        dtype: torch.dtype = torch.float64,
    ) -> None:
        super().__init__(voxel_size, device, lattice)
        self.dim = check_count("dim", dim)
        if dtype not in SUM_DTYPES.values():
            raise ValueError(f"dtype={dtype}: expected one of {list(SUM_DTYPES.values())}")
        self.dtype = dtype
        self._accumulator("sums", (self.dim,), dtype)
        self._accumulator("counts", (), torch.int64)

    def __repr__(self) -> str:
        return (
            f"VoxelMap(voxel_size={self.voxel_size}, dim={self.dim}, device={self.device}, "
            f"lattice={self.lattice!r}, voxels={len(self)})"
        )

    @property
    def _sums(self) -> RowBlocks:  # [capacity, D] float64 feature sums
        return self._acc["sums"]

    @property
    def _counts(self) -> RowBlocks:  # [capacity] int64 points per voxel
        return self._acc["counts"]

    def _add_rows(self, rows: Tensor, step: int, values) -> None:
        """``sums[rows[i]] += values(positions)[i]`` in chunks of ``step`` positions, block by
        block of the accumulator (one stable split per call: a row's additions keep their
        order, so the sums equal those of one tensor bit for bit). ``values`` turns a slice or
        an index tensor of positions into their features in the sums' dtype."""
        for b, pos, local in self._sums._split(rows):
            block = self._sums.blocks[b]
            n = local.numel()
            for start in range(0, n, step):
                where = slice(start, start + step) if pos is None else pos[start : start + step]
                block.index_add_(0, local[start : start + step], values(where))

    def add(self, points: Tensor, features: Tensor) -> None:
        """Add points and their features to the running sums.

        Args:
            points: ``[N, 3]`` world coordinates in metres (finite; select valid ones first).
            features: ``[N, D]`` features (any floating dtype; summed in float64).
        """
        if not isinstance(features, Tensor) or features.ndim != 2:
            shape = tuple(features.shape) if isinstance(features, Tensor) else type(features)
            raise ValueError(f"features of shape {shape}: expected an [N, {self.dim}] tensor")
        if features.shape[1] != self.dim:
            raise ValueError(
                f"features of shape {tuple(features.shape)}: the map has dim={self.dim}"
            )
        if not features.is_floating_point():
            raise ValueError(f"features of dtype {features.dtype}: expected floating point")
        points = self._check_points(points, features.shape[0])
        if points.shape[0] == 0:
            return
        rows = self._rows_of(points)
        self._counts.index_add_(rows, torch.ones_like(rows))
        features = features.to(self.device)
        self._add_rows(rows, max(1, _CHUNK_ELEMENTS // self.dim),
                       lambda at: features[at].to(dtype=self.dtype))  # fmt: skip

    def add_pairs(self, index: Tensor, counts: Tensor, features: Tensor, source: Tensor) -> None:
        """Add points given as (voxel, feature) pairs with multiplicities.

        Pair ``i`` stands for ``counts[i]`` points of voxel ``index[i]`` that all carry the
        feature ``features[source[i]]`` (e.g. the pixels of one patch that fall in one voxel,
        :func:`resireg.mapping.pixel_pairs`): the voxel's sum grows by ``counts[i] *
        features[source[i]]`` and its count by ``counts[i]``. For float32 features the product
        is exact in float64 (24 + 31 bits), so the map equals the one ``add`` builds from the
        points one by one, up to the order of the float64 sums.

        Args:
            index: ``[M, 3]`` int64 voxel indices (this map's lattice, :func:`voxel_indices`).
            counts: ``[M]`` integer multiplicities (>= 1).
            features: ``[P, D]`` features (any floating dtype).
            source: ``[M]`` int64 rows of ``features``.
        """
        if not isinstance(features, Tensor) or features.ndim != 2 or features.shape[1] != self.dim:
            shape = tuple(features.shape) if isinstance(features, Tensor) else type(features)
            raise ValueError(f"features of shape {shape}: expected [P, {self.dim}]")
        if not features.is_floating_point():
            raise ValueError(f"features of dtype {features.dtype}: expected floating point")
        m = index.shape[0]
        if index.shape != (m, 3) or counts.shape != (m,) or source.shape != (m,):
            raise ValueError(
                f"index {tuple(index.shape)}, counts {tuple(counts.shape)}, source "
                f"{tuple(source.shape)}: expected [M, 3], [M], [M]"
            )
        if m == 0:
            return
        keys = self._keys_of(index.to(device=self.device, dtype=torch.int64))
        # The pairs in voxel order (stable: a voxel's pairs keep their order, so its sum adds
        # them in the same sequence as in the given order, bit for bit): the sort doubles as
        # torch.unique's, and the scatter below then meets each map row in one run of pairs
        # instead of at random, so a row is read from memory once per call, not once per pair.
        keys, order = torch.sort(keys, stable=True)
        first = torch.ones_like(keys, dtype=torch.bool)
        first[1:] = keys[1:] != keys[:-1]
        rows = self._rows_of_keys(keys[first])[torch.cumsum(first, 0) - 1]
        counts = counts.to(device=self.device, dtype=torch.int64)[order]
        source = source.to(self.device)[order]
        self._counts.index_add_(rows, counts)
        # Features are gathered in their own dtype and widened per chunk, never as a whole
        # [P, D] float64 copy (35 MB at 8,640 x 512: one page-faulted block per call), in
        # chunks small enough to stay in the cache between the gather, the product and the
        # scatter (docs/benchmarks.md).
        features = features.to(self.device)

        def values(at):
            chunk = features.index_select(0, source[at]).to(torch.float64)
            return chunk.mul_(counts[at, None]).to(self.dtype)

        self._add_rows(rows, max(1, _PAIR_CHUNK_ELEMENTS // self.dim), values)

    @property
    def counts(self) -> Tensor:
        """``[M]`` int64 points per voxel, in the order of :attr:`indices`."""
        return self._counts.gather(self._rows)

    def means(self) -> Tensor:
        """``[M, D]`` float64 mean feature per voxel (not normalised), in :attr:`indices` order."""
        rows = self._rows
        return self._sums.gather(rows).double() / self._counts.gather(rows)[:, None]

    def features(self) -> tuple[Tensor, Tensor]:
        """Voxel centres ``[M, 3]`` and L2-normalised mean features ``[M, D]``, both float32.

        ``mean / max(||mean||, 1e-12)`` computed in float64 (a zero mean stays zero), in row
        chunks, so a query needs the float32 result plus one ~8 MB temporary, not a float64
        copy of the map.
        """
        unit = torch.empty(self._size, self.dim, dtype=torch.float32, device=self.device)
        step = max(1, _CHUNK_ELEMENTS // self.dim)
        order = self._rows
        for start in range(0, self._size, step):
            rows = order[start : start + step]
            mean = self._sums.gather(rows).double() / self._counts.gather(rows)[:, None]
            unit[start : start + step] = mean / mean.norm(dim=1, keepdim=True).clamp_min(1e-12)
        return self.centres(), unit

    def unit_rows(self, rows: Tensor) -> Tensor:
        """``[R, D]`` float32 unit mean features of ``rows``, computed as :meth:`features`
        computes them (the same values, bit for bit)."""
        mean = self._sums.gather(rows).double() / self._counts.gather(rows)[:, None]
        return (mean / mean.norm(dim=1, keepdim=True).clamp_min(1e-12)).to(torch.float32)

    def exact_scores(self, rows: Tensor, queries: Tensor) -> Tensor:
        """``[R, T]`` float64 dot products of the unit features of ``rows`` (as
        :meth:`features` gives them) with ``queries`` ``[T, D]``."""
        return self.unit_rows(rows).double() @ queries.to(self.device).double().T

    def all_scores(self, queries: Tensor) -> Tensor:
        """``[M, T]`` float64 scores of every voxel in row order: :meth:`exact_scores` of all
        rows, computed block by block (no gather)."""
        q = queries.to(self.device).double().T
        out = torch.empty(len(self), q.shape[1], dtype=torch.float64, device=self.device)
        spans = zip(self._sums.spans(len(self)), self._counts.spans(len(self)), strict=True)
        for (start, sums), (_, counts) in spans:
            step = max(1, _CHUNK_ELEMENTS // self.dim)
            for s in range(0, sums.shape[0], step):
                mean = sums[s : s + step].double() / counts[s : s + step, None]
                unit = (mean / mean.norm(dim=1, keepdim=True).clamp_min(1e-12)).float()
                out[start + s : start + s + unit.shape[0]] = unit.double() @ q
        return out

    def merge_from(self, other: VoxelMap, keys: Tensor | None = None) -> None:
        """Add ``other``'s sums and counts to this map, in place, block by block of
        ``other`` (no copy of either map); ``keys``: the key here of each of ``other``'s rows
        (``None``: its own; re-keyed voxels that meet in one voxel add up)."""
        if other.dim != self.dim or other.dtype != self.dtype:
            raise ValueError(f"merge: a map of dim {other.dim} {other.dtype} into one of dim "
                             f"{self.dim} {self.dtype}")  # fmt: skip
        m = len(other)
        keys = other.keys if keys is None else keys.to(self.device)
        counts = list(other._counts.spans(m))
        for (start, sums), (_, n) in zip(other._sums.spans(m), counts, strict=True):
            k = keys[start : start + sums.shape[0]]
            uniq, inv = torch.unique(k, return_inverse=True)
            rows = self._rows_of_keys(uniq)[inv]
            self._counts.index_add_(rows, n.to(self.device))
            step = max(1, _CHUNK_ELEMENTS // self.dim)
            for s in range(0, rows.numel(), step):
                chunk = sums[s : s + step].to(device=self.device, dtype=self.dtype)
                self._sums.index_add_(rows[s : s + step], chunk)
