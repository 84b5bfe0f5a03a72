"""What a training run prints: one line per epoch, and no library noise.

``EpochLog`` writes one line per epoch (losses, learning rate, evaluation scores, skipped
examples, steps, seconds) through :mod:`logging`, so it reaches the run's ``train.log``
(Hydra's file handler) always, and the console when stdout is not a terminal (a batch
job, ``nohup``, a pipe): on a terminal the progress bar shows the same values. The progress
bar is drawn only on a terminal (:func:`on_terminal`; ``resireg-train`` leaves it out
otherwise, where its redraws would fill the log with control characters).

:func:`quiet_library_noise` silences the messages every run would print that are not the
user's business (see the README's "What a run prints").
"""

from __future__ import annotations

import logging
import math
import sys
import time
import warnings
from typing import Any

import lightning as L
from lightning.pytorch.callbacks import ModelSummary as _ModelSummary
from lightning.pytorch.callbacks import RichProgressBar
from lightning.pytorch.utilities.model_summary.model_summary import _format_summary_table

from resireg_train.record.epochs import epoch_metrics

__all__ = ["EpochLog", "ModelSummary", "ProgressBar", "bar_metrics", "epoch_line", "on_terminal",
           "quiet_library_noise"]  # fmt: skip

log = logging.getLogger(__name__)
#: Hydra's default log line format (conf/hydra keeps Hydra's job_logging).
_FORMAT = "[%(asctime)s][%(name)s][%(levelname)s] - %(message)s"
#: The epoch lines' own logger (kept off terminal handlers, see ``EpochLog``).
lines = logging.getLogger(f"{__name__}.epochs")

#: ``(message regex, why it is silenced)`` of Python warnings every run would print.
_NOISE_WARNINGS = (
    (r"Found \d+ module\(s\) in eval mode at the start of training",
     "the backbone, text tower and teacher are frozen on purpose"),
    (r"Your `IterableDataset` has `__len__` defined",
     "the caption stream shards itself per worker and rank, so its length is exact"),
    (r"`isinstance\(treespec, LeafSpec\)` is deprecated",
     "Lightning's own use of a torch API, nothing a user can change"),
    (r"It is recommended to use `self\.log\('[^']*', \.\.\., sync_dist=True\)`",
     "no metric is logged with sync_dist on purpose: every cross-rank value is reduced "
     "explicitly by all ranks at one point (docs/runs.md#run-records-and-faults), and the contrastive "
     "loss is already the global batch's on every rank"),
    (r"Checkpoint directory .* exists and is not empty",
     "a resume writes into its own run's checkpoints/ (a new run never takes a folder that "
     "holds a run: resireg_train.jobs.train.RunFolderCheck refuses it)"),
)  # fmt: skip
#: Log records (logger name, message start) silenced the same way.
_NOISE_RECORDS = (("lightning", "💡 Tip:"),)  # an advertisement for a cloud logger


class _DropRecords(logging.Filter):
    def filter(self, record: logging.LogRecord) -> bool:
        return not any(
            record.name.startswith(name) and str(record.msg).startswith(start)
            for name, start in _NOISE_RECORDS
        )


_DROP = _DropRecords()


def quiet_library_noise() -> None:
    """Silence :data:`_NOISE_WARNINGS` and :data:`_NOISE_RECORDS` in this process (idempotent;
    called by the entry points and, for spawned DDP ranks, by :class:`EpochLog`).

    Lightning's package adds its own console handler (``INFO: ...``) to the ``lightning``
    logger, whose records also reach the root logger's handlers (Hydra's console and log
    file): with root handlers configured, that handler goes, so each line is printed once
    (in Hydra's format, and kept in the run's log file)."""
    for pattern, _why in _NOISE_WARNINGS:
        warnings.filterwarnings("ignore", message=pattern)
    if logging.getLogger().handlers:
        own = logging.getLogger("lightning")
        for handler in list(own.handlers):
            if type(handler) is logging.StreamHandler and own.propagate:
                own.removeHandler(handler)
    # Lightning logs through whichever of these loggers its rank-zero helpers were bound to.
    for name in ("lightning_utilities.core.rank_zero", "lightning.pytorch.utilities.rank_zero",
                 "lightning.fabric.utilities.rank_zero", "lightning.pytorch", "lightning.fabric"):  # fmt: skip
        logger = logging.getLogger(name)
        if _DROP not in logger.filters:
            logger.addFilter(_DROP)
        for handler in logger.handlers:
            if _DROP not in handler.filters:
                handler.addFilter(_DROP)


