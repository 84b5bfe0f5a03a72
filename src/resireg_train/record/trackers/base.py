"""What every tracker shares: the :class:`Tracker` base class, the trackers of one run
(:class:`RunTrackers`, built from :data:`~resireg_train.record.trackers.specs.TRACKER_SPECS`
and driven by its :class:`~resireg_train.record.run_record.RunRecord`), the process state they
put back, and the metrics and keys they show.

A tracker does up to four things, each a method of its :class:`Tracker` class
(one module per tracker: :mod:`~resireg_train.record.trackers.csv`,
:mod:`~resireg_train.record.trackers.tensorboard`, :mod:`~resireg_train.record.trackers.mlflow`,
:mod:`~resireg_train.record.trackers.wandb`):

- :meth:`Tracker.address`: the network address it needs, checked before any work
  (:func:`resireg.network.reach`, ``tracker.<name>.check_timeout`` seconds): an unreachable tracker refuses
  the run in one line (:class:`TrackerUnreachable`) or, with ``tracker.<name>.unreachable=warn``,
  is left out with a warning and the run completes with its local records (``results.json``'s
  ``tracking.unreachable`` names it);
- :meth:`Tracker.begin`: at the run's start (W&B: its run, given the resolved config);
- :meth:`Tracker.lightning_logger`: a training run's Lightning logger (its curves);
- :meth:`Tracker.running`: once its run exists, what records the run while it runs (MLflow's
  system-metrics monitor);
- :meth:`Tracker.end`: at the run's end, after the final status is written, with the record
  (MLflow: parameters, provenance tags, final metrics, artifacts; TensorBoard and CSV: an
  evaluation's or a map's final metrics; W&B: the summary, then the run is finished).

What the trackers change in the process that runs them (its environment, MLflow's tracking URI
and active run, W&B's service) is put back when they finish (:class:`ProcessState`): a run
called from Python leaves its caller's process as it found it.

Every value a tracker receives has the passwords of its URLs masked
(:func:`resireg.secrets.mask_text`); adding a tracker: :mod:`~resireg_train.record.trackers.specs`.
"""

from __future__ import annotations

import logging
import math
import os
import re
import sys
from collections.abc import Mapping
from dataclasses import dataclass
from typing import Any
from urllib.parse import urlsplit

from resireg.errors import ConfigError, ResiregError
from resireg.network import reach
from resireg.secrets import mask_text, mask_url
from resireg_train.record.settings import RecordSettings
from resireg_train.record.trackers.specs import TRACKER_SPECS, TrackerSpec

__all__ = [
    "ProcessState",
    "RunTrackers",
    "Tracker",
    "TrackerUnreachable",
    "map_counts",
    "mlflow_key",
    "note_tracking",
    "recorded_id",
    "run_metrics",
]

log = logging.getLogger(__name__)


class TrackerUnreachable(ResiregError, RuntimeError):
    """A tracker's server could not be reached before the run started (one line: the tracker,
    the address with its password masked, the reason, and the keys that change it)."""


# --------------------------------------------------------------------- what trackers show
_KEY = re.compile(r"[^A-Za-z0-9_\-. /]")  # what MLflow accepts in a metric or param name


def mlflow_key(name: str) -> str:
    """``name`` with the characters MLflow refuses in a key replaced by ``_``
    (``val/ovss/x/miou_full@n_prototypes:24`` -> ``val/ovss/x/miou_full_n_prototypes_24``)."""
    return _KEY.sub("_", name)


def _number(v: Any) -> bool:
    return isinstance(v, (int, float)) and not isinstance(v, bool) and math.isfinite(float(v))


def map_counts(record: Mapping[str, Any]) -> dict[str, float]:
    """A ``resireg-map`` record's counts (``map/voxels``, ``map/frames``, ``frames/used``,
    ...): what a map run has for metrics. Empty for other runs."""
    counts = {}
    for part in ("map", "frames"):
        section = record.get(part)
        if isinstance(section, Mapping):
            counts.update({f"{part}/{k}": float(v) for k, v in section.items() if _number(v)})
    return counts


def run_metrics(record: Mapping[str, Any]) -> dict[str, float]:
    """A run record's metrics as a tracker shows them: every finite final value and, for a
    map, its counts (:func:`map_counts`)."""
    metrics = {k: float(v) for k, v in (record.get("final") or {}).items() if _number(v)}
    return {**metrics, **map_counts(record)}


def note_tracking(record: Any, key: str, value: Any) -> None:
    """Add ``key: value`` to the record's ``tracking`` (the job's writer only)."""
    if record.writer and value is not None:
        tracking = record.get("tracking") or {}
        if tracking.get(key) != value:
            record.update(tracking={**tracking, key: value})


def recorded_id(record: Any, key: str) -> str | None:
    """``tracking.<key>`` of the run's record, the id a resumed run continues."""
    value = (record.get("tracking") or {}).get(key) if record.writer else None
    return value if isinstance(value, str) and value else None


