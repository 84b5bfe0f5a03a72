"""Sparse voxel maps: running feature sums (:class:`VoxelMap`) and class votes (:class:`LabelVoxelMap`).

A point ``p`` (metres) falls in the voxel of an integer index per axis, by one of two lattices
(:data:`LATTICES`, docs/method.md#the-voxel-map):

- ``"round"`` (the default): index ``round(p / voxel_size)`` (half to even, as ``torch.round``),
  centre ``index * voxel_size``: RayFronts' ``geometry3d.pointcloud_to_sparse_voxels``, whose
  evaluation (``scripts/semseg_eval.py``) the paper's Table 2 follows;
- ``"floor"``: index ``floor(p / voxel_size)``, centre ``(index + 0.5) * voxel_size``.

The index is computed in float64 (``points.double() / voxel_size``). A map stores, for the
occupied voxels only, a per-voxel accumulator (feature sum and point count, or class votes), so
memory grows with the occupied voxels and a map can grow frame by frame.

Storage: rows of dense accumulators in order of first occupation, kept in blocks
(:class:`RowBlocks`: a block never moves once it holds :data:`BLOCK_ROWS` rows, so a map grows
by one block at a time, never by copying itself), and a hash index from the voxels' packed
int64 keys (:mod:`resireg.mapping.keys`) to their rows (:class:`~resireg.mapping.keys.KeyIndex`).
``add`` finds the rows of new points by one ``torch.unique`` of their keys and one index lookup
per call, gives unseen voxels new rows and scatters with ``index_add_``: vectorised, no Python
loop over points, no pass over the map (the time to add a frame does not grow with the map),
chunked so no temporary exceeds ~8 MB. Everything stays on the map's device. Results are
returned in key order, which is the lexicographic order of the ``(i, j, k)`` indices (the order
of ``numpy.unique(indices, axis=0)``), whatever order the points came in: the order is sorted
once when read and kept until the map gains a voxel.
"""

from __future__ import annotations

import copy
import math
from typing import TypeVar

import torch
from torch import Tensor

from resireg.mapping.keys import KEY_BITS, MAX_INDEX, KeyIndex, pack_keys, unpack_keys
from resireg.specs.mapping import LATTICES
from resireg.specs.mapping import SUM_DTYPES as SUM_DTYPE_NAMES

__all__ = [
    "BLOCK_ROWS",
    "LATTICES",
    "RowBlocks",
    "SUM_DTYPES",
    "SparseVoxels",
    "VoxelMap",
    "LabelVoxelMap",
    "check_lattice",
    "check_voxel_size",
    "lattice_transform",
    "transform_keys",
    "voxel_centres",
    "voxel_indices",
]

# Elements per float64 temporary in add, add_pairs and features (8 MB): glibc serves such blocks
# from its heap once freed, while one over its 32 MB mmap threshold is page-faulted afresh on
# every call, which on a 512-d frame costs more than the additions (docs/benchmarks.md).
_CHUNK_ELEMENTS = 1 << 20
# Elements per float64 chunk of add_pairs' gathered features (2 MB: 512 rows of 512; 1 MB chunks
# were 10-15% slower here, 4 MB ones 5-40% slower: docs/benchmarks.md).
_PAIR_CHUNK_ELEMENTS = 1 << 18


#: The dtypes of :class:`VoxelMap`'s feature sums, by name.
SUM_DTYPES = {name: getattr(torch, name) for name in SUM_DTYPE_NAMES}


def check_lattice(lattice: str) -> str:
    if lattice not in LATTICES:
        raise ValueError(f"lattice={lattice!r}: expected one of {LATTICES}")
    return lattice


def lattice_index(scaled: Tensor, lattice: str = "round") -> Tensor:
    """Integer voxel indices of coordinates already divided by the voxel size (float64):
    ``round`` (half to even) or ``floor``, as int64."""
    op = torch.round if check_lattice(lattice) == "round" else torch.floor
    index = op(scaled)
    # Refused before the int64 cast: a float beyond int64's range casts to -2**63 (or
    # wraps), which would pass a range check on the integers and pack into a wrong voxel.
    if index.numel() and not bool((index.abs() <= MAX_INDEX).all()):
        bad = index[~(index.abs() <= MAX_INDEX)]
        raise ValueError(
            f"voxel indices beyond +-{MAX_INDEX} (up to {float(bad.abs().max()):g}, or "
            f"non-finite; keys pack {KEY_BITS} bits per axis): points that far (e.g. from "
            "out-of-range depth) cannot be mapped; drop them first"
        )
    return index.to(torch.int64)


