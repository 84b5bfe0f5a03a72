"""Callbacks that DDP tests load into real runs (``+callbacks.<name>._target_=helpers.ddp.<Class>``,
tests/ on PYTHONPATH): what each rank read, and a rank that dies."""

import json
import os
from pathlib import Path

import lightning as L
import optuna


class SeenCaptions(L.Callback):
    """Writes ``<folder>/seen-<global rank>.json``: per epoch, the captions of every sample
    this rank trained on (in order), so a test counts them across ranks."""

    def __init__(self, folder: str) -> None:
        self.folder, self.seen = Path(folder), {}

    def on_train_batch_start(self, trainer, pl_module, batch, batch_idx) -> None:
        self.seen.setdefault(str(trainer.current_epoch), []).extend(batch["caption"])

    def on_train_epoch_end(self, trainer, pl_module) -> None:
        self.folder.mkdir(parents=True, exist_ok=True)
        path = self.folder / f"seen-{trainer.global_rank}.json"
        path.write_text(json.dumps({"world_size": trainer.world_size, "seen": self.seen}))


class DieAt(L.Callback):
    """Global rank ``rank`` ends its process at once (``os._exit``, no clean-up: a crash, an
    out-of-memory kill) at training batch ``batch`` of trial ``trial`` of a search (any run
    when ``trial`` is None); ``batch=None``: when the callback is built, before the ranks meet
    (the other ranks then cannot reach their master), the rank read from ``RANK``."""

    def __init__(self, rank: int, batch: int | None = 1, trial: int | None = None,
                 number=None) -> None:  # fmt: skip
        self.rank, self.batch, self.trial, self.number = rank, batch, trial, number
        if (batch is None and int(os.environ.get("RANK", "0")) == rank
                and (trial is None or trial == number)):  # fmt: skip
            os._exit(3)

    def on_train_batch_start(self, trainer, pl_module, batch, batch_idx) -> None:
        if (trainer.global_rank == self.rank and batch_idx == self.batch
                and (self.trial is None or self.trial == self.number)):  # fmt: skip
            os._exit(3)


class PruneNumber(optuna.pruners.BasePruner):
    """Prunes trial ``number`` at its first report, and no other: a pruned trial that does
    not depend on the scores."""

    def __init__(self, number: int) -> None:
        self.number = number

    def prune(self, study, trial) -> bool:
        return trial.number == self.number
