"""A sparse map's rows in blocks: :class:`RowBlocks`, one accumulator ``[rows, *shape]``.

A map grows by one block at a time, never by copying itself; a loaded map's blocks are
memory-mapped from its file (:meth:`RowBlocks.adopt`).
"""

from __future__ import annotations

import torch
from torch import Tensor

__all__ = ["BLOCK_ROWS", "RowBlocks"]


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