def voxel_indices(points: Tensor, voxel_size: float, lattice: str = "round") -> Tensor:
    """Integer voxel indices ``[N, 3]`` int64 of ``points`` ``[N, 3]``: ``round(points /
    voxel_size)`` or ``floor(...)`` by ``lattice`` (float64 division; module docstring)."""
    return lattice_index(points.to(torch.float64) / voxel_size, lattice)


def voxel_centres(index: Tensor, voxel_size: float, lattice: str = "round") -> Tensor:
    """``[M, 3]`` float32 centres of voxel indices ``[M, 3]``.

    ``round``: ``index * voxel_size`` computed in float32 (``float32(index) * voxel_size``), as
    RayFronts' ``pointcloud_to_sparse_voxels`` computes its centres, so the two give the same
    float32 values and nearest-neighbour ties between lattice points resolve alike.
    ``floor``: ``(index + 0.5) * voxel_size`` in float64, then rounded to float32.
    """
    if check_lattice(lattice) == "round":
        return index.to(torch.float32) * voxel_size
    return ((index.to(torch.float64) + 0.5) * voxel_size).to(torch.float32)


def lattice_transform(transform, voxel_size: float) -> tuple[Tensor, Tensor] | None:
    """``(R, t)`` (int64 ``[3, 3]``, ``[3]``) when the rigid ``transform`` ``[4, 4]`` keeps the
    voxel lattice: its rotation a signed permutation (multiples of 90 degrees about the axes,
    determinant +1) and its translation whole voxels (within 1e-6 of a voxel); else ``None``."""
    t = torch.as_tensor(transform, dtype=torch.float64)
    if t.shape != (4, 4) or not bool(torch.isfinite(t).all()):
        raise ValueError(f"transform of shape {tuple(t.shape)}: expected a finite [4, 4] matrix")
    rot, shift = t[:3, :3], t[:3, 3] / voxel_size
    r = rot.round()
    perm = (r.abs().sum(0) == 1).all() and (r.abs().sum(1) == 1).all()
    whole = (shift - shift.round()).abs().max() <= 1e-6
    if not (perm and whole and (rot - r).abs().max() <= 1e-9 and torch.det(r) > 0):
        return None
    return r.to(torch.int64), shift.round().to(torch.int64)


def transform_keys(keys: Tensor, transform, voxel_size: float, lattice: str = "round") -> Tensor:
    """The key of each voxel (``[M]`` packed keys) after the rigid ``transform`` ``[4, 4]``.

    A transform that keeps the lattice (:func:`lattice_transform`) maps each voxel onto one
    voxel, computed on the integers: ``R i + t`` (``round`` lattice), ``R i + t + (R 1 - 1) /
    2`` (``floor``: the centre ``i + 1/2`` turned). Any other moves the voxel's centre (float64)
    and takes the voxel it falls in (an approximation of transforming the points themselves)."""
    index = unpack_keys(keys)
    exact = lattice_transform(transform, voxel_size)
    if exact is not None:
        r, t = (x.to(keys.device) for x in exact)
        moved = index @ r.T + t
        if check_lattice(lattice) == "floor":
            moved = moved + (r.sum(dim=1) - 1) // 2
        return pack_keys(moved)
    m = torch.as_tensor(transform, dtype=torch.float64, device=keys.device)
    shift = 0.0 if check_lattice(lattice) == "round" else 0.5
    centres = (index.to(torch.float64) + shift) * voxel_size
    return pack_keys(voxel_indices(centres @ m[:3, :3].T + m[:3, 3], voxel_size, lattice))


def check_voxel_size(voxel_size: float) -> float:
    """``voxel_size`` as a float when it is a finite number > 0 (metres); else a ValueError."""
    try:
        v = float(voxel_size)
    except (TypeError, ValueError):
        v = math.nan
    if not (math.isfinite(v) and v > 0) or isinstance(voxel_size, bool):
        raise ValueError(f"voxel_size={voxel_size!r}: expected a finite number > 0 (metres)")
    return v


def _check_count(name: str, value: int) -> int:
    if isinstance(value, bool) or not isinstance(value, int) or value < 1:
        raise ValueError(f"{name}={value!r}: expected an integer >= 1")
    return value


#: Rows per block of :class:`RowBlocks` once a map has outgrown its first block.
BLOCK_ROWS = 8192


