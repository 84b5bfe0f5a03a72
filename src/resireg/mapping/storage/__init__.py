"""How a :class:`~resireg.mapping.SemanticMap` stores its voxels (``storage=``,
:data:`~resireg.specs.mapping.STORAGES`): one interface (:class:`.base.MapStorage`), an exact
implementation (:mod:`.exact`: running sums) and a compact one (:mod:`.compact`: low-precision
unit features, optionally projected by a basis). The map asks its storage; it never branches on
the kind (:func:`make_storage` picks the class by name). Imported by
:mod:`resireg.mapping` only (the map and its query helpers); it imports the voxel maps, the
lifting and the basis below it."""

from __future__ import annotations

from typing import Any

from resireg.mapping.storage.base import MapStorage
from resireg.mapping.storage.compact import CompactStorage
from resireg.mapping.storage.exact import ExactStorage

__all__ = ["STORAGE_TYPES", "make_storage"]

#: The storage class of each ``storage=`` name (:data:`~resireg.specs.mapping.STORAGES`).
STORAGE_TYPES: dict[str, type[MapStorage]] = {"exact": ExactStorage, "compact": CompactStorage}


def make_storage(storage: str, **settings: Any) -> MapStorage:
    """The storage named ``storage``, built from the map's ``settings`` (:class:`MapStorage`'s
    arguments); a ValueError naming the value when no storage has that name."""
    if storage not in STORAGE_TYPES:
        raise ValueError(f"storage={storage!r}: expected one of {list(STORAGE_TYPES)}")
    return STORAGE_TYPES[storage](**settings)
