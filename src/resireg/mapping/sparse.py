"""The occupied voxels of a sparse map: keys, their rows, and the accumulators (:class:`SparseVoxels`).

Storage: rows of dense accumulators in order of first occupation, kept in blocks
(:class:`~resireg.mapping.blocks.RowBlocks`: a block never moves once it holds
:data:`~resireg.mapping.blocks.BLOCK_ROWS` rows, so a map grows by one block at a time, never by
copying itself), and a hash index from the voxels' packed int64 keys (:mod:`resireg.mapping.keys`)
to their rows (:class:`~resireg.mapping.keys.KeyIndex`). ``add`` (the subclasses': the feature
map :class:`~resireg.mapping.voxels.VoxelMap`, the class votes
:class:`~resireg.mapping.labels.LabelVoxelMap`, the compact map
:class:`~resireg.mapping.compact.CompactVoxelMap`) finds the rows of new points by one
``torch.unique`` of their keys and one index lookup per call, gives unseen voxels new rows and
scatters with ``index_add_``: vectorised, no Python loop over points, no pass over the map (the
time to add a frame does not grow with the map), chunked so no temporary exceeds ~8 MB.
Everything stays on the map's device. Results are returned in key order, which is the
lexicographic order of the ``(i, j, k)`` indices (the order of ``numpy.unique(indices,
axis=0)``), whatever order the points came in: the order is sorted once when read and kept until
the map gains a voxel.
"""

from __future__ import annotations

import copy
from typing import TypeVar

import torch
from torch import Tensor

from resireg.mapping.blocks import RowBlocks
from resireg.mapping.keys import (
    MAX_INDEX,
    KeyIndex,
    check_lattice,
    check_voxel_size,
    pack_keys,
    unpack_keys,
    voxel_centres,
    voxel_indices,
)

__all__ = ["SparseVoxels", "check_count"]


def check_count(name: str, value: int) -> int:
    """``value`` when it is an integer >= 1; else a ValueError naming ``name``."""
    if isinstance(value, bool) or not isinstance(value, int) or value < 1:
        raise ValueError(f"{name}={value!r}: expected an integer >= 1")
    return value


_Map = TypeVar("_Map", bound="SparseVoxels")


