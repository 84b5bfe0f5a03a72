"""The best voxels of a query (:func:`best_voxels`, a :class:`TopK`) and the voxels of a region
(:func:`region_rows`: a box or a ball, looked up in the key index without reading the map), over
a map's storage (:class:`~resireg.mapping.storage.base.MapStorage`)."""

from __future__ import annotations

import math
from typing import Any, NamedTuple

import torch
from torch import Tensor

from resireg.mapping.keys import unpack_keys, voxel_centres
from resireg.mapping.storage.base import MapStorage

__all__ = ["TopK", "best_voxels", "region_rows"]


class TopK(NamedTuple):
    """The best voxels of a text (:meth:`SemanticMap.top_k <resireg.mapping.SemanticMap.top_k>`),
    best first (ties: the lower voxel index, in lexicographic order)."""

    indices: Tensor  #: ``[k, 3]`` int64 voxel indices
    centres: Tensor  #: ``[k, 3]`` float32 voxel centres
    scores: Tensor  #: ``[k]`` float64 cosine scores (the voxels' features as :meth:`features` gives them)


def best_voxels(
    store: MapStorage, q: Tensor, k: int, box: Any, centre: Any, radius: float | None,
    approx: tuple[Tensor, Tensor] | None = None,
) -> TopK:  # fmt: skip
    """One query's ``k`` best voxels (``q`` ``[k']`` in the stored space), among those of a
    region when one is given (:func:`region_rows`); ``approx``: its low-precision scores and
    their bound when several queries were scored in one pass (:meth:`MapStorage.joint_scores`).
    The candidates' float64 scores come from the storage (:meth:`MapStorage.candidates`)."""
    vmap = store.voxels
    if vmap is None or not len(vmap):
        empty = torch.empty(0, 3, dtype=torch.int64)
        return TopK(empty, empty.float(), torch.empty(0, dtype=torch.float64))
    q = q[None].to(store.device)
    if box is not None or centre is not None or radius is not None:
        rows = region_rows(store, box, centre, radius)
        scores = vmap.exact_scores(rows, q)[:, 0] if rows.numel() else q.new_zeros(0).double()
    else:
        rows, scores = store.candidates(q, k, approx)
    keys = vmap.keys[rows]
    by_key = torch.argsort(keys)
    best = by_key[torch.argsort(-scores[by_key], stable=True)[:k]]
    index = unpack_keys(keys[best])
    return TopK(index.cpu(), voxel_centres(index, store.voxel_size, store.lattice).cpu(),
                scores[best].cpu())  # fmt: skip


def region_rows(store: MapStorage, box: Any, centre: Any, radius: float | None) -> Tensor:
    """Rows of the voxels whose centre lies in ``box`` or within ``radius`` of ``centre``."""
    if box is not None and (centre is not None or radius is not None):
        raise ValueError("region: give box= or centre= and radius=, not both")
    if box is not None:
        b = torch.as_tensor(box, dtype=torch.float64).reshape(-1)
        if b.numel() != 6 or not bool(torch.isfinite(b).all()) or bool((b[3:] < b[:3]).any()):
            raise ValueError(f"box={box!r}: expected [[x0, y0, z0], [x1, y1, z1]] with x0 "
                             "<= x1 ... (metres)")  # fmt: skip
        lo, hi = b[:3], b[3:]
    else:
        c = torch.as_tensor(centre if centre is not None else [], dtype=torch.float64)
        r = float("nan") if radius is None else float(radius)
        if c.numel() != 3 or not bool(torch.isfinite(c).all()) or not (r >= 0) or math.isinf(r):
            raise ValueError(f"centre={centre!r}, radius={radius!r}: expected a point "
                             "[x, y, z] and a finite radius >= 0 (metres)")  # fmt: skip
        lo, hi = c - r, c + r
    shift = 0.0 if store.lattice == "round" else 0.5
    first = torch.floor(lo / store.voxel_size - shift).to(torch.int64)
    last = torch.ceil(hi / store.voxel_size - shift).to(torch.int64)
    rows = store.voxels.rows_in_box(first, last)
    if not rows.numel():
        return rows
    at = voxel_centres(unpack_keys(store.voxels.keys[rows]), store.voxel_size, store.lattice)
    at = at.double()
    if box is not None:
        keep = ((at >= lo.to(at.device)) & (at <= hi.to(at.device))).all(dim=1)
    else:
        keep = (at - c.to(at.device)).norm(dim=1) <= r
    return rows[keep]
