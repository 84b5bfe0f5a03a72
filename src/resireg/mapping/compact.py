"""Compact voxel storage: low-precision unit features, accumulated without drift (docs/maps.md#compact-storage).

:class:`CompactVoxelMap` keeps, per occupied voxel, the *direction* of its mean feature in
``float16`` (or ``bfloat16``), the mean's length (``float32``), the number of points it saw
(``int32``) and, with ``colour=True``, its mean colour (``uint8``) and that colour's count:
``2 k + 8`` bytes of features and weights for ``k`` channels (``k = 128``: 264), ``+ 7`` of
colour, beside the key index's ``8 + 5.7..11.4`` (:mod:`resireg.mapping.keys`).

Why not a low-precision running mean: a ``float16`` mean updated with each new point stalls once
the update ``(x - mean) / n`` falls below half a unit in the last place (``n`` in the hundreds
to thousands), so a voxel seen for a long time would keep the mean of its first views. Here
the points of a voxel accumulate first in a ``float32`` *block* (the "hot" voxels: those seen
recently), and a block is folded into the stored mean, with one rounding to ``float16``, only
when it holds as many points as the stored mean (``b >= n``): a voxel seen ``n`` times is
rounded ``~log2(n)`` times, each rounding's error shrunk by the later folds (``n / (n + b) <=
1/2`` each), so its stored direction stays within about one ``float16`` unit of the exact
``float64`` mean however long it is watched (``tests/resireg/mapping/test_compact_map.py``: 10,000 updates, a
cosine above 0.9999). A new voxel folds at the end of its first call. The block buffer holds
at most ``hot_voxels`` voxels; past it, the blocks that are largest relative to what their
voxel holds are folded first (they lose least). Queries read a hot voxel as stored mean and
block together, so nothing waits for a fold. Hand-written, because no library offers blocked
low-precision accumulation for sparse rows.

Reading: :meth:`CompactVoxelMap.features` (unit features, ``float32``), :meth:`means`,
:attr:`counts`, :meth:`mean_colours`; scoring for queries without a pass in ``float64``
(:meth:`approx_scores`, :meth:`exact_scores`). Saving: :meth:`tensors` (row order, blocks as
they are) and :meth:`from_tensors`.

One idea: the compact voxel map, one data structure. Its accumulation (stored unit means in
low precision, float32 blocks of the hot voxels, the folds between them) and its scoring (the
low-precision products with their error bound, the float64 re-scoring, the classify rule over
stored and hot rows) read the same private layout of rows, blocks and weights; split, each half
would reach into the other's internals. Its settings (:class:`CompactSettings`) and the storage
that uses it (:mod:`resireg.mapping.storage.compact`: the basis, the waiting windows) live apart.
"""

from __future__ import annotations

import functools
import math
from collections.abc import Mapping
from dataclasses import asdict, dataclass
from typing import Any

import torch
from torch import Tensor

from resireg.mapping.sparse import SparseVoxels
from resireg.specs.mapping import COMPACT_DTYPES

__all__ = ["STORED_DTYPES", "CompactSettings", "CompactVoxelMap", "half_mv_error"]

#: The stored dtypes of the unit features, by name (:data:`resireg.specs.mapping.COMPACT_DTYPES`).
STORED_DTYPES = {name: getattr(torch, name) for name in COMPACT_DTYPES}
# Rows per chunk of the float32 passes (features, scores): 4 MB of float32 at k = 128.
_CHUNK_ROWS = 8192
# Rows per chunk of the float64 folds and stores (2 MB at k = 128): a window's new voxels are
# written a chunk at a time, so its float64 temporaries do not scale with the window.
_STORE_ROWS = 2048


@dataclass(frozen=True)
class CompactSettings:
    """The ``compact`` block of ``conf/map.yaml`` (its defaults are these; a test compares).

    Attributes:
        dtype: the stored unit features, ``float16`` or ``bfloat16``.
        dim: ``None`` (keep the encoder's dimension) or the ``k`` dimensions features are
            projected to by a basis (an uncentred PCA, :func:`fit_basis`).
        basis: ``None`` (fitted on the first ``basis_rows`` features the map is given) or a
            file: a saved map (a map folder or a run folder, :func:`resireg.mapping.map_folder`;
            its basis) or a ``.safetensors`` file holding ``basis``
            ``[D, k]``; maps that merge must share one.
        basis_rows: features the basis is fitted on (the first frames' points).
        hot_voxels: voxels whose recent points wait in ``float32`` blocks (module docstring).
    """

    dtype: str = "float16"
    dim: int | None = 128
    basis: str | None = None
    basis_rows: int = 4096
    hot_voxels: int = 8192

    @classmethod
    def of(cls, value: CompactSettings | Mapping[str, Any] | None) -> CompactSettings:
        if value is None:
            return cls()
        if isinstance(value, CompactSettings):
            return value
        unknown = sorted(set(value) - set(cls.__dataclass_fields__))
        if unknown:
            raise ValueError(f"compact: unknown keys {unknown}; expected "
                             f"{sorted(cls.__dataclass_fields__)}")  # fmt: skip
        return cls(**dict(value))

    def as_dict(self) -> dict[str, Any]:
        return asdict(self)