class RowBlocks:
    """The rows ``0 .. capacity - 1`` of one accumulator (``[rows, *shape]``), in blocks.

    The last block grows geometrically (x1.5) up to :data:`BLOCK_ROWS` rows, then a new block
    starts; a full block never moves. Growing a map therefore never copies it (a single tensor
    grown x1.5 holds 2.5x the map while it copies, and copies it all) and the spare rows are
    less than one block. Blocks may also be adopted whole (:meth:`adopt`): the rows of a loaded
    map, memory-mapped from its file. Row ``r`` is in the block whose start is the last one
    ``<= r``; operations group their rows by block with one stable sort (the order of the
    updates of one row is kept: sums stay bit for bit those of one tensor).
    """

    def __init__(self, shape: tuple[int, ...], dtype: torch.dtype, device: torch.device) -> None:
        self.shape = tuple(shape)
        self.dtype = dtype
        self.device = torch.device(device)
        self.blocks: list[Tensor] = []
        self.starts: list[int] = []
        self._adopted = 0  # blocks adopted whole (never grown)
        self._starts: Tensor | None = None

    @property
    def capacity(self) -> int:
        return self.starts[-1] + self.blocks[-1].shape[0] if self.blocks else 0

    @property
    def nbytes(self) -> int:
        return sum(b.numel() * b.element_size() for b in self.blocks)

    def _new(self, rows: int) -> Tensor:
        return torch.zeros((rows, *self.shape), dtype=self.dtype, device=self.device)

    def reserve(self, rows: int) -> None:
        """Make room for rows ``0 .. rows - 1`` (new rows are zero)."""
        while self.capacity < rows:
            last = self.blocks[-1] if self.blocks else None
            growable = last is not None and len(self.blocks) > self._adopted
            if growable and last.shape[0] < BLOCK_ROWS:
                want = rows - self.starts[-1]
                size = min(BLOCK_ROWS, max(want, int(last.shape[0] * 1.5) + 16))
                new = self._new(size)
                new[: last.shape[0]] = last
                self.blocks[-1] = new
            else:
                self.starts.append(self.capacity)
                self.blocks.append(self._new(min(BLOCK_ROWS, max(16, rows - self.capacity))))
                self._starts = None

    def adopt(self, block: Tensor) -> None:
        """Append ``block`` (``[n, *shape]``, e.g. memory-mapped) as rows ``capacity ..``;
        it is used in place, never grown."""
        if tuple(block.shape[1:]) != self.shape or block.dtype != self.dtype:
            raise ValueError(f"block of shape {tuple(block.shape)} {block.dtype}: expected "
                             f"[n, {', '.join(map(str, self.shape))}] {self.dtype}")  # fmt: skip
        if self.blocks and len(self.blocks) > self._adopted:
            raise ValueError("adopt() before any row of this accumulator's own")
        self.starts.append(self.capacity)
        self.blocks.append(block)
        self._adopted += 1
        self._starts = None

    def _split(self, rows: Tensor) -> list[tuple[int, Tensor | None, Tensor]]:
        """``(block, positions or None for all, rows within the block)`` per block touched."""
        if len(self.blocks) == 1:
            return [(0, None, rows)]
        if self._starts is None:
            self._starts = torch.tensor(self.starts, dtype=torch.int64, device=self.device)
        block = torch.searchsorted(self._starts, rows, right=True) - 1
        lo, hi = int(block.min()), int(block.max()) if rows.numel() else (0, -1)
        if lo == hi:
            return [(lo, None, rows - self.starts[lo])]
        order = torch.argsort(block, stable=True)
        counts = torch.bincount(block, minlength=len(self.blocks)).tolist()
        out, at = [], 0
        for b, n in enumerate(counts):
            if n:
                pos = order[at : at + n]
                out.append((b, pos, rows[pos] - self.starts[b]))
                at += n
        return out

    def index_add_(self, rows: Tensor, values: Tensor) -> None:
        """``self[rows[i]] += values[i]``, in the order of ``i`` for each row."""
        if rows.numel() == 0:
            return
        for b, pos, local in self._split(rows):
            self.blocks[b].index_add_(0, local, values if pos is None else values[pos])

    def flat_add_(self, rows: Tensor, cols: Tensor, values: Tensor) -> None:
        """``self[rows[i], cols[i]] += values[i]`` (a 2-D accumulator)."""
        if rows.numel() == 0:
            return
        width = self.shape[0]
        for b, pos, local in self._split(rows):
            c = cols if pos is None else cols[pos]
            v = values if pos is None else values[pos]
            self.blocks[b].view(-1).index_add_(0, local * width + c, v)

    def gather(self, rows: Tensor) -> Tensor:
        """``[N, *shape]`` copy of the rows."""
        parts = self._split(rows) if rows.numel() else []
        if len(parts) == 1 and parts[0][1] is None:
            return self.blocks[parts[0][0]][parts[0][2]]
        out = torch.empty((rows.numel(), *self.shape), dtype=self.dtype, device=self.device)
        for b, pos, local in parts:
            out[pos] = self.blocks[b][local]
        return out

    def put(self, rows: Tensor, values: Tensor) -> None:
        """``self[rows] = values``."""
        for b, pos, local in self._split(rows) if rows.numel() else []:
            self.blocks[b][local] = values if pos is None else values[pos]

    def spans(self, size: int):
        """``(start, view)`` of rows ``0 .. size - 1``, block by block (views, no copy)."""
        for start, block in zip(self.starts, self.blocks, strict=True):
            if start >= size:
                return
            yield start, block[: size - start]

    def rows(self, size: int) -> Tensor:
        """Rows ``0 .. size - 1`` as one tensor (a view when one block holds them)."""
        views = [v for _, v in self.spans(size)]
        if not views:
            return self._new(0)
        return views[0] if len(views) == 1 else torch.cat(views)


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
        self.dim = _check_count("dim", dim)
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