# ------------------------------------------------------------------------------- trackers
class Tracker:
    """One tracker of one run (base class: every hook does nothing).

    Args:
        spec: its table entry.
        settings: its ``tracker.<name>`` block (plain values).
        run: the run's settings (:class:`~resireg_train.record.settings.RecordSettings`).
        record: the run's :class:`~resireg_train.record.run_record.RunRecord`.
    """

    def __init__(
        self, spec: TrackerSpec, settings: dict[str, Any], run: RecordSettings, record: Any
    ):
        self.spec = spec
        self.settings = settings
        self.run = run
        self.record = record
        self._logger: Any = None

    @property
    def training(self) -> bool:
        """Whether the run trains (Lightning logs its curves through :meth:`lightning_logger`)."""
        return self.run.training

    def own(self, key: str) -> Any:
        """One of its own keys (``tracker.<name>.<key>``); conf/tracker/<name>.yaml sets each."""
        if key not in self.settings:
            raise ConfigError(f"tracker.{self.spec.name}.{key}: missing ({self.spec.config} "
                              "sets it)")  # fmt: skip
        return self.settings[key]

    def logger_settings(self) -> dict[str, Any]:
        """Its block without its own keys: its Lightning logger's ``_target_`` and keywords."""
        return {k: v for k, v in self.settings.items() if k not in self.spec.params}

    def address(self) -> str | None:
        """The URL it must reach over the network (checked before any work), or ``None``."""
        return None

    def begin(self) -> None:
        """At the run's start, after the check."""

    def running(self) -> None:
        """Once the tracker's run exists (after :meth:`begin` for an evaluation or a map, after
        the Lightning loggers are made for a training run): start what records the run while
        it runs (MLflow: its system-metrics monitor)."""

    def lightning_logger(self, resume_step: int | None) -> Any:
        """A training run's Lightning logger: its block's ``_target_`` instantiated (made
        once); ``None`` without one."""
        if self._logger is None:
            settings = self.logger_settings()
            if "_target_" not in settings:
                return None
            import hydra

            self._logger = hydra.utils.instantiate(settings)
        return self._logger

    def end(self, record: dict[str, Any], failed: bool) -> dict[str, Any] | None:
        """At the run's end, after the final status is written: record the run (``record``:
        its ``results.json``). Returns fields to add to the record's ``tracking``, or
        ``None``."""
        return None


_MLFLOW_URI = "mlflow.tracking._tracking_service.utils"  # holds the URI set_tracking_uri set

_WANDB_SETUP = "wandb.sdk.wandb_setup"  # holds W&B's singleton (its service connection)


def _wandb_service() -> bool:
    """Whether this process holds a W&B service connection (``wandb.setup``'s singleton, made
    by this process, connected); W&B not imported: ``False``."""
    setup = getattr(sys.modules.get(_WANDB_SETUP), "_singleton", None)
    return bool(setup is not None and getattr(setup, "_pid", None) == os.getpid()
                and getattr(setup, "_connection", None) is not None)  # fmt: skip


@dataclass(frozen=True)
class ProcessState:
    """What a run's trackers change in the process that runs them, as it was: the
    environment (MLflow's credentials from a ``tracking_uri``, the variables W&B and
    Lightning set), MLflow's process-wide tracking URI (Lightning's ``MLFlowLogger`` sets it)
    and active run, and whether a W&B service runs (W&B starts one and keeps it). Read
    (:meth:`now`) before the trackers start, put back (:meth:`restore`) once they ended, so a
    run called from Python (a notebook, a search's trials) leaves the caller's process as it
    found it. Only libraries already imported are read (nothing heavy is imported here)."""

    environ: dict[str, str]
    mlflow_uri: str | None
    mlflow_run: str | None
    wandb_service: bool

    @classmethod
    def now(cls) -> ProcessState:
        utils = sys.modules.get(_MLFLOW_URI)
        run = None
        if "mlflow" in sys.modules:
            active = sys.modules["mlflow"].active_run()
            run = active.info.run_id if active is not None else None
        return cls(dict(os.environ), getattr(utils, "_tracking_uri", None), run,
                   _wandb_service())  # fmt: skip

    def restore(self) -> None:
        """Put the state back: MLflow's runs started since ended (as MLflow's ``end_run``
        ends them), its tracking URI set back, a W&B service started since torn down
        (``wandb.teardown``), then every environment variable as it was (set, changed or
        removed since). A step that fails is a warning naming it; the others still run."""
        steps = []
        if "mlflow" in sys.modules:
            steps.append(("MLflow's active run", self._end_mlflow_runs))
        if sys.modules.get(_MLFLOW_URI) is not None:
            steps.append(("MLflow's tracking URI", self._mlflow_uri_back))
        if not self.wandb_service and _wandb_service():
            steps.append(("W&B's service", self._wandb_down))
        for what, step in steps:
            try:
                step()
            except (Exception, SystemExit) as err:  # (wandb.teardown may sys.exit)
                log.warning("could not put back %s: %s", what, mask_text(str(err)))
        for key in set(os.environ) - set(self.environ):
            del os.environ[key]
        for key, value in self.environ.items():
            if os.environ.get(key) != value:
                os.environ[key] = value

    def _end_mlflow_runs(self) -> None:
        import mlflow

        for _ in range(100):  # (a stack of nested runs; never a loop without end)
            active = mlflow.active_run()
            if active is None or active.info.run_id == self.mlflow_run:
                return
            mlflow.end_run()

    def _mlflow_uri_back(self) -> None:
        utils = sys.modules[_MLFLOW_URI]
        if utils._tracking_uri != self.mlflow_uri:
            utils.set_tracking_uri(self.mlflow_uri)

    @staticmethod
    def _wandb_down() -> None:
        import wandb

        wandb.teardown()