def on_terminal() -> bool:
    """Whether this process's stdout is a terminal (where a progress bar belongs)."""
    isatty = getattr(sys.stdout, "isatty", None)
    return bool(isatty and isatty())


def _format(value: float) -> str:
    if math.isnan(value) or value == 0 or 1e-3 <= abs(value) < 1e4:
        return f"{value:.4g}"
    return f"{value:.3e}"


def epoch_line(epoch: int, max_epochs: int, metrics: dict[str, float], steps: int,
               seconds: float) -> str:  # fmt: skip
    """``epoch 1/5 | train/loss=2.83 ... | 8 steps | 3.1 s``: the epoch-level metrics sorted
    by name, training first, then evaluation (mIoU; the f-mIoU stay in ``results.json``), then
    data counts. Epochs are numbered from 0 to ``max_epochs - 1``, as Lightning's progress bar
    shows them and as the checkpoint files (``epoch001.ckpt``) and ``results.json`` (``epoch``)
    number them, so the console, the files and the record name an epoch alike."""
    order = {"train": 0, "val": 1, "data": 2}
    shown = [k for k in metrics if "/fmiou_" not in k]
    names = sorted(shown, key=lambda k: (order.get(k.split("/")[0], 3), k))
    values = " ".join(f"{k}={_format(metrics[k])}" for k in names)
    return f"epoch {epoch}/{max_epochs - 1} | {values} | {steps} steps | {seconds:.1f} s"


def bar_metrics(metrics: dict[str, float]) -> dict[str, str]:
    """What the progress bar shows: the values of :func:`epoch_line`, in its order and format
    (losses, learning rate, evaluation mIoU, skip counts), with the running step loss first."""
    order = {"train": 0, "val": 1, "data": 2}
    step = {k: metrics[k] for k in ("train/loss_step",) if k in metrics}
    shown = [k for k in metrics if "/fmiou_" not in k and not k.endswith("_step")]
    names = sorted(shown, key=lambda k: (order.get(k.split("/")[0], 3), k))
    return {k: _format(float(v)) for k, v in {**step, **{k: metrics[k] for k in names}}.items()}


class ProgressBar(RichProgressBar):
    """Lightning's rich progress bar showing what the epoch lines log (:func:`bar_metrics`):
    the running step loss, and the last finished epoch's losses, learning rate, evaluation
    mIoU and skip counts (Lightning's own bar shows only the values logged with
    ``prog_bar=True``). Drawn only on a terminal (``resireg-train`` leaves it out otherwise)."""

    def get_metrics(self, trainer: L.Trainer, pl_module: L.LightningModule) -> dict[str, Any]:
        metrics = epoch_metrics(trainer)
        step = trainer.callback_metrics.get("train/loss_step")
        if step is not None:
            metrics["train/loss_step"] = float(step)
        return bar_metrics(metrics)


class ModelSummary(_ModelSummary):
    """Lightning's model summary (through logging: the console and the run's log file) without
    the FLOPs column and ``Total Flops: 0`` line when FLOPs were not measured (they are only
    with an ``example_input_array``, which the module has not: its inputs are image-caption
    batches); a measured count is shown as Lightning shows it."""

    @staticmethod
    def summarize(summary_data: list[tuple[str, list[str]]], total_parameters: int,
                  trainable_parameters: int, model_size: float,
                  total_training_modes: dict[str, int], total_flops: int,
                  **summarize_kwargs: Any) -> None:  # fmt: skip
        if total_flops:
            _ModelSummary.summarize(summary_data, total_parameters, trainable_parameters,
                                    model_size, total_training_modes, total_flops)  # fmt: skip
            return
        columns = [c for c in summary_data if c[0] != "FLOPs"]
        table = _format_summary_table(total_parameters, trainable_parameters, model_size,
                                      total_training_modes, 0, *columns)  # fmt: skip
        head, _, last = table.rpartition("\n")
        logging.getLogger("lightning.pytorch.callbacks.model_summary").info(
            "\n" + (head if "Flops" in last else table)
        )