class LabelVoxelMap(SparseVoxels):
    """Ground-truth class votes per voxel.

    Every point with a label in ``0 .. num_classes - 1`` adds one vote for its class to its voxel;
    points with any other label (``ignore_index``, e.g. 255, or any other id outside the range)
    are dropped and create no voxel. Their numbers are counted in :attr:`ignored` (labels equal
    to ``ignore_index``) and :attr:`out_of_range` (all other dropped labels), so a label mapping
    that leaks unexpected ids can be detected.

    Args:
        voxel_size: voxel edge in metres (> 0).
        num_classes: number of classes ``K``.
        ignore_index: the "no label" id; must lie outside ``0 .. K - 1``.
        device: where the map's tensors live.
        lattice: ``"round"`` or ``"floor"`` (module docstring).
    """

    def __init__(
        self,
        voxel_size: float,
        num_classes: int,
        ignore_index: int = 255,
        device: torch.device | str = "cpu",
        lattice: str = "round",
    ) -> None:
        super().__init__(voxel_size, device, lattice)
        self.num_classes = _check_count("num_classes", num_classes)
        if isinstance(ignore_index, bool) or not isinstance(ignore_index, int):
            raise ValueError(f"ignore_index={ignore_index!r}: expected an integer")
        if 0 <= ignore_index < self.num_classes:
            raise ValueError(
                f"ignore_index={ignore_index}: it is a class id (num_classes={self.num_classes})"
            )
        self.ignore_index = ignore_index
        self.ignored = 0
        self.out_of_range = 0
        self._accumulator("votes", (self.num_classes,), torch.int64)

    def __repr__(self) -> str:
        return (
            f"LabelVoxelMap(voxel_size={self.voxel_size}, num_classes={self.num_classes}, "
            f"device={self.device}, lattice={self.lattice!r}, voxels={len(self)})"
        )

    @property
    def _votes(self) -> RowBlocks:  # [capacity, K] int64 class votes
        return self._acc["votes"]

    def add(self, points: Tensor, labels: Tensor) -> None:
        """Add one vote per labelled point.

        Args:
            points: ``[N, 3]`` world coordinates in metres (finite).
            labels: ``[N]`` integer class ids; ids outside ``0 .. K - 1`` are dropped.
        """
        if not isinstance(labels, Tensor) or labels.ndim != 1:
            shape = tuple(labels.shape) if isinstance(labels, Tensor) else type(labels)
            raise ValueError(f"labels of shape {shape}: expected an [N] integer tensor")
        if labels.is_floating_point() or labels.is_complex() or labels.dtype == torch.bool:
            raise ValueError(f"labels of dtype {labels.dtype}: expected an integer tensor")
        points = self._check_points(points, labels.shape[0])
        labels = labels.to(device=self.device, dtype=torch.int64)
        keep = (labels >= 0) & (labels < self.num_classes)
        n_ignored = int((labels == self.ignore_index).sum())
        self.ignored += n_ignored
        self.out_of_range += int((~keep).sum()) - n_ignored
        points, labels = points[keep], labels[keep]
        if points.shape[0] == 0:
            return
        rows = self._rows_of(points)
        self._votes.flat_add_(rows, labels, torch.ones_like(rows))

    @property
    def votes(self) -> Tensor:
        """``[M, K]`` int64 votes per voxel and class, in the order of :attr:`indices`."""
        return self._votes.gather(self._rows)

    @property
    def counts(self) -> Tensor:
        """``[M]`` int64 labelled points per voxel."""
        return self.votes.sum(dim=1)

    def labels(self) -> tuple[Tensor, Tensor]:
        """Voxel centres ``[M, 3]`` float32 and labels ``[M]`` int64, the most-voted class.

        Ties go to the lowest class id (``torch.argmax`` returns the first maximum).
        """
        return self.centres(), torch.argmax(self.votes, dim=1)
