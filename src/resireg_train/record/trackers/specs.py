"""The trackers by name (``tracker=<name>``, ``conf/tracker/<name>.yaml``): one table,
:data:`TRACKER_SPECS`, read before anything heavy loads (each entry names its
:class:`~resireg_train.record.trackers.base.Tracker` class, one module per tracker beside
:mod:`~resireg_train.record.trackers.base`).

Adding a tracker:

1. a :class:`Tracker` subclass (its ``address``, ``begin``, ``lightning_logger``, ``end``:
   those it needs), in a module of its own under :mod:`resireg_train.record.trackers`;
2. a :class:`TrackerSpec` entry below: its name, the class as ``"module:Class"``, one line of
   what it records, and the rules of its own keys (those that are not its Lightning logger's
   keywords: ``check_timeout``, ``unreachable``, ``filename``...);
3. ``conf/tracker/<name>.yaml`` holding one block, ``<name>:``, with its Lightning logger's
   ``_target_`` and keywords (a training run instantiates it) and its own keys' defaults.

``tracker=<name>`` then runs it for ``resireg-train``, ``resireg-eval`` and ``resireg-map``;
``tests/resireg_train/record/test_records.py`` checks that every table entry has its conf file and every conf file
its entry.
"""

from __future__ import annotations

from dataclasses import dataclass, field

from resireg.specs.rules import Rule, number, one_of
from resireg.specs.table import SpecTable

__all__ = ["TRACKER_SPECS", "TrackerSpec"]

#: The own keys of a tracker that needs a network: how long to wait for it, and what to do
#: when it cannot be reached.
_NETWORK: dict[str, Rule] = {
    "check_timeout": number(0, strict=True, finite=True),
    "unreachable": one_of(("refuse", "warn")),
}


@dataclass(frozen=True)
class TrackerSpec:
    """One tracker: its name (the key under ``tracker:``), its :class:`Tracker` class
    (``"module:Class"``), what it records, and the rules of its own keys in
    ``conf/tracker/<name>.yaml`` (the keys its Lightning logger does not take)."""

    name: str
    target: str
    summary: str
    params: dict[str, Rule] = field(default_factory=dict)

    @property
    def config(self) -> str:
        """Its defaults' file."""
        return f"conf/tracker/{self.name}.yaml"

    def load(self) -> type:
        """The :class:`~resireg_train.record.trackers.base.Tracker` subclass (imported now)."""
        from resireg.specs.table import load

        return load(self.target)


TRACKER_SPECS: SpecTable[TrackerSpec] = SpecTable("tracker", [
    TrackerSpec("csv", "resireg_train.record.trackers.csv:CsvTracker",
                "metrics.csv: training's every step and epoch (always written), an evaluation's "
                "or a map's final metrics as one row", {"filename": (
                    lambda v: isinstance(v, str) and bool(v) and "/" not in v,
                    "a file name (no folder)")}),
    TrackerSpec("tensorboard", "resireg_train.record.trackers.tensorboard:TensorBoardTracker",
                "<run>/tensorboard: training's curves; an evaluation's or a map's final "
                "metrics as scalars and its provenance as text"),
    TrackerSpec("mlflow", "resireg_train.record.trackers.mlflow:MlflowTracker",
                "one MLflow run per job (a sweep's jobs under one parent): config, provenance "
                "tags, final metrics, per-class IoU table, the run's files", dict(_NETWORK)),
    TrackerSpec("wandb", "resireg_train.record.trackers.wandb:WandbTracker",
                "one W&B run per job (a sweep's jobs in one group): config, curves, "
                "results.json's summary", dict(_NETWORK)),
], where="resireg_train.record.trackers.specs")  # fmt: skip
