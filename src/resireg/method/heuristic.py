"""The prototype heuristic: how many ReSiReg Full prototypes to use for a batch size.

The batch x prototype ablation (``conf/sweep/prototype_batch.yaml``) measures OVSS mIoU
on a grid; ``resireg-report`` fits ``n(B) = a + b * ln(B)`` by least squares to the best
prototype count of every batch size and writes it as JSON. Larger batches hold more
distinct content, so the best count grows with B; a log law captures the diminishing
growth seen as images start repeating content.
"""

from __future__ import annotations

import json
import math
import os
from collections.abc import Sequence
from dataclasses import asdict, dataclass
from pathlib import Path

from resireg.specs.rules import check_batch_size

__all__ = ["PrototypeHeuristic", "HEURISTIC_ENV"]

HEURISTIC_ENV = "RESIREG_PROTOTYPE_HEURISTIC"


@dataclass(frozen=True)
class PrototypeHeuristic:
    """``n(B) = round(intercept + slope * ln B)``, clipped to ``[min_prototypes, max_prototypes]``."""

    intercept: float
    slope: float
    min_prototypes: int = 1
    max_prototypes: int = 100_000

    def __call__(self, batch_size: int) -> int:
        check_batch_size(batch_size)
        n = round(self.intercept + self.slope * math.log(batch_size))
        return int(min(self.max_prototypes, max(self.min_prototypes, n)))

    @classmethod
    def fit(cls, batch_sizes: Sequence[int], best_prototypes: Sequence[int]) -> PrototypeHeuristic:
        """Least-squares fit of the best prototype count against ``ln(batch size)``."""
        if len(batch_sizes) != len(best_prototypes) or not batch_sizes:
            raise ValueError("fit needs one best prototype count per batch size (and at least one)")
        xs = [math.log(b) for b in batch_sizes]
        ys = [float(n) for n in best_prototypes]
        mx, my = sum(xs) / len(xs), sum(ys) / len(ys)
        sxx = sum((x - mx) ** 2 for x in xs)
        slope = (
            sum((x - mx) * (y - my) for x, y in zip(xs, ys, strict=True)) / sxx if sxx > 0 else 0.0
        )
        return cls(
            intercept=my - slope * mx,
            slope=slope,
            min_prototypes=int(min(best_prototypes)),
            max_prototypes=int(max(best_prototypes)),
        )

    def save(self, path: str | os.PathLike) -> None:
        Path(path).write_text(
            json.dumps({"form": "intercept + slope * ln(batch_size)", **asdict(self)}, indent=2)
        )

    @classmethod
    def load(cls, path: str | os.PathLike) -> PrototypeHeuristic:
        data = json.loads(Path(path).read_text())
        return cls(
            intercept=float(data["intercept"]),
            slope=float(data["slope"]),
            min_prototypes=int(data.get("min_prototypes", 1)),
            max_prototypes=int(data.get("max_prototypes", 100_000)),
        )

    @classmethod
    def resolve(cls, source: object = None) -> PrototypeHeuristic:
        """A heuristic from a callable, a JSON path, or (``None``) ``$RESIREG_PROTOTYPE_HEURISTIC``."""
        if callable(source):
            return source  # type: ignore[return-value]
        if source is None:
            source = os.environ.get(HEURISTIC_ENV)
            if not source:
                raise ValueError(
                    "n_prototypes='auto' needs a fitted prototype heuristic: pass heuristic=PATH "
                    f"(the prototype_heuristic.json that `resireg-report` writes for a "
                    f"prototype_batch sweep) or set ${HEURISTIC_ENV} to that file"
                )
        path = Path(str(source))
        if not path.is_file():
            raise ValueError(f"heuristic file {str(path)!r} does not exist")
        return cls.load(path)
