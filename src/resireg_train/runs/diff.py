"""``resireg-runs diff A B``: what differs between two runs (their config, their provenance
without what differs for every pair, their metrics), key by key (:func:`diff_runs`).

Imported by ``resireg_train.cli.runs`` and rerun's verdict
(:mod:`resireg_train.runs.rerun.verdict`).
"""

from __future__ import annotations

from collections.abc import Mapping
from typing import Any

from resireg.specs.tree import flatten
from resireg_train.runs.index import Run

__all__ = ["diff_runs"]


def _compare(a: Mapping[str, Any], b: Mapping[str, Any]) -> list[tuple[str, Any, Any]]:
    keys = sorted(set(a) | set(b))
    return [(k, a.get(k), b.get(k)) for k in keys if a.get(k) != b.get(k)]


#: Provenance fields that differ between any two runs and say nothing about the result.
_VOLATILE = ("provenance.run_id", "provenance.time.", "provenance.machine.pid",
             "provenance.environment.command", "provenance.environment.config_sha256")  # fmt: skip


def diff_runs(a: Run, b: Run) -> dict[str, list[tuple[str, Any, Any]]]:
    """``{"config", "provenance", "metrics"}``: each differing key with A's and B's value
    (provenance without what differs for every pair of runs: ids, times, PIDs)."""
    prov = [row for row in _compare(flatten(a.provenance, "provenance"),
                                    flatten(b.provenance, "provenance"))
            if not row[0].startswith(_VOLATILE)]  # fmt: skip
    return {
        "config": _compare(a.config, b.config),
        "provenance": prov,
        "metrics": _compare(a.metrics, b.metrics),
    }
