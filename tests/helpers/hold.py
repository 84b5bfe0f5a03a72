"""A Lightning callback that pauses a real training job once it has started (its run folder
locked, its files written), until a file appears: tests/project/test_cli_hygiene.py's first job."""

import sys
import time
from pathlib import Path

import lightning as L


class WaitFor(L.Callback):
    def __init__(self, path: str, timeout: float = 600.0) -> None:
        self.path, self.timeout = Path(path), timeout

    def on_train_start(self, trainer, pl_module) -> None:
        print("holding", flush=True)
        sys.stderr.flush()
        deadline = time.monotonic() + self.timeout
        while not self.path.exists() and time.monotonic() < deadline:
            time.sleep(0.1)
