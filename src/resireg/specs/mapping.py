"""The 3D mapping library's named options, without importing torch.

Read by :mod:`resireg.mapping` (its own argument checks) and by the ScanNet protocol's config
rules (``resireg_train.data.specs``), so each list is written once.
"""

from __future__ import annotations

__all__ = ["LATTICES", "POINTS"]

#: Voxel lattices: voxel ``i`` covers ``[(i - 1/2) v, (i + 1/2) v)`` (``round``, RayFronts)
#: or ``[i v, (i + 1) v)`` (``floor``) (:mod:`resireg.mapping.voxels`).
LATTICES = ("round", "floor")
#: How features are lifted to 3D: one point per patch centre, or every pixel at its patch's
#: depth (:class:`resireg.mapping.SemanticMap`).
POINTS = ("patch", "pixel")