@functools.cache
def half_mv_error(dtype: torch.dtype = torch.float16) -> float:
    """The largest error of torch's low-precision matrix-vector product on this machine,
    relative to the bound :meth:`CompactVoxelMap.approx_scores` assumes (one rounding of a
    float32-accumulated result): ``<= 1`` when the bound holds. Measured once per process on
    4096 random unit rows against float64, so a build that accumulated in low precision would
    be caught (the scores then come from the float32 path)."""
    g = torch.Generator().manual_seed(0)
    k = 128
    rows = torch.nn.functional.normalize(torch.randn(4096, k, generator=g), dim=1).to(dtype)
    q = torch.nn.functional.normalize(torch.randn(k, generator=g), dim=0).to(dtype)
    got = (rows @ q).double()
    exact = rows.double() @ q.double()
    unit = _unit_roundoff(dtype)
    bound = unit * exact.abs() + _sum_bound(k) * 1.001 + 2.0**-24
    return float(((got - exact).abs() / bound).max())


def _unit_roundoff(dtype: torch.dtype) -> float:
    return torch.finfo(dtype).eps / 2


def _sum_bound(k: int) -> float:
    """gamma_k of a float32 sum of ``k`` products of unit-bounded vectors (Higham)."""
    u = 2.0**-24
    return k * u / (1 - k * u)


