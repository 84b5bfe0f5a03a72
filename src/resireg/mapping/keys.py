"""Packed voxel keys: integer voxel indices ``[N, 3]`` as one sortable int64 per voxel.

The one job of this module is the key that the sparse voxel maps (:mod:`.voxels`) sort and
search their voxels by, and that the pixel lifting (:mod:`.lifting`) and the label transfer
(:mod:`.query`) group and match voxels by. Each axis's index ``i`` (``|i| <= MAX_INDEX``) is
stored as ``i + 2**20`` in ``KEY_BITS = 21`` bits, the three axes in 63 bits of a
non-negative int64, so the order of the keys is the lexicographic order of the ``(i, j, k)``
index tuples.
"""

from __future__ import annotations

import torch
from torch import Tensor

__all__ = ["KEY_BITS", "MAX_INDEX", "pack_keys", "unpack_keys"]

#: bits per axis of a packed key (three axes: 63 bits, a non-negative int64)
KEY_BITS = 21
_OFFSET = 1 << (KEY_BITS - 1)
#: the largest ``|index|`` per axis that a key holds
MAX_INDEX = _OFFSET - 1


def pack_keys(index: Tensor) -> Tensor:
    """``[N, 3]`` int64 voxel indices (each ``|index| <= MAX_INDEX``, not checked) -> ``[N]``
    int64 keys, ordered like the index tuples."""
    shifted = index + _OFFSET
    return (shifted[:, 0] << (2 * KEY_BITS)) | (shifted[:, 1] << KEY_BITS) | shifted[:, 2]


def unpack_keys(keys: Tensor) -> Tensor:
    """Inverse of :func:`pack_keys`: ``[M]`` keys -> ``[M, 3]`` int64 indices."""
    mask = (1 << KEY_BITS) - 1
    parts = [(keys >> (2 * KEY_BITS)) & mask, (keys >> KEY_BITS) & mask, keys & mask]
    return torch.stack(parts, dim=1) - _OFFSET


# --------------------------------------------------------------------------- the key index
# Teschner et al. (2003), "Optimized spatial hashing for collision detection of deformable
# objects": the primes of the voxel-hashing literature (Niessner et al. 2013), over the three
# 21-bit fields of a key; then Mueller's 32-bit integer finaliser so a surface's regular keys
# spread over the table's low bits. Every product stays below 2**60: no int64 overflow.
_PRIMES = (73856093, 19349663, 83492791)
_MIX = 0x45D9F3B
_M32 = 0xFFFFFFFF
#: The largest fraction of a :class:`KeyIndex`'s slots in use before it doubles.
MAX_LOAD = 0.7
# Slots a probe round reads per key after the first round.
_WINDOW = 4


def hash_keys(keys: Tensor) -> Tensor:
    """``[N]`` packed keys -> ``[N]`` int64 hashes in ``[0, 2**32)`` (module comment above)."""
    mask = (1 << KEY_BITS) - 1
    h = ((keys >> (2 * KEY_BITS)) & mask) * _PRIMES[0]
    h = h + ((keys >> KEY_BITS) & mask) * _PRIMES[1] + (keys & mask) * _PRIMES[2]
    h = h & _M32
    h = (((h >> 16) ^ h) * _MIX) & _M32
    h = (((h >> 16) ^ h) * _MIX) & _M32
    return (h >> 16) ^ h


