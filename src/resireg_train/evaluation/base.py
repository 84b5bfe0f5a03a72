"""What ``resireg-eval``'s tasks share (docs/architecture.md#adding-a-task); torch-free (the engines'
shared parts, which import torch, are :mod:`resireg_train.evaluation.engine`).

The task table (:data:`resireg_train.evaluation.specs.TASK_SPECS`) names one :class:`EvalTask`
subclass per ``task``; :func:`resireg_train.cli.eval.evaluate` drives it: ``check`` (source
checks before the encoder loads), ``build`` (dataset and engine), ``run`` (the scoring pass),
``results`` (the task's own ``results.json`` fields), and :func:`write_results` writes what
every task records (scores, per-class IoU, image counts, ELBO prototype counts, seconds) and
fails a run that scored nothing (:func:`require_scored`).
"""

from __future__ import annotations

import logging
from abc import ABC, abstractmethod
from collections import Counter
from collections.abc import Mapping, Sequence
from pathlib import Path
from typing import TYPE_CHECKING, Any

from resireg.errors import ConfigError, ResiregError
from resireg_train.config.errors import config_path
from resireg_train.evaluation.specs import TaskSpec, find_task, task_names
from resireg_train.record.run_record import RunRecord

if TYPE_CHECKING:
    from torch import nn

    from resireg.models import DenseEncoder
    from resireg_train.evaluation.engine import EvalEngine, StageTimer

__all__ = [
    "NothingScoredError",
    "EvalTask",
    "elbo_counts",
    "require_scored",
    "require_task",
    "write_results",
]

log = logging.getLogger(__name__)


def require_task(name: Any, key: str = "task") -> TaskSpec:
    """The table entry of task ``name`` (:data:`resireg_train.evaluation.specs.TASK_SPECS`); an unknown
    one is a :class:`ConfigError` naming ``<key>=<name>`` and the known tasks."""
    spec = find_task(name)
    if spec is None:
        raise ConfigError(f"{key}={name!r}: expected one of {task_names()} (the tasks of "
                          "resireg_train.evaluation.specs.TASK_SPECS)")  # fmt: skip
    return spec


class EvalTask(ABC):
    """One ``resireg-eval`` task (an entry of :data:`resireg_train.evaluation.specs.TASK_SPECS` names
    its subclass). :func:`resireg_train.cli.eval.evaluate` calls, in this order:

    - :meth:`check` before the encoder loads: the sources a build would fail on;
    - :meth:`build` with the encoder: dataset and engine; returns fields recorded at once;
    - :meth:`run`: the scoring pass; returns a result with ``scores()``,
      ``per_class_iou()`` and ``images``;
    - :meth:`results`: the task's own ``results.json`` fields (:func:`write_results` adds
      the shared ones).

    Args:
        spec: the task's table entry.
        cfg: the composed ``eval.yaml`` config.
        params: the run's resolved parameters (``results.json``'s ``params``).
        out: the run's output folder (``results.json`` and any file the task writes).
    """

    def __init__(self, spec: TaskSpec, cfg: Any, params: Mapping[str, Any], out: Path) -> None:
        self.spec = spec
        self.cfg = cfg
        self.params = params
        self.out = out
        self.classes: Sequence[str] = ()  # the dataset's, set by build

    def check(self, variants: Mapping[str, nn.Module]) -> None:
        """Fail on a missing dataset folder or segmentation-prior model before the encoder
        loads (a large backbone takes minutes): the builders' own checks, run early. The base
        checks the prior of ``+prior`` configurations; a task adds its dataset's."""
        from resireg.priors import SAM_MODEL, check_sam_source
        from resireg.specs.variants import takes_prior

        if any(takes_prior(v) for v in variants):
            with config_path("prior", ("model",)):
                check_sam_source(str(self.params["prior"].get("model") or SAM_MODEL))

    @abstractmethod
    def build(self, encoder: DenseEncoder, variants: Mapping[str, nn.Module]) -> dict[str, Any]:
        """Build the dataset and the engine for ``encoder``; check the variants on its
        batches (a :class:`ConfigError` naming the configuration); returns the fields to
        record now (``protocol``)."""

    @abstractmethod
    def run(self, encoder: DenseEncoder, variants: Mapping[str, nn.Module],
            timer: StageTimer) -> Any:  # fmt: skip
        """Score every variant; ``timer`` collects seconds per stage."""

    @abstractmethod
    def results(self, result: Any) -> dict[str, Any]:
        """The task's own ``results.json`` fields of ``result`` (at least ``skipped`` and
        ``skipped_samples``); warns of skipped samples."""

    @staticmethod
    def check_batches(engine: EvalEngine, variants: Mapping[str, nn.Module]) -> None:
        """``engine.check_variants``, its error a :class:`ConfigError` (a setting the
        dataset's batches cannot take: more prototypes than points)."""
        try:
            engine.check_variants(variants)
        except ValueError as err:
            raise ConfigError(str(err)) from err


