"""The labels of a segmentation, read without torch (so ``resireg-segment`` reports bad
``--labels`` before the models load)."""

from __future__ import annotations

from collections.abc import Sequence

__all__ = ["parse_labels"]


def parse_labels(labels: str | Sequence[str], name: str = "labels") -> tuple[str, ...]:
    """``"floor,chair, table"`` or a list -> ``("floor", "chair", "table")``; empty or
    repeated labels are an error naming ``name``."""
    items = labels.split(",") if isinstance(labels, str) else list(labels)
    out = tuple(str(x).strip() for x in items)
    if not out or any(not x for x in out):
        raise ValueError(f"{name}={labels!r}: expected non-empty labels separated by commas")
    if len(set(out)) != len(out):
        raise ValueError(f"{name}={labels!r}: a label is repeated")
    if len(out) > 255:
        raise ValueError(f"{name}: {len(out)} labels; the label map PNG holds at most 255")
    return out
