"""The 3D mapping library's named options and the rules of a map's settings, without importing torch.

Read by :mod:`resireg.mapping` (its own argument checks), by ``resireg-map``'s config check
(``resireg_train.checks.map``), by the live node's parameters (:mod:`resireg.ros2.settings`) and by
the ScanNet protocol's config rules (``resireg_train.data.specs``), so each list and each rule
is written once (:data:`MAP_RULES`).
"""

from __future__ import annotations

from collections.abc import Mapping
from typing import Any

from resireg.specs.rules import Rule, integer, number, one_of, optional_int

__all__ = [
    "COMPACT_DTYPES",
    "LATTICES",
    "MAP_RULES",
    "POINTS",
    "STORAGES",
    "SUM_DTYPES",
    "compact_defaults",
    "map_errors",
]

#: Voxel lattices: voxel ``i`` covers ``[(i - 1/2) v, (i + 1/2) v)`` (``round``, RayFronts)
#: or ``[i v, (i + 1) v)`` (``floor``) (:mod:`resireg.mapping.keys`).
LATTICES = ("round", "floor")
#: How features are lifted to 3D: one point per patch centre, or every pixel at its patch's
#: depth (:class:`resireg.mapping.SemanticMap`).
POINTS = ("patch", "pixel")
#: How a map stores its voxels: ``exact`` (running sums of ``sum_dtype``) or ``compact``
#: (low-precision unit features, optionally projected: :mod:`resireg.mapping.compact`).
STORAGES = ("exact", "compact")
#: The dtypes of an ``exact`` map's feature sums.
SUM_DTYPES = ("float64", "float32")
#: The dtypes of a ``compact`` map's stored features.
COMPACT_DTYPES = ("float16", "bfloat16")


def _basis_ok(v: Any) -> bool:
    return v is None or (isinstance(v, str) and bool(v))


#: The rule of every map setting, by its key in ``conf/map.yaml`` (``compact.*``: the keys of
#: its ``compact`` block). The one place these rules are written: ``resireg-map``, the live
#: node and the 3D task check their values here.
MAP_RULES: dict[str, Rule] = {
    "window": integer(1),
    "voxel_size": number(0, strict=True, finite=True),
    "points": one_of(POINTS),
    "lattice": one_of(LATTICES),
    "sum_dtype": one_of(SUM_DTYPES),
    "max_voxels": optional_int(1),
    "short_side": optional_int(1),
    "save_every": integer(0),
    "storage": one_of(STORAGES),
    "compact.dtype": one_of(COMPACT_DTYPES),
    "compact.dim": optional_int(1),
    "compact.basis": (
        _basis_ok,
        "null (fitted on the first frames) or a map folder, run folder or .safetensors file "
        "holding its basis",
    ),
    "compact.basis_rows": integer(1),
    "compact.hot_voxels": integer(0),
}


def compact_defaults(conf: Any = None) -> dict[str, Any]:
    """The ``compact`` block of ``conf/map.yaml`` (``conf``: the folder; default the project's
    :func:`resireg.specs.table.conf_dir`): the compact storage's settings wherever a map is made
    outside ``resireg-map`` (the 3D task), read from their one source."""
    from pathlib import Path

    from resireg.specs.table import compose_conf, conf_dir

    folder = Path(conf_dir() if conf is None else conf)
    block = compose_conf(folder, "map").get("compact")
    if block is None or not isinstance(block[0], Mapping):
        raise ValueError(f"{folder / 'map.yaml'}: no compact block")
    return dict(block[0])


def _lookup(values: Mapping[str, Any], key: str) -> tuple[bool, Any]:
    node: Any = values
    for part in key.split("."):
        if not isinstance(node, Mapping) or part not in node:
            return False, None
        node = node[part]
    return True, node


def map_errors(values: Mapping[str, Any], prefix: str = "", keys: Any = None) -> list[str]:
    """``<prefix><key>=<value>: expected <what>`` for every setting of :data:`MAP_RULES` (or of
    ``keys``) present in ``values`` (nested: ``{"compact": {"dim": 0}}``) that its rule
    refuses; a ``compact`` block with a key of no rule is named too."""
    errors = []
    for key in MAP_RULES if keys is None else keys:
        present, value = _lookup(values, key)
        if present and not MAP_RULES[key][0](value):
            errors.append(f"{prefix}{key}={value!r}: expected {MAP_RULES[key][1]}")
    block = values.get("compact") if isinstance(values, Mapping) else None
    if keys is None and isinstance(block, Mapping):
        known = {k.split(".", 1)[1] for k in MAP_RULES if k.startswith("compact.")}
        errors += [f"{prefix}compact.{k}: no such setting (expected one of {sorted(known)})"
                   for k in block if k not in known]  # fmt: skip
    return errors
