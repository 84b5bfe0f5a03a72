"""Nested settings as dotted leaves: the one flattener and the one comparison of two settings
trees (a config, a map's recorded identity, a run record's block), torch-free.

Used wherever a nested mapping is shown, compared or logged key by key: the run record's
columns and tracker parameters, the resume checks of ``resireg-train``, ``resireg-map`` and the
live node, and the node's parameters.
"""

from __future__ import annotations

from collections.abc import Mapping
from typing import Any

__all__ = ["MISSING", "differences", "flatten"]


class _Missing:
    """The value of a key one side of :func:`differences` lacks."""

    def __repr__(self) -> str:
        return "<absent>"


#: A key one tree lacks, in :func:`differences`' output (its ``repr`` is ``<absent>``).
MISSING: Any = _Missing()


def flatten(tree: Any, prefix: str = "") -> dict[str, Any]:
    """``{"a.b.c": value}``: the dotted paths of ``tree``'s leaves (anything that is not a
    mapping; lists are values), each after ``prefix``. An empty mapping has no leaf; a
    ``tree`` that is not a mapping is one leaf named ``prefix``."""
    if not isinstance(tree, Mapping):
        return {prefix: tree}
    out: dict[str, Any] = {}
    for key, value in tree.items():
        path = f"{prefix}.{key}" if prefix else str(key)
        if isinstance(value, Mapping):
            out.update(flatten(value, path))
        else:
            out[path] = value
    return out


def differences(
    a: Mapping[str, Any], b: Mapping[str, Any], skip: tuple[str, ...] = ()
) -> list[tuple[str, Any, Any]]:
    """``(key, value in a, value in b)`` for every leaf whose values differ, a key one side
    lacks included (its value :data:`MISSING`), the shallowest keys first, then by name.
    ``skip``: top-level keys left out (a resume's own ``ckpt_path``)."""
    left, right = flatten(a), flatten(b)
    keys = sorted(
        (k for k in set(left) | set(right) if k.split(".")[0] not in skip),
        key=lambda k: (k.count("."), k),
    )
    return [
        (k, left.get(k, MISSING), right.get(k, MISSING))
        for k in keys
        if left.get(k, MISSING) != right.get(k, MISSING)
    ]