class SparseVoxels:
    """The occupied voxels' keys, a :class:`~resireg.mapping.keys.KeyIndex` to their rows, and
    the accumulators (:class:`RowBlocks`, named in ``_acc``, given by the subclass); rows are
    numbered in order of first occupation."""

    def __init__(self, voxel_size: float, device: torch.device | str, lattice: str) -> None:
        self.voxel_size = check_voxel_size(voxel_size)
        self.lattice = check_lattice(lattice)
        self.device = torch.device(device)
        self._index = KeyIndex(self.device) if self.device.type != "meta" else None
        self._acc: dict[str, RowBlocks] = {}
        self._sorted: tuple[Tensor, Tensor] | None = None  # (sorted keys, their rows)

    def __len__(self) -> int:
        """Number of occupied voxels."""
        return 0 if self._index is None else self._index.size

    @property
    def _size(self) -> int:
        return len(self)

    def _accumulator(self, name: str, shape: tuple[int, ...], dtype: torch.dtype) -> None:
        self._acc[name] = RowBlocks(shape, dtype, self.device)

    def reserve(self, voxels: int) -> None:
        """Make room for ``voxels`` occupied voxels in all, so adding up to that many allocates
        nothing."""
        for acc in self._acc.values():
            acc.reserve(voxels)

    def clone(self: _Map) -> _Map:
        """An independent copy of the map (same device)."""
        return copy.deepcopy(self)

    @property
    def nbytes(self) -> int:
        """Bytes held by the map's tensors: the accumulators' blocks (their spare rows
        included) and the key index."""
        index = 0 if self._index is None else self._index.nbytes
        return index + sum(acc.nbytes for acc in self._acc.values())

    def _capacity(self) -> int:
        return next(iter(self._acc.values())).capacity

    def _check_points(self, points: Tensor, n: int | None = None) -> Tensor:
        if not isinstance(points, Tensor) or points.ndim != 2 or points.shape[1] != 3:
            shape = tuple(points.shape) if isinstance(points, Tensor) else type(points)
            raise ValueError(f"points of shape {shape}: expected an [N, 3] tensor")
        if not points.is_floating_point():
            raise ValueError(f"points of dtype {points.dtype}: expected floating-point metres")
        if n is not None and points.shape[0] != n:
            raise ValueError(f"points of shape {tuple(points.shape)}: expected {n} rows")
        points = points.to(self.device)
        if not bool(torch.isfinite(points).all()):
            raise ValueError(
                "points contain non-finite values: select the valid ones first "
                "(points[valid] with the mask from unproject / patch_points)"
            )
        return points

    def _rows_of(self, points: Tensor) -> Tensor:
        """Accumulator rows ``[N]`` of the points' voxels; unseen voxels get new rows."""
        return self._rows_of_index(voxel_indices(points, self.voxel_size, self.lattice), points)

    def _rows_of_index(self, index: Tensor, points: Tensor | None = None) -> Tensor:
        """Accumulator rows ``[N]`` of voxel indices ``[N, 3]``; unseen voxels get new rows."""
        keys, inverse = torch.unique(self._keys_of(index, points), return_inverse=True)
        return self._rows_of_keys(keys)[inverse]

    def _keys_of(self, index: Tensor, points: Tensor | None = None) -> Tensor:
        """Packed keys ``[N]`` of voxel indices ``[N, 3]``, or a ValueError naming the range."""
        if index.numel() and int(index.abs().max()) > MAX_INDEX:
            where = (
                f"points with |coordinate| {float(points.abs().max()):g} m"
                if points is not None
                else f"voxel indices up to {int(index.abs().max())}"
            )
            raise ValueError(
                f"{where}: voxel indices beyond +-{MAX_INDEX} "
                f"at voxel_size={self.voxel_size:g} (keys pack 21 bits per axis)"
            )
        return pack_keys(index)

    def _rows_of_keys(self, keys: Tensor) -> Tensor:
        """Accumulator rows ``[K]`` of distinct keys ``[K]``; unseen voxels get new rows (in
        the order of ``keys``)."""
        rows = self._index.lookup(keys)
        new = rows < 0
        if bool(new.any()):
            rows[new] = self._index.insert(keys[new])
            self.reserve(len(self))
            self._sorted = None
        return rows

    def count_new(self, index: Tensor) -> int:
        """How many distinct voxels of the indices ``[N, 3]`` the map does not hold yet (what
        adding them would occupy; nothing is added). Indices beyond the packable range count as
        new."""
        index = index.to(device=self.device, dtype=torch.int64)
        if index.numel() == 0:
            return 0
        inside = (index.abs() <= MAX_INDEX).all(dim=1)
        keys = torch.unique(pack_keys(index[inside]))
        return int((self._index.lookup(keys) < 0).sum()) + int((~inside).sum())

    def _order(self) -> tuple[Tensor, Tensor]:
        """The keys in sorted order and the row of each (sorted when first read after the map
        gained a voxel)."""
        if self._sorted is None:
            if self._index is None:
                empty = torch.empty(0, dtype=torch.int64, device=self.device)
                return empty, empty
            self._sorted = torch.sort(self._index.keys)
        return self._sorted

    @property
    def _rows(self) -> Tensor:
        """``[M]`` the row of each voxel, in :attr:`indices` order."""
        return self._order()[1]

    @property
    def sorted_rows(self) -> Tensor:
        """``[M]`` the row of each voxel, in :attr:`indices` order (sorted once after the map
        gained a voxel)."""
        return self._order()[1]

    def state(self) -> dict[str, Tensor]:
        """The map's content in :attr:`indices` order: ``indices`` ``[M, 3]`` int64 and each
        accumulator's rows (``sums``, ``counts``; ``votes``), on the host: what
        :meth:`load_state` takes back (e.g. through ``safetensors``)."""
        rows = self._rows
        out = {"indices": self.indices.cpu()}
        out.update({name: acc.gather(rows).cpu() for name, acc in self._acc.items()})
        return out

    def load_state(self, state: dict[str, Tensor], ordered: bool = True) -> None:
        """Replace the content with a :meth:`state` of a map of the same kind, voxel size and
        dtype: adding the same points afterwards gives the same sums, bit for bit, as adding
        them to the map that was saved. The accumulators' tensors are used as they are (not
        copied: a memory-mapped file's stay mapped). ``ordered``: the indices must be in
        lexicographic order (a :meth:`state`); else distinct, in any order (rows)."""
        index = state["indices"].to(device=self.device, dtype=torch.int64)
        m = index.shape[0]
        keys = pack_keys(index) if m else torch.empty(0, dtype=torch.int64, device=self.device)
        if ordered and m and not bool((keys[1:] > keys[:-1]).all()):
            raise ValueError("state: indices are not distinct and in lexicographic order")
        if not ordered and m and torch.unique(keys).numel() != m:
            raise ValueError("state: indices are not distinct")
        self._load_rows(keys, {k: v for k, v in state.items() if k != "indices"},
                        state.get("slots"))  # fmt: skip

    def _load_rows(self, keys: Tensor, values: dict[str, Tensor], slots: Tensor | None) -> None:
        """The map of ``keys`` (row order) with the accumulators' ``values`` (row order)."""
        m = keys.numel()
        acc = {}
        for name, old in self._acc.items():
            value = values[name]
            if (
                value.dtype != old.dtype
                or tuple(value.shape[1:]) != old.shape
                or (value.shape[0] != m)
            ):
                raise ValueError(
                    f"state[{name!r}] of shape {tuple(value.shape)} and dtype {value.dtype}: "
                    f"expected {[m, *old.shape]} {old.dtype}"
                )
            acc[name] = RowBlocks(old.shape, old.dtype, self.device)
            if m:
                acc[name].adopt(value.to(self.device))
        self._acc = acc
        self._index = KeyIndex.from_state(keys, None if slots is None else slots.to(self.device))
        self._sorted = None

    @property
    def keys(self) -> Tensor:
        """``[M]`` the packed keys, by row (row order: the order of first occupation)."""
        if self._index is None:
            return torch.empty(0, dtype=torch.int64, device=self.device)
        return self._index.keys

    @property
    def indices(self) -> Tensor:
        """``[M, 3]`` int64 voxel indices, in lexicographic order."""
        return unpack_keys(self._order()[0])

    def centres(self) -> Tensor:
        """``[M, 3]`` float32 voxel centres of :attr:`indices` (:func:`voxel_centres`)."""
        return voxel_centres(self.indices, self.voxel_size, self.lattice)

    def find_rows(self, index: Tensor) -> Tensor:
        """Row ``[N]`` (int64) of each voxel index ``[N, 3]``, ``-1`` where the map has no
        such voxel (no voxel is created)."""
        index = index.to(device=self.device, dtype=torch.int64)
        out = torch.full((index.shape[0],), -1, dtype=torch.int64, device=self.device)
        inside = (index.abs() <= MAX_INDEX).all(dim=1)
        if len(self) and bool(inside.any()):
            out[inside] = self._index.lookup(pack_keys(index[inside]))
        return out

    def find(self, index: Tensor) -> Tensor:
        """Position in :attr:`indices` order ``[N]`` (int64) of each voxel index ``[N, 3]``,
        ``-1`` where the map has no such voxel (no voxel is created)."""
        rows = self.find_rows(index)
        if not len(self):
            return rows
        rank = torch.empty(len(self), dtype=torch.int64, device=self.device)
        rank[self._rows] = torch.arange(len(self), device=self.device)
        return torch.where(rows >= 0, rank[rows.clamp_min(0)], -1)

    def rows_in_box(self, lo: Tensor, hi: Tensor) -> Tensor:
        """Rows (sorted) of the occupied voxels with indices in ``[lo, hi]`` per axis
        (``[3]`` int64 each). A box of at most four times as many cells as the map holds
        voxels is enumerated and looked up (the map itself is not read); a larger one is
        answered from the keys."""
        lo = lo.to(device=self.device, dtype=torch.int64).clamp(-MAX_INDEX, MAX_INDEX)
        hi = hi.to(device=self.device, dtype=torch.int64).clamp(-MAX_INDEX, MAX_INDEX)
        empty = torch.empty(0, dtype=torch.int64, device=self.device)
        if not len(self) or bool((hi < lo).any()):
            return empty
        sizes = (hi - lo + 1).tolist()
        cells = sizes[0] * sizes[1] * sizes[2]
        if cells > 4 * len(self):
            index = unpack_keys(self.keys)
            inside = ((index >= lo) & (index <= hi)).all(dim=1)
            return inside.nonzero().squeeze(1)
        found = []
        plane = sizes[1] * sizes[2]
        step = max(1, (1 << 20) // plane)  # whole planes of the first axis per lookup
        for start in range(0, sizes[0], step):
            axes = [torch.arange(int(lo[0]) + start, int(lo[0]) + min(sizes[0], start + step),
                                 device=self.device)]  # fmt: skip
            axes += [torch.arange(int(lo[i]), int(hi[i]) + 1, device=self.device) for i in (1, 2)]
            grid = torch.stack(torch.meshgrid(*axes, indexing="ij"), dim=-1).reshape(-1, 3)
            rows = self._index.lookup(pack_keys(grid))
            found.append(rows[rows >= 0])
        return torch.sort(torch.cat(found)).values if found else empty

    def tensors(self) -> dict[str, list[Tensor]]:
        """The map's tensors in row order, each as the list of its blocks' used rows (views,
        no copy): ``keys``, ``slots`` (the key index) and the accumulators; what
        :meth:`load_tensors` takes back."""
        m = len(self)
        out: dict[str, list[Tensor]] = {
            "keys": [self.keys],
            "slots": [self._index.state()["slots"]],
        }
        for name, acc in self._acc.items():
            out[name] = [v for _, v in acc.spans(m)] or [acc.rows(0)]
        return out

    def load_tensors(self, tensors: dict[str, Tensor]) -> None:
        """Replace the content with :meth:`tensors` read back (used in place)."""
        keys = tensors["keys"].to(device=self.device, dtype=torch.int64)
        if keys.numel() and torch.unique(keys).numel() != keys.numel():
            raise ValueError("keys are not distinct")
        self._load_rows(keys, {k: tensors[k] for k in self._acc}, tensors.get("slots"))