class KeyIndex:
    """Packed voxel keys -> rows ``0 .. M - 1`` (a row per key, in order of insertion).

    An open-addressing hash table with linear probing (:func:`hash_keys`), every probe round
    vectorised over the keys still looking: finding or adding ``N`` keys costs ``O(N)``
    expected work whatever the number ``M`` of keys held. (A sorted key array searched with
    ``torch.searchsorted`` finds as fast but costs ``O(M)`` per insertion, which made fusion
    4x slower at a million voxels.) Written here because neither torch nor numpy nor scipy
    offers a hash map over tensors. The table holds ``int32`` rows (``-1``: empty), at most
    :data:`MAX_LOAD` full, and doubles (every key placed again) when it would be fuller:
    ``4 / load`` bytes per key, 5.7 to 11.4, beside the 8 of the key itself.

    Args:
        device: where the table lives.
        capacity: keys to make room for now.
    """

    def __init__(self, device: torch.device | str = "cpu", capacity: int = 0) -> None:
        self.device = torch.device(device)
        self.size = 0
        self._keys = self._key_buffer(max(16, capacity))
        self._slots = self._empty_slots(self._slot_count(capacity))

    def _key_buffer(self, capacity: int) -> Tensor:
        """Room for ``capacity`` keys and, last, the sentinel ``-1`` that row ``-1`` (an empty
        slot) reads, so a probe compares keys without masking empty slots first."""
        buf = torch.empty(capacity + 1, dtype=torch.int64, device=self.device)
        buf[-1] = -1
        return buf

    @staticmethod
    def _slot_count(keys: int) -> int:
        slots = 16
        while keys > MAX_LOAD * slots:
            slots *= 2
        return slots

    def _empty_slots(self, n: int) -> Tensor:
        return torch.full((n,), -1, dtype=torch.int32, device=self.device)

    def __len__(self) -> int:
        return self.size

    @property
    def keys(self) -> Tensor:
        """``[M]`` the keys, by row."""
        return self._keys[: self.size]

    @property
    def nbytes(self) -> int:
        return self._keys.numel() * 8 + self._slots.numel() * 4

    def lookup(self, keys: Tensor) -> Tensor:
        """``[N]`` int64 row of each key (``-1``: not held)."""
        if self.size == 0 or keys.numel() == 0:
            return torch.full_like(keys, -1)
        mask = self._slots.numel() - 1
        pos = hash_keys(keys) & mask
        # First round: one slot per key (most keys end here, found or absent) ...
        rows = self._slots[pos].long()
        hit = self._keys[rows] == keys
        out = torch.where(hit, rows, -1)
        active = (~hit & (rows >= 0)).nonzero().squeeze(1)
        want, pos = keys[active], (pos[active] + 1) & mask
        # ... then a window of slots per key and round, so a probe sequence's long tail takes
        # a few rounds, not a round of a dozen tensor calls per slot.
        step = torch.arange(_WINDOW, device=self.device)
        while active.numel():
            rows = self._slots[(pos[:, None] + step) & mask].long()  # [n, W]
            hit = self._keys[rows] == want[:, None]
            stop = hit | (rows < 0)
            first = stop.to(torch.int8).argmax(dim=1)  # the slot that ends each search
            done = stop.any(dim=1)
            found = done & hit.gather(1, first[:, None]).squeeze(1)
            out[active[found]] = rows[found, first[found]]
            active, want, pos = active[~done], want[~done], (pos[~done] + _WINDOW) & mask
        return out

    def insert(self, keys: Tensor) -> Tensor:
        """Give distinct keys that are not held the next rows, in the order given; returns
        them (``[N]`` int64)."""
        n = keys.numel()
        rows = torch.arange(self.size, self.size + n, dtype=torch.int64, device=self.device)
        if n == 0:
            return rows
        if self.size + n > self._keys.numel() - 1:
            grown = self._key_buffer(max(self.size + n, int(self._keys.numel() * 1.5)))
            grown[: self.size] = self._keys[: self.size]
            self._keys = grown
        self._keys[self.size : self.size + n] = keys
        self.size += n
        if self.size > MAX_LOAD * self._slots.numel():  # double, and place every key again
            self._slots = self._empty_slots(self._slot_count(self.size))
            self._place(self.keys, torch.arange(self.size, device=self.device))
        else:
            self._place(keys, rows)
        return rows

    def _place(self, keys: Tensor, rows: Tensor) -> None:
        """Write ``rows`` into the first empty slot of each key's probe sequence. Keys that
        meet at one empty slot in a round: the first of a stable sort takes it, the others
        probe on (a sort of the keys still placing per round, never a pass over the table)."""
        mask = self._slots.numel() - 1
        pos = hash_keys(keys) & mask
        todo = torch.arange(keys.numel(), device=self.device)
        while todo.numel():
            free = (self._slots[pos] < 0).nonzero().squeeze(1)
            won = torch.zeros(todo.numel(), dtype=torch.bool, device=self.device)
            if free.numel():
                slot, order = torch.sort(pos[free], stable=True)
                first = torch.ones_like(slot, dtype=torch.bool)
                first[1:] = slot[1:] != slot[:-1]
                winners = free[order[first]]
                self._slots[pos[winners]] = rows[todo[winners]].to(torch.int32)
                won[winners] = True
            todo, pos = todo[~won], (pos[~won] + 1) & mask

    def _valid_table(self) -> bool:
        """Whether the table holds every row once, each in a slot its key's probe sequence
        reaches (no empty slot between the key's hash and it): a table read from a file is
        checked, not trusted (a slot off the sequence would let its key be added twice).
        ``O(M + S)``: one prefix count of the empty slots, no lookup."""
        slots, n = self._slots, self.size
        if bool((slots < -1).any()) or bool((slots >= n).any()):
            return False
        at = (slots >= 0).nonzero().squeeze(1)
        rows = slots[at].long()
        if rows.numel() != n or not bool((torch.bincount(rows, minlength=n) == 1).all()):
            return False
        where = torch.empty(n, dtype=torch.int64, device=self.device)
        where[rows] = at
        size = slots.numel()
        empty = torch.zeros(size + 1, dtype=torch.int64, device=self.device)
        empty[1:] = torch.cumsum(slots < 0, 0)  # empty[i]: empty slots before slot i
        start = hash_keys(self.keys) & (size - 1)
        wraps = start > where
        gaps = torch.where(wraps, empty[size] - empty[start] + empty[where + 1],
                           empty[where + 1] - empty[start])  # fmt: skip
        return not bool((gaps > 0).any())

    def state(self) -> dict[str, Tensor]:
        """``keys`` (by row) and ``slots`` (the table): what :meth:`from_state` takes back
        without placing any key again."""
        return {"keys": self.keys, "slots": self._slots}

    @classmethod
    def from_state(cls, keys: Tensor, slots: Tensor | None = None) -> KeyIndex:
        """The index of distinct ``keys`` (``[M]``, row order), with the table ``slots`` of
        :meth:`state` (``None``: placed anew)."""
        index = cls(keys.device, int(keys.numel()))
        index._keys[: keys.numel()] = keys
        index.size = int(keys.numel())
        if slots is None:
            index._place(index.keys, torch.arange(index.size, device=index.device))
        elif slots.numel() != index._slots.numel():
            raise ValueError(f"slots of {slots.numel()} entries: expected "
                             f"{index._slots.numel()} for {index.size} keys")  # fmt: skip
        else:
            index._slots = slots.to(device=index.device, dtype=torch.int32)
            if not index._valid_table():
                raise ValueError("slots: the hash table does not hold each key at its row")
        return index