class _NotOnTerminal(logging.Filter):
    """Drops this module's epoch lines on a handler that writes to a terminal."""

    def filter(self, record: logging.LogRecord) -> bool:
        return record.name != lines.name


class EpochLog(L.Callback):
    """Logs :func:`epoch_line` at the end of every training epoch (rank 0), after the
    evaluation and ``ResultsTracker``: the values are those ``results.json`` records
    (epoch-level metrics; ``idle_metric_prefixes`` of other callbacks left out). Caption
    examples the data pipeline skipped are summed over workers and ranks
    (``data/skipped_*``) and, when any were, also reported as one warning per epoch.
    """

    def __init__(self) -> None:
        self._start = time.perf_counter()
        self._first_step = 0
        self._quieted: list[logging.Handler] = []
        self._added: list[logging.Handler] = []
        # The log files of this (Hydra-configured) process, for ranks spawned without logging.
        self._log_files = [
            h.baseFilename
            for h in logging.getLogger().handlers
            if isinstance(h, logging.FileHandler)
        ]

    def setup(self, trainer: L.Trainer, pl_module: L.LightningModule, stage: str) -> None:
        quiet_library_noise()
        root = logging.getLogger()
        if not root.handlers:
            # A process spawned for a DDP rank (ddp_spawn) starts with logging unconfigured:
            # log to the run's files and stdout as the launching process does.
            formatter = logging.Formatter(_FORMAT)
            handlers = [logging.FileHandler(f) for f in self._log_files]
            handlers.append(logging.StreamHandler(sys.stdout))
            for handler in handlers:
                handler.setFormatter(formatter)
                root.addHandler(handler)
            root.setLevel(logging.INFO)
            self._added = handlers
        # A handler whose stream is a terminal shows the progress bar: no epoch lines there.
        for handler in root.handlers:
            stream = getattr(handler, "stream", None)
            isatty = getattr(stream, "isatty", None)
            if isinstance(handler, logging.StreamHandler) and isatty is not None and isatty():
                handler.addFilter(_NOT_ON_TERMINAL)
                self._quieted.append(handler)

    def teardown(self, trainer: L.Trainer, pl_module: L.LightningModule, stage: str) -> None:
        for handler in self._quieted:
            handler.removeFilter(_NOT_ON_TERMINAL)
        for handler in self._added:
            logging.getLogger().removeHandler(handler)
            handler.close()
        self._quieted, self._added = [], []

    def on_train_epoch_start(self, trainer: L.Trainer, pl_module: L.LightningModule) -> None:
        self._start = time.perf_counter()
        self._first_step = trainer.global_step

    def on_train_epoch_end(self, trainer: L.Trainer, pl_module: L.LightningModule) -> None:
        if not trainer.is_global_zero:
            return
        metrics = epoch_metrics(trainer)
        steps = trainer.global_step - self._first_step
        seconds = time.perf_counter() - self._start
        lines.info(epoch_line(trainer.current_epoch, trainer.max_epochs, metrics, steps, seconds))
        skipped = {k.removeprefix("data/skipped_"): int(v) for k, v in metrics.items()
                   if k.startswith("data/skipped_") and v}  # fmt: skip
        if skipped:
            detail = ", ".join(f"{reason} {n}" for reason, n in sorted(skipped.items()))
            log.warning(
                "epoch %d: skipped %d caption examples (%s; all workers and ranks)",
                trainer.current_epoch, sum(skipped.values()), detail,
            )  # fmt: skip

    def state_dict(self) -> dict[str, Any]:
        return {}


_NOT_ON_TERMINAL = _NotOnTerminal()
