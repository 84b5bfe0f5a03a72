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
