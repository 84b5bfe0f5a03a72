"""Faults injected into real runs (loaded by the entry point from the ``callbacks`` group)."""

import os
import signal

import lightning as L


class SigintAt(L.Callback):
    """Sends this process a real SIGINT (Ctrl-C) during training epoch ``epoch`` of a run
    that was not resumed (so the printed resume command, which repeats it, runs through)."""

    def __init__(self, epoch: int, batch: int = 2) -> None:
        self.epoch, self.batch = epoch, batch

    def on_train_batch_end(self, trainer, pl_module, outputs, batch, batch_idx) -> None:
        resumed = trainer.ckpt_path is not None
        if not resumed and trainer.current_epoch == self.epoch and batch_idx == self.batch:
            os.kill(os.getpid(), signal.SIGINT)


class RaiseAt(L.Callback):
    """Raises ``RuntimeError(message)`` when training starts: a crash, not a config error."""

    def __init__(self, message: str = "injected crash") -> None:
        self.message = message

    def on_train_start(self, trainer, pl_module) -> None:
        raise RuntimeError(self.message)
