"""Packed voxel keys: integer voxel indices ``[N, 3]`` as one sortable int64 per voxel.

The one job of this module is the key that the sparse voxel maps (:mod:`.voxels`) sort and
search their voxels by, and that the pixel lifting (:mod:`.lifting`) and the label transfer
(:mod:`.query`) group and match voxels by. Each axis's index ``i`` (``|i| <= MAX_INDEX``) is
stored as ``i + 2**20`` in ``KEY_BITS = 21`` bits, the three axes in 63 bits of a
non-negative int64, so the order of the keys is the lexicographic order of the ``(i, j, k)``
index tuples.

A point ``p`` (metres) falls in the voxel of an integer index per axis, by one of two lattices
(:data:`LATTICES`, docs/maps.md#the-voxel-map):

- ``"round"`` (the default): index ``round(p / voxel_size)`` (half to even, as ``torch.round``),
  centre ``index * voxel_size``: RayFronts' ``geometry3d.pointcloud_to_sparse_voxels``, whose
  evaluation (``scripts/semseg_eval.py``) the paper's Table 2 follows;
- ``"floor"``: index ``floor(p / voxel_size)``, centre ``(index + 0.5) * voxel_size``.

The index is computed in float64 (``points.double() / voxel_size``) (:func:`voxel_indices`,
:func:`voxel_centres`, :func:`transform_keys`: the lattice is the first half of a key, its
packing the second). :class:`KeyIndex` finds the row of a key in a sparse map.
"""

from __future__ import annotations

import math

import torch
from torch import Tensor

from resireg.specs.mapping import LATTICES

__all__ = [
    "KEY_BITS",
    "LATTICES",
    "MAX_INDEX",
    "KeyIndex",
    "check_lattice",
    "check_voxel_size",
    "lattice_index",
    "lattice_transform",
    "pack_keys",
    "transform_keys",
    "unpack_keys",
    "voxel_centres",
    "voxel_indices",
]

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


# ----------------------------------------------------------------------------- the lattice
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