class CompactVoxelMap(SparseVoxels):
    """Sparse voxels of unit features in low precision (module docstring).

    Args:
        voxel_size: voxel edge in metres (> 0).
        dim: channels ``k`` of the stored features.
        device: where the map's tensors live.
        lattice: ``"round"`` or ``"floor"`` (:mod:`resireg.mapping.keys`).
        dtype: ``torch.float16`` or ``torch.bfloat16``.
        colour: also keep a mean colour per voxel.
        hot_voxels: the most voxels whose points wait in ``float32`` blocks.
    """

    def __init__(
        self,
        voxel_size: float,
        dim: int,
        device: torch.device | str = "cpu",
        lattice: str = "round",
        dtype: torch.dtype = torch.float16,
        colour: bool = True,
        hot_voxels: int = 8192,
    ) -> None:
        super().__init__(voxel_size, device, lattice)
        if isinstance(dim, bool) or not isinstance(dim, int) or dim < 1:
            raise ValueError(f"dim={dim!r}: expected an integer >= 1")
        if dtype not in STORED_DTYPES.values():
            raise ValueError(f"dtype={dtype}: expected one of {list(STORED_DTYPES.values())}")
        if isinstance(hot_voxels, bool) or not isinstance(hot_voxels, int) or hot_voxels < 0:
            raise ValueError(f"hot_voxels={hot_voxels!r}: expected an integer >= 0")
        self.dim, self.dtype, self.colour, self.hot_voxels = dim, dtype, bool(colour), hot_voxels
        self._accumulator("unit", (dim,), dtype)
        self._accumulator("norm", (), torch.float32)
        self._accumulator("counts", (), torch.int32)
        if self.colour:
            self._accumulator("colour", (3,), torch.uint8)
            self._accumulator("colour_counts", (), torch.int32)
        self._clear_hot()

    def __repr__(self) -> str:
        return (
            f"CompactVoxelMap(voxel_size={self.voxel_size}, dim={self.dim}, dtype={self.dtype}, "
            f"lattice={self.lattice!r}, voxels={len(self)}, hot={self.hot_rows.numel()})"
        )

    # ------------------------------------------------------------------ the hot blocks
    # The blocks live in slots of fixed arrays (a slot per hot voxel, -1 in _hot_row when
    # free), so a call touches its own voxels' slots and never copies the buffer; a sorted
    # (row, slot) index, rebuilt when voxels enter or leave, finds a row's slot.
    def _clear_hot(self, capacity: int = 0) -> None:
        d = self.device
        self._hot_row = torch.full((capacity,), -1, dtype=torch.int64, device=d)
        self._hot_n = torch.zeros(capacity, dtype=torch.int64, device=d)  # its stored count
        self._hot_sums = torch.zeros(capacity, self.dim, dtype=torch.float32, device=d)
        self._hot_counts = torch.zeros(capacity, dtype=torch.int64, device=d)
        self._hot_colour = torch.zeros(capacity, 3, dtype=torch.float32, device=d)
        self._hot_colour_counts = torch.zeros(capacity, dtype=torch.int64, device=d)
        self._hot_index: tuple[Tensor, Tensor] | None = None

    def _hot_lookup(self) -> tuple[Tensor, Tensor]:
        """(the hot voxels' rows, sorted; their slots)."""
        if self._hot_index is None:
            used = (self._hot_row >= 0).nonzero().squeeze(1)
            rows, order = torch.sort(self._hot_row[used])
            self._hot_index = (rows, used[order])
        return self._hot_index

    @property
    def hot_rows(self) -> Tensor:
        """``[H]`` the rows of the voxels with a hot block, sorted."""
        return self._hot_lookup()[0]

    @property
    def nbytes(self) -> int:
        """Bytes held: the stored rows (spare rows of the last block included), the key
        index and the hot blocks' slots."""
        hot = (self._hot_row, self._hot_n, self._hot_sums, self._hot_counts, self._hot_colour,
               self._hot_colour_counts)  # fmt: skip
        return super().nbytes + sum(t.numel() * t.element_size() for t in hot)

    def add(self, points: Tensor, features: Tensor, colours: Tensor | None = None) -> None:
        """Add points ``[N, 3]`` with features ``[N, k]`` (and colours ``[N, 3]`` in [0, 1])."""
        self._check_features(features)
        points = self._check_points(points, features.shape[0])
        if points.shape[0] == 0:
            return
        rows = self._rows_of(points)
        ones = torch.ones_like(rows)
        self._accumulate(rows, ones, features.to(self.device), None, colours)

    def add_pairs(self, index: Tensor, counts: Tensor, features: Tensor, source: Tensor,
                  colours: Tensor | None = None) -> None:  # fmt: skip
        """:meth:`resireg.mapping.VoxelMap.add_pairs`: pair ``i`` stands for ``counts[i]``
        points of voxel ``index[i]`` with feature ``features[source[i]]`` (and colour
        ``colours[source[i]]``)."""
        self._check_features(features)
        m = index.shape[0]
        if index.shape != (m, 3) or counts.shape != (m,) or source.shape != (m,):
            raise ValueError(
                f"index {tuple(index.shape)}, counts {tuple(counts.shape)}, source "
                f"{tuple(source.shape)}: expected [M, 3], [M], [M]"
            )
        if m == 0:
            return
        rows = self._rows_of_index(index.to(device=self.device, dtype=torch.int64))
        self._accumulate(rows, counts.to(device=self.device, dtype=torch.int64),
                         features.to(self.device), source.to(self.device), colours)  # fmt: skip

    def _check_features(self, features: Tensor) -> None:
        if not isinstance(features, Tensor) or features.ndim != 2 or features.shape[1] != self.dim:
            shape = tuple(features.shape) if isinstance(features, Tensor) else type(features)
            raise ValueError(f"features of shape {shape}: expected [N, {self.dim}]")
        if not features.is_floating_point():
            raise ValueError(f"features of dtype {features.dtype}: expected floating point")

    def _accumulate(self, rows: Tensor, weights: Tensor, features: Tensor,
                    source: Tensor | None, colours: Tensor | None) -> None:  # fmt: skip
        """Sum this call's points per voxel (float64), add the sums to the voxels' hot
        blocks, then fold the blocks the rule says (module docstring)."""
        uniq, inv = torch.unique(rows, return_inverse=True)
        r = uniq.numel()
        sums = torch.zeros(r, self.dim, dtype=torch.float64, device=self.device)
        w = weights.to(torch.float64)[:, None]
        step = max(1, (1 << 20) // self.dim)
        for start in range(0, rows.numel(), step):
            at = slice(start, start + step)
            chunk = features[at] if source is None else features.index_select(0, source[at])
            sums.index_add_(0, inv[at], chunk.to(torch.float64).mul_(w[at]))
        counts = torch.zeros(r, dtype=torch.int64, device=self.device).index_add_(0, inv, weights)
        csums = ccounts = None
        if self.colour and colours is not None:
            rgb = colours.to(self.device)
            rgb = rgb if source is None else rgb.index_select(0, source)
            csums = torch.zeros(r, 3, dtype=torch.float64, device=self.device)
            csums.index_add_(0, inv, rgb.to(torch.float64).mul_(w))
            ccounts = counts
        self._add(uniq, sums, counts, csums, ccounts)

    def _add(self, rows: Tensor, sums: Tensor, counts: Tensor, csums: Tensor | None,
             ccounts: Tensor | None) -> None:  # fmt: skip
        """Add per-voxel float64 sums of distinct ``rows``: to their hot blocks, or, for a
        voxel without one whose new points are at least what it holds (a new voxel among
        them), straight into its stored values (the fold a fresh block would make, without a
        slot); the others get a block. Then the due blocks fold."""
        slot = self._hot_at(rows)
        cold = slot < 0
        if bool(cold.any()):
            r = rows[cold]
            n = self._acc["counts"].gather(r).to(torch.int64)
            now = counts[cold] >= n
            if bool(now.any()):
                pick = cold.nonzero().squeeze(1)[now]
                for at in range(0, pick.numel(), _STORE_ROWS):  # row-wise: chunks change nothing
                    p = pick[at : at + _STORE_ROWS]
                    mean, held = self._combined(rows[p], None)
                    total = held + counts[p]
                    mean.mul_(held[:, None]).add_(sums[p]).div_(total[:, None])
                    self._store(rows[p], mean, total, None if csums is None else csums[p],
                                None if ccounts is None else ccounts[p])  # fmt: skip
                keep = torch.ones_like(cold)
                keep[pick] = False
                rows, sums, counts = rows[keep], sums[keep], counts[keep]
                csums = None if csums is None else csums[keep]
                ccounts = None if ccounts is None else ccounts[keep]
        if rows.numel():
            self._to_hot(rows, sums, counts, csums, ccounts)
        self._fold_due()

    def _to_hot(self, rows: Tensor, sums: Tensor, counts: Tensor, csums: Tensor | None,
                ccounts: Tensor | None) -> None:  # fmt: skip
        """Add per-voxel sums of distinct ``rows`` to their hot blocks (new blocks made)."""
        slot = self._hot_at(rows)
        missing = slot < 0
        if bool(missing.any()):
            free = (self._hot_row < 0).nonzero().squeeze(1)
            need = int(missing.sum()) - free.numel()
            if need > 0:  # more slots (x1.5): the arrays grow, their slots stay
                grow = max(need, self._hot_row.numel() // 2, 16)
                old = self._hot_row.numel()

                def more(t: Tensor, fill: int = 0) -> Tensor:
                    return torch.cat([t, t.new_full((grow, *t.shape[1:]), fill)])

                self._hot_row, self._hot_n = more(self._hot_row, -1), more(self._hot_n)
                self._hot_sums, self._hot_counts = more(self._hot_sums), more(self._hot_counts)
                self._hot_colour = more(self._hot_colour)
                self._hot_colour_counts = more(self._hot_colour_counts)
                free = torch.cat([free, torch.arange(old, old + grow, device=self.device)])
            new = free[: int(missing.sum())]
            self._hot_row[new] = rows[missing]
            self._hot_n[new] = self._acc["counts"].gather(rows[missing]).to(torch.int64)
            slot[missing] = new
            self._hot_index = None
        self._hot_sums.index_add_(0, slot, sums.to(torch.float32))
        self._hot_counts.index_add_(0, slot, counts)
        if csums is not None:
            self._hot_colour.index_add_(0, slot, csums.to(torch.float32))
            self._hot_colour_counts.index_add_(0, slot, ccounts)

    def _fold_due(self) -> None:
        """Fold the hot blocks that hold at least what their voxel holds (new voxels
        included), then, past ``hot_voxels``, those largest relative to their voxel (ties: the
        higher row first)."""
        used = self._hot_row >= 0
        if not bool(used.any()):
            return
        n, b = self._hot_n, self._hot_counts
        due = used & (b >= n)
        waiting = used & ~due
        keep = int(waiting.sum())
        if keep > self.hot_voxels:
            slots = waiting.nonzero().squeeze(1)
            by_row = slots[torch.argsort(self._hot_row[slots])]
            ratio = b[by_row].double() / n[by_row].clamp_min(1).double()
            kept = by_row[torch.argsort(ratio, stable=True)[: self.hot_voxels]]
            due = used.clone()
            due[kept] = False
        if bool(due.any()):
            self._fold(due)

    def flush(self) -> None:
        """Fold every hot block (e.g. before a merge)."""
        used = self._hot_row >= 0
        if bool(used.any()):
            self._fold(used)

    def _combined(self, rows: Tensor, at: Tensor | None) -> tuple[Tensor, Tensor]:
        """float64 mean features ``[R, k]`` and counts ``[R]`` of ``rows``, their hot blocks
        (positions ``at`` in the hot buffer, ``-1``: none) included."""
        n = self._acc["counts"].gather(rows).to(torch.int64)
        mean = self._acc["unit"].gather(rows).to(torch.float64)
        mean.mul_(self._acc["norm"].gather(rows).to(torch.float64)[:, None])
        if at is None:
            return mean, n
        hot = at >= 0
        if bool(hot.any()):
            h = at[hot]
            b = self._hot_counts[h]
            total = n[hot] + b
            mean[hot] = (mean[hot] * n[hot, None] + self._hot_sums[h].double()) / total[:, None]
            n = n.clone()
            n[hot] = total
        return mean, n

    def _store(self, rows: Tensor, mean: Tensor, total: Tensor, csums: Tensor | None,
               ccounts: Tensor | None) -> None:  # fmt: skip
        """Write float64 means ``[R, k]`` and point counts of ``rows`` (one rounding to the
        stored dtype), and add colour sums and counts to their mean colours."""
        norm = mean.norm(dim=1)
        unit = mean.div_(norm.clamp_min(1e-300)[:, None])  # in place: the callers are done with it
        self._acc["unit"].put(rows, unit.to(self.dtype))
        self._acc["norm"].put(rows, norm.to(torch.float32))
        self._acc["counts"].put(rows, total.to(torch.int32))
        if self.colour and csums is not None:
            cn = self._acc["colour_counts"].gather(rows).to(torch.int64)
            c = self._acc["colour"].gather(rows).to(torch.float64) / 255
            both = cn + ccounts
            new = torch.where((both > 0)[:, None], (c * cn[:, None] + csums.double())
                              / both.clamp_min(1)[:, None], c)  # fmt: skip
            self._acc["colour"].put(rows, (new.clamp(0, 1) * 255).round().to(torch.uint8))
            self._acc["colour_counts"].put(rows, both.to(torch.int32))

    def _fold(self, mask: Tensor) -> None:
        """Fold the hot blocks of the slots at ``mask`` into their voxels' stored values and
        free the slots."""
        at = mask.nonzero().squeeze(1)
        for start in range(0, at.numel(), _STORE_ROWS):  # row-wise: chunks change nothing
            a = at[start : start + _STORE_ROWS]
            rows = self._hot_row[a]
            mean, n = self._combined(rows, a)
            self._store(rows, mean, n, self._hot_colour[a], self._hot_colour_counts[a])
        self._hot_row[at] = -1
        self._hot_n[at] = 0
        self._hot_sums[at] = 0
        self._hot_counts[at] = 0
        self._hot_colour[at] = 0
        self._hot_colour_counts[at] = 0
        self._hot_index = None

    def _hot_at(self, rows: Tensor) -> Tensor:
        """The hot slot of each row, ``-1`` where it has no block."""
        hot, slots = self._hot_lookup()
        if not hot.numel():
            return torch.full_like(rows, -1)
        pos = torch.searchsorted(hot, rows).clamp_max(hot.numel() - 1)
        return torch.where(hot[pos] == rows, slots[pos], -1)

    # ------------------------------------------------------------------ reading
    @property
    def counts(self) -> Tensor:
        """``[M]`` int64 points per voxel, in :attr:`indices` order."""
        rows = self._rows
        return self._combined(rows, self._hot_at(rows))[1]

    def means(self) -> Tensor:
        """``[M, k]`` float64 mean feature per voxel, in :attr:`indices` order."""
        rows = self._rows
        return self._combined(rows, self._hot_at(rows))[0]

    def unit_rows(self, rows: Tensor) -> Tensor:
        """``[R, k]`` float32 features of ``rows`` as :meth:`features` gives them: the stored
        direction, or for a hot voxel its mean with its block, normalised."""
        out = self._acc["unit"].gather(rows).to(torch.float32)
        at = self._hot_at(rows)
        hot = at >= 0
        if bool(hot.any()):
            mean, _ = self._combined(rows[hot], at[hot])
            out[hot] = (mean / mean.norm(dim=1, keepdim=True).clamp_min(1e-12)).float()
        return out

    def features(self) -> tuple[Tensor, Tensor]:
        """Voxel centres ``[M, 3]`` and unit features ``[M, k]`` float32, in :attr:`indices`
        order (the stored directions; a hot voxel's with its block)."""
        order = self._rows
        out = torch.empty(order.numel(), self.dim, dtype=torch.float32, device=self.device)
        for start in range(0, order.numel(), _CHUNK_ROWS):
            rows = order[start : start + _CHUNK_ROWS]
            out[start : start + _CHUNK_ROWS] = self._acc["unit"].gather(rows)
        hot = self.hot_rows
        if hot.numel():
            rank = torch.empty(len(self), dtype=torch.int64, device=self.device)
            rank[order] = torch.arange(len(self), device=self.device)
            out[rank[hot]] = self.unit_rows(hot)
        return self.centres(), out

    def mean_colours(self) -> Tensor:
        """``[M, 3]`` uint8 mean colour per voxel, in :attr:`indices` order."""
        if not self.colour:
            raise ValueError("this map keeps no colour (colour=False)")
        rows = self._rows
        out = self._acc["colour"].gather(rows).clone()
        at = self._hot_at(rows)
        hot = at >= 0
        if bool(hot.any()):
            r, h = rows[hot], at[hot]
            cn = self._acc["colour_counts"].gather(r).to(torch.float64)
            total = cn + self._hot_colour_counts[h]
            c = out[hot].double() / 255 * cn[:, None] + self._hot_colour[h].double()
            c = torch.where(total[:, None] > 0, c / total.clamp_min(1)[:, None],
                            out[hot].double() / 255)  # fmt: skip
            out[hot] = (c.clamp(0, 1) * 255).round().to(torch.uint8)
        return out.cpu()

    # ------------------------------------------------------------------ scoring
    def approx_scores(self, queries: Tensor, fast: bool = True) -> tuple[Tensor, Tensor]:
        """Scores ``[M, T]`` float32 (row order) of unit ``queries`` ``[T, k]`` and a bound
        ``[T]`` on their error against :meth:`exact_scores`.

        One text: torch's low-precision matrix-vector product (float32 accumulation, one
        rounding of each result: error ``<= u |s| + gamma_k + |q16 - q|``, checked on this
        machine by :func:`half_mv_error`); several texts, ``fast=False``, or where that check
        fails: each block widened to float32 in chunks and multiplied in float32 (error
        ``<= gamma_k``). Hot voxels are scored exactly."""
        q = queries.to(device=self.device, dtype=torch.float32)
        m = len(self)
        out = torch.empty(m, q.shape[0], dtype=torch.float32, device=self.device)
        sums = _sum_bound(self.dim) * 1.001 * q.norm(dim=1)
        fast = (fast and q.shape[0] == 1 and self.device.type == "cpu"
                and half_mv_error(self.dtype) <= 1)  # fmt: skip
        if fast:
            q16 = q[0].to(self.dtype)
            bound = (_unit_roundoff(self.dtype) * 1.001 * q.norm(dim=1) + sums
                     + 1.001 * (q16.float() - q[0]).norm() + 2.0**-24)  # fmt: skip
            for start, block in self._acc["unit"].spans(m):
                out[start : start + block.shape[0], 0] = (block @ q16).float()
        else:
            bound = sums + 2.0**-20 * q.norm(dim=1)
            for _ in self.stored_products(q, out=out):
                pass
        hot = self.hot_rows
        if hot.numel():
            out[hot] = self.exact_scores(hot, q).to(torch.float32)
        return out, bound

    def stored_products(self, queries: Tensor, out: Tensor | None = None, rows_first: bool = True,
                        chunk: int = _CHUNK_ROWS):  # fmt: skip
        """The one product of the stored features with queries ``[T, k]`` float32, chunk by
        chunk of rows in row order (what :meth:`approx_scores`, :meth:`query` through it,
        :meth:`~resireg.mapping.SemanticMap.top_k` and :meth:`classify` share): yields
        ``(start, x, scores)``: ``x`` the chunk's stored directions widened to float32 ``[n,
        k]`` (exactly: a buffer the next chunk reuses), ``scores`` ``x @ queries.T`` ``[n, T]``
        (``rows_first=False``: ``[T, n]``, the layout whose reductions over the texts
        vectorise), written into ``out[start : start + n]`` when given; ``chunk`` rows at a
        time (at most: a block's end cuts a chunk). Each score is within
        ``gamma_k ||x|| ||q||`` of its float64 value (a float32 sum of ``k`` products). Hot
        voxels' blocks are not in ``x`` (the callers score them apart)."""
        m = len(self)
        if not m:
            return
        buf = torch.empty(min(m, chunk), self.dim, dtype=torch.float32, device=self.device)
        for start, block in self._acc["unit"].spans(m):
            for s in range(0, block.shape[0], chunk):
                part = block[s : s + chunk]
                x = buf[: part.shape[0]]
                x.copy_(part)
                at = start + s
                if out is not None:
                    scores = torch.mm(x, queries.T, out=out[at : at + x.shape[0]])
                elif rows_first:
                    scores = torch.mm(x, queries.T)
                else:
                    scores = torch.mm(queries, x.T)
                yield at, x, scores

    def classify(self, prototypes: Tensor, threshold: float | None = None,
                 denoise: float | None = None, temperature: float = 100.0, none: int = -1,
                 denoise_chunk: int = 10_000) -> Tensor:  # fmt: skip
        """``[M]`` int64 class per voxel, in :attr:`indices` order: the rule of
        :func:`resireg.mapping.classify` (cosine argmax; with ``threshold`` / ``denoise``
        RayFronts' softmax rule, its denoising chunks taken in :attr:`indices` order) over the
        voxels' features as :meth:`features` gives them, *exactly* as computed in float64
        (both sides normalised, ties to the lowest class id).

        One float32 pass (:meth:`stored_products`, the texts' side ``[K, n]``) gives each
        row's best class and, with the rule, its probability, each with an error bound; a row
        whose decision the bound leaves open (a second class within twice the bound, a
        probability within its bound of ``threshold`` or ``denoise``, a hot voxel, a
        near-zero feature) is decided in float64, and so are the rows whose best class the
        denoising removes (their best remaining class). ``denoise < 0.5`` (a removed class
        need not be a row's best) is decided in float64 throughout. (A probability equal to
        the threshold to float64's own rounding goes the way torch's float64 softmax says.)"""
        protos = prototypes.to(self.device, torch.float64)
        if protos.ndim != 2 or protos.shape[1] != self.dim or protos.shape[0] == 0:
            raise ValueError(f"prototypes of shape {tuple(prototypes.shape)}: expected "
                             f"[K >= 1, {self.dim}]")  # fmt: skip
        protos = protos / protos.norm(dim=1, keepdim=True).clamp_min(1e-12)
        m, n_cls = len(self), protos.shape[0]
        if not m:
            return torch.empty(0, dtype=torch.int64, device=self.device)
        rule = threshold is not None or denoise is not None
        best = torch.empty(m, dtype=torch.int64, device=self.device)
        prob = torch.ones(m, dtype=torch.float32, device=self.device)
        open_ = torch.zeros(m, dtype=torch.bool, device=self.device)
        if denoise is not None and denoise < 0.5:
            open_[:] = True
        else:
            p32 = protos.to(torch.float32)
            # |float32 score - float64 score| <= c ||x||: the float32 sum of k products, the
            # prototypes' rounding to float32, the norm's own rounding (x is exact)
            c = (_sum_bound(self.dim) + 4 * 2.0**-24) * 1.01
            # relative error of a row's probability (1 / its softmax denominator): each
            # exponent that counts (>= -32) off by <= 2 T c (the two scores) and 32 (k + 2) u
            # (the norm's and the scaling's rounding), exp's and the sum's rounding; twice it
            u = 2.0**-24
            margin = 2 * (math.expm1(2 * temperature * c + 32 * (self.dim + 2) * u)
                          + (4 + n_cls) * 2 * u)  # fmt: skip
            weights = torch.stack([torch.ones(n_cls), torch.arange(n_cls, dtype=torch.float32)]).to(
                self.device
            )
            near = None
            for at, x, s in self.stored_products(p32, rows_first=False):
                n = x.shape[0]
                if near is None:
                    near = torch.empty_like(s)
                norm = torch.linalg.vector_norm(x, dim=1)
                top = s.amax(0)
                flags = torch.ge(s, top - 2 * c * norm, out=near[:, :n])  # 1.0: near the top
                count, index = torch.mm(weights, flags)  # classes near the top, their id sum
                best[at : at + n] = index.to(torch.int64)
                open_[at : at + n] = (count != 1) | (norm < 1e-6)
                if rule:
                    # exponents below -80 (terms < 2e-35, within the margin) clamped: the
                    # float32 exp of a denormal result takes a slow path
                    z = s.sub_(top).mul_(temperature / norm).clamp_(min=-80.0).exp_().sum(0)
                    p = 1 / z
                    prob[at : at + n] = p
                    for level in (threshold, denoise):
                        if level is not None:
                            open_[at : at + n] |= (p - level).abs() <= margin * p
            hot = self.hot_rows
            if hot.numel():
                open_[hot] = True
        order = self.sorted_rows
        rank = torch.empty(m, dtype=torch.int64, device=self.device)
        rank[order] = torch.arange(m, device=self.device)
        chunk = rank // denoise_chunk

        def exact(rows: Tensor):
            """``(rows, float64 probabilities (the rule) or cosines (argmax))``, in chunks."""
            for s in range(0, rows.numel(), _CHUNK_ROWS):
                r = rows[s : s + _CHUNK_ROWS]
                f = self.unit_rows(r).to(torch.float64)
                f = f / f.norm(dim=1, keepdim=True).clamp_min(1e-12)
                cos = f @ protos.T
                yield r, torch.softmax(temperature * cos, dim=1) if rule else cos

        label = best.clone()
        decided = open_.nonzero().squeeze(1)
        keep = None
        if denoise is not None:
            keep = torch.zeros(int(chunk.max()) + 1, n_cls, dtype=torch.bool, device=self.device)
            sure = ~open_ & (prob >= denoise)  # a probability >= 0.5 only the best class has
            keep[chunk[sure], best[sure]] = True
            for r, p in exact(decided):
                hit = (p >= denoise).nonzero()
                keep[chunk[r[hit[:, 0]]], hit[:, 1]] = True
            # rows whose best class their chunk removes: their best remaining one, in float64
            removed = ~open_ & ~keep[chunk, best.masked_fill(open_, 0)]
            decided = torch.cat([decided, removed.nonzero().squeeze(1)])
            open_ |= removed
        for r, p in exact(decided):
            if keep is not None:
                p[~keep[chunk[r]]] = -torch.inf
            value, cls = torch.max(p, dim=1)
            if threshold is not None:
                cls = torch.where(value < threshold, none, cls)
            label[r] = cls
        if threshold is not None:
            label[~open_ & (prob < threshold)] = none
        return label[order]

    def exact_scores(self, rows: Tensor, queries: Tensor) -> Tensor:
        """``[R, T]`` float64 dot products of the unit features of ``rows`` (as
        :meth:`features` gives them) with ``queries`` ``[T, k]``."""
        return self.unit_rows(rows).double() @ queries.to(self.device).double().T

    # ------------------------------------------------------------------ merging
    def merge_from(self, other: CompactVoxelMap, keys: Tensor | None = None) -> None:
        """Add ``other``'s voxels (their points, as counts and means) to this map, in place;
        ``keys``: the voxel key of each of ``other``'s rows here (``None``: its own). Both
        maps' blocks are folded first; a voxel new here is copied as it is stored."""
        self.flush()
        other.flush()
        m = len(other)
        keys = other.keys if keys is None else keys.to(self.device)
        step = 1 << 16
        for start in range(0, m, step):
            src = torch.arange(start, min(m, start + step), device=other.device)
            k = keys[start : start + step]
            uniq, inv = torch.unique(k, return_inverse=True)
            rows = self._index.lookup(uniq)
            fresh = rows < 0
            dup = torch.bincount(inv, minlength=uniq.numel()) > 1
            if bool(fresh.any()):
                rows[fresh] = self._index.insert(uniq[fresh])
                self.reserve(len(self))
                self._sorted = None
            target = rows[inv]
            # voxels new here and met once: copied as stored (no rounding)
            copy = (fresh & ~dup)[inv]
            if bool(copy.any()):
                s, t = src[copy], target[copy]
                for name in self._acc:
                    self._acc[name].put(t, other._acc[name].gather(s))
            rest = ~copy
            if bool(rest.any()):
                s, t = src[rest], target[rest]
                mean, n = other._combined(s, None)
                sums = torch.zeros(uniq.numel(), self.dim, dtype=torch.float64,
                                   device=self.device)  # fmt: skip
                cnt = torch.zeros(uniq.numel(), dtype=torch.int64, device=self.device)
                u = inv[rest]
                sums.index_add_(0, u, mean * n[:, None])
                cnt.index_add_(0, u, n)
                csums = ccnt = None
                if self.colour and other.colour:
                    cn = other._acc["colour_counts"].gather(s).to(torch.int64)
                    c = other._acc["colour"].gather(s).to(torch.float64) / 255
                    csums = torch.zeros(uniq.numel(), 3, dtype=torch.float64,
                                        device=self.device)  # fmt: skip
                    csums.index_add_(0, u, c * cn[:, None])
                    ccnt = torch.zeros_like(cnt).index_add_(0, u, cn)
                touched = torch.unique(u)
                self._add(rows[touched], sums[touched], cnt[touched],
                          None if csums is None else csums[touched],
                          None if ccnt is None else ccnt[touched])  # fmt: skip
                self.flush()

    # ------------------------------------------------------------------ files
    def tensors(self) -> dict[str, list[Tensor]]:
        """The map's tensors in row order, each as the list of its blocks' used rows (no
        copy): ``keys``, ``slots`` (the key index) and the accumulators, and the hot blocks
        (``hot_rows`` ...). What :meth:`from_tensors` takes back."""
        m = len(self)
        out: dict[str, list[Tensor]] = {
            "keys": [self._index.keys],
            "slots": [self._index.state()["slots"]],
        }
        for name, acc in self._acc.items():
            out[name] = [v for _, v in acc.spans(m)]
        rows, slots = self._hot_lookup()
        out.update(hot_rows=[rows], hot_sums=[self._hot_sums[slots]],
                   hot_counts=[self._hot_counts[slots]])  # fmt: skip
        if self.colour:
            out.update(hot_colour=[self._hot_colour[slots]],
                       hot_colour_counts=[self._hot_colour_counts[slots]])  # fmt: skip
        return out

    def load_tensors(self, tensors: Mapping[str, Tensor]) -> None:
        """Replace the content with :meth:`tensors` read back (used in place: memory-mapped
        tensors stay mapped). The hot blocks are checked against the map (their shapes, rows
        distinct, sorted and held) before their slots are allocated: a file's row count
        never sizes an allocation its own bytes do not hold."""
        self._load_rows(tensors["keys"], {k: tensors[k] for k in self._acc}, tensors.get("slots"))
        names = ["hot_rows", "hot_sums", "hot_counts"]
        if self.colour:
            names += ["hot_colour", "hot_colour_counts"]
        if "hot_rows" not in tensors:  # (a map saved without blocks)
            self._clear_hot(0)
            return
        hot = {k: tensors[k] for k in names}
        n = int(hot["hot_rows"].shape[0]) if hot["hot_rows"].ndim == 1 else -1
        shapes = {"hot_rows": (n,), "hot_sums": (n, self.dim), "hot_counts": (n,),
                  "hot_colour": (n, 3), "hot_colour_counts": (n,)}  # fmt: skip
        for name, t in hot.items():
            if tuple(t.shape) != shapes[name]:
                raise ValueError(f"{name} of shape {list(t.shape)}: expected "
                                 f"{list(shapes[name])} (hot_rows [H], dim={self.dim})")  # fmt: skip
        rows = hot["hot_rows"].to(self.device, torch.int64)
        if n and not (n <= len(self) and int(rows.min()) >= 0 and int(rows.max()) < len(self)
                      and bool((rows[1:] > rows[:-1]).all())):  # fmt: skip
            raise ValueError(f"hot_rows: {n} rows not distinct, sorted and held by the map's "
                             f"{len(self)} voxels")  # fmt: skip
        self._clear_hot(n)
        if not n:
            return
        self._hot_row[:] = rows
        self._hot_n[:] = self._acc["counts"].gather(rows).to(torch.int64)
        self._hot_sums[:] = hot["hot_sums"].to(self.device, torch.float32)
        self._hot_counts[:] = hot["hot_counts"].to(self.device, torch.int64)
        if self.colour:
            self._hot_colour[:] = hot["hot_colour"].to(self.device, torch.float32)
            self._hot_colour_counts[:] = hot["hot_colour_counts"].to(self.device, torch.int64)