def write_results(
    record: RunRecord,
    task: EvalTask,
    result: Any,
    variants: Mapping[str, nn.Module],
    timer: StageTimer,
) -> dict[str, Any]:
    """Record a finished pass in the run's record (``results.json``): ``final`` (the scores, logged),
    ``per_class_iou`` (by class name), ``images``, the task's fields
    (:meth:`EvalTask.results`), ``elbo_prototypes`` (:func:`elbo_counts`) and ``seconds``;
    then fail if nothing was scored (:func:`require_scored`), else mark it ``completed``.
    Returns the record."""
    scores = result.scores()
    for name, value in scores.items():
        log.info("%s = %.4f", name, value)
    classes = task.classes
    fields = record.update(
        final=scores,
        per_class_iou={
            v: dict(zip(classes, ious, strict=True)) for v, ious in result.per_class_iou().items()
        },  # fmt: skip
        images=result.images,
        **task.results(result),
        **elbo_counts(variants),
        seconds={k: round(v, 4) for k, v in sorted(timer.seconds.items())},
    )
    require_scored(fields, task.spec.unit)
    return record.update(status="completed")


def elbo_counts(variants: Mapping[str, Any]) -> dict[str, Any]:
    """``{"elbo_prototypes": {configuration: {count: batches}}}`` of the ``full.n_prototypes=
    elbo`` configurations (the count each batch was given, docs/method.md#the-prototype-count-by-the-evidence-lower-bound); ``{}``
    when none ran."""
    counts = {name: dict(sorted(Counter(str(n) for n in v.chosen).items(), key=lambda c: int(c[0])))
              for name, v in variants.items() if getattr(v, "chosen", None)}  # fmt: skip
    return {"elbo_prototypes": counts} if counts else {}


class NothingScoredError(ResiregError, RuntimeError):
    """Every image (3D: frame) of the dataset was skipped: there is no score to report."""


def require_scored(record: Mapping[str, Any], unit: str) -> Mapping[str, Any]:
    """``record`` (a run's ``results.json``) if it scored at least one ``unit``; else raise
    :class:`NothingScoredError` with the skip counts: a score over nothing (mIoU NaN) is a
    failed run, never a completed one."""
    if record.get("images", 0) > 0:
        return record
    skipped, dropped = int(record.get("skipped") or 0), int(record.get("frames_dropped") or 0)
    samples = record.get("skipped_samples") or []
    counts = f"{skipped} of {skipped + dropped} {unit}s skipped (unreadable or invalid)"
    if dropped:
        counts += f", {dropped} dropped (non-finite pose)"
    first = f"; the first: {samples[0]['file']}: {samples[0]['reason']}" if samples else ""
    name = (record.get("params") or {}).get("dataset", {}).get("name")
    raise NothingScoredError(
        f"dataset={name}: no {unit} was scored: {counts}{first} (results.json's "
        "skipped_samples names each with its reason)"
    )
