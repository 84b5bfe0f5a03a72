"""Merging maps of several mapping runs: what keeps two maps apart (:func:`merge_differences`)
and the merge itself (:func:`merge_into`), for :meth:`SemanticMap.merge
<resireg.mapping.SemanticMap.merge>` (its docstring: the transforms and the parts)."""

from __future__ import annotations

from typing import Any

import torch

from resireg.errors import MapError
from resireg.mapping.map_file import MAX_PARTS

#: A :class:`~resireg.mapping.SemanticMap` (not imported: the map sits above this module).
SemanticMap = Any

__all__ = ["merge_differences", "merge_into"]


def merge_differences(target: SemanticMap, other: SemanticMap) -> list[str]:
    """What keeps ``other`` from merging into ``target``: settings (but ``max_voxels``),
    the feature dimension, the basis (by SHA-256, not by where it was read from: a map
    fitted its own, the next run read it from that map's folder) and the encoder's weights
    (by the digest ``resireg-map`` and the live node record in
    ``meta["identity"]["weights"]``)."""

    def compared(smap: SemanticMap) -> dict[str, Any]:
        out = {k: v for k, v in smap.settings().items() if k != "max_voxels"}
        if out.get("compact") is not None:
            out["compact"] = {k: v for k, v in out["compact"].items() if k != "basis"}
        return out

    mine, theirs = compared(target), compared(other)
    out = [f"{k}: {mine.get(k)!r} here, {theirs.get(k)!r} in the other map"
           for k in sorted(set(mine) | set(theirs)) if mine.get(k) != theirs.get(k)]  # fmt: skip
    if target.dim is not None and other.dim is not None and target.dim != other.dim:
        out.append(f"dim: {target.dim} here, {other.dim} in the other map")
    if (target.basis_sha256 or other.basis_sha256) and target.basis_sha256 != other.basis_sha256:
        out.append(f"basis_sha256: {target.basis_sha256} here, {other.basis_sha256} in the "
                   "other map (map the second run with compact.basis=<the first map>)")  # fmt: skip
    a = (target.meta.get("identity") or {}).get("weights")
    b = (other.meta.get("identity") or {}).get("weights")
    if a is not None and b is not None and a != b:
        out.append(f"encoder weights: {a} here, {b} in the other map")
    return out


@torch.no_grad()
def merge_into(target: SemanticMap, other: SemanticMap, transform: Any = None) -> SemanticMap:
    """(:meth:`SemanticMap.merge <resireg.mapping.SemanticMap.merge>`) Add another map of the same encoder and settings (another mapping run) to ``target``,
    in place; returns ``target``.

    ``transform``: ``None`` (the same world frame) or the ``[4, 4]`` rigid transform from
    ``other``'s world to ``target``'s. One that keeps the lattice (a rotation by multiples
    of 90 degrees about the axes, e.g. about the vertical, and a translation by whole
    voxels) re-keys the voxels exactly: the result equals mapping the transformed frames
    (keys and counts exactly, means to float64 / the storage's rounding). Any other
    transform moves each voxel centre and takes the voxel it falls in: an approximation
    of re-mapping the frames (points near a voxel face change voxels; docs/benchmarks.md
    gives its measured error). A map that differs (:func:`merge_differences`) is refused,
    naming what differs, and so is one that shares a part (``parts``) with ``target``
    (a map and a merge that holds it): merged, its points would count twice. The result
    is made of both maps' parts."""
    mine = set(target.parts)
    shared = next((p for p in other.parts if p in mine), None)
    if shared is not None:  # a map merged with one it is part of: its points count twice
        raise MapError(f"merge: the maps share the part {shared} (one holds the other's "
                       "frames: merged, they would count twice)")  # fmt: skip
    parts = [*target.parts, *other.parts]
    if len(parts) > MAX_PARTS:
        raise MapError(f"merge: the maps are made of {len(parts)} parts, more than "
                       f"{MAX_PARTS}")  # fmt: skip
    target.fit_pending()
    other.fit_pending()
    target.store.adopt_basis(other.store)
    differ = merge_differences(target, other)
    if differ:
        raise MapError(f"merge: the maps differ ({len(differ)}): " + "; ".join(differ))
    target.store.merge_from(other.store, transform)
    target.frames += other.frames
    target.windows += other.windows
    target.parts = parts
    step = None if transform is None else torch.as_tensor(transform).double().tolist()
    target.meta.setdefault("merged", []).append(
        {"frames": other.frames, "voxels": len(other), "transform": step,
         "identity": (other.meta or {}).get("identity")})  # fmt: skip
    return target