class RunTrackers:
    """The trackers of one run: those its settings name (``tracker``, in its order:
    :attr:`~resireg_train.record.settings.RecordSettings.trackers`), built from
    :data:`TRACKER_SPECS` (an unknown name is a :class:`ConfigError` naming the closest),
    their own keys checked by the entry's rules. Driven by the run's record. What they change
    in the process (:class:`ProcessState`) is put back when they finish."""

    def __init__(self, run: RecordSettings, record: Any) -> None:
        self.run = run
        self.record = record
        self.trackers: list[Tracker] = []
        self.unreachable: dict[str, str] = {}
        self._begun: list[Tracker] = []
        self._before: ProcessState | None = None  # read at start, put back at finish
        for name, plain in run.trackers.items():
            spec = TRACKER_SPECS.find(name)
            if spec is None:
                raise ConfigError(TRACKER_SPECS.unknown(name, setting="tracker"))
            errors = [f"tracker.{name}.{key}={plain[key]!r}: expected {expected}"
                      for key, (check, expected) in spec.params.items()
                      if key in plain and not check(plain[key])]  # fmt: skip
            if errors:
                raise ConfigError("; ".join(errors))
            self.trackers.append(spec.load()(spec, plain, run, record))

    def names(self) -> list[str]:
        return [t.spec.name for t in self.trackers]

    def start(self) -> None:
        """Check every tracker that needs a network (:func:`resireg.network.reach`), then begin each. An
        unreachable one raises :class:`TrackerUnreachable` (``unreachable: refuse``) or is
        left out with a warning (``warn``), named in ``results.json``'s ``tracking``. The
        process's state is read first (:class:`ProcessState`): :meth:`finish` puts it back."""
        if self._before is None:
            self._before = ProcessState.now()
        kept = []
        for tracker in self.trackers:
            url = tracker.address()
            if url is not None:
                timeout = float(tracker.own("check_timeout"))
                why = reach(url, timeout)
                if why is not None:
                    name = tracker.spec.name
                    start = "" if urlsplit(url).hostname is None else "start it, "
                    line = (f"tracker.{name}: cannot reach {mask_url(url)} ({why}); {start}"
                            f"fix its address, or set tracker.{name}.unreachable=warn to run "
                            "with local records only")  # fmt: skip
                    if tracker.own("unreachable") != "warn":
                        raise TrackerUnreachable(line)
                    log.warning("%s; this run goes on without it", line.split("; start")[0])
                    self.unreachable[name] = mask_text(why)
                    continue
            kept.append(tracker)
        self.trackers = kept
        if self.unreachable:
            tracking = self.record.get("tracking") or {}
            self.record.update(tracking={**tracking, "unreachable": self.unreachable})
        for tracker in self.trackers:
            tracker.begin()
            self._begun.append(tracker)
        if not self.run.training:  # a training run's trackers run once its loggers exist
            for tracker in self.trackers:
                tracker.running()

    def lightning_loggers(self, resume_step: int | None) -> list[Any]:
        """A training run's Lightning loggers: ``metrics.csv``'s first (always: it is the
        training's own record), then each tracker's (:meth:`Tracker.lightning_logger`)."""
        csv_tracker = TRACKER_SPECS.get("csv").load()  # the table's entry, loaded lazily
        csv = next((t for t in self.trackers if isinstance(t, csv_tracker)), None)
        csv = csv or csv_tracker.always(self.run, self.record)
        loggers = [csv.lightning_logger(resume_step)]
        for tracker in self.trackers:
            if tracker is not csv and (made := tracker.lightning_logger(resume_step)) is not None:
                loggers.append(made)
        for tracker in self.trackers:
            tracker.running()
        return loggers

    def finish(self, record: dict[str, Any], failed: bool) -> None:
        """Each started tracker records the finished run (:meth:`Tracker.end`); a tracker that
        fails is a warning naming it, never a lost run (``results.json`` keeps everything).
        Then the process's state read at :meth:`start` is put back (:class:`ProcessState`)."""
        added: dict[str, Any] = {}
        try:
            for tracker in self._begun:
                try:
                    added.update(tracker.end(record, failed) or {})
                except Exception as err:  # a tracker down must not fail a finished run
                    log.warning("tracker.%s: could not record the run in %s: %s",
                                tracker.spec.name, self.record.folder,
                                mask_text(str(err)))  # fmt: skip
        finally:
            self._begun = []
            before, self._before = self._before, None
            if before is not None:
                before.restore()
        if added:
            try:
                tracking = self.record.get("tracking") or {}
                self.record.update(tracking={**tracking, **added})
            except OSError as err:
                log.warning("could not add %s to %s: %s", sorted(added), self.record.path, err)
