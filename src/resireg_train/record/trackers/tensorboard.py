"""The ``tensorboard`` tracker: training's curves (Lightning's ``TensorBoardLogger``); an
evaluation or a map writes its final metrics as scalars and its provenance as text under
``<run>/tensorboard``.
"""

from __future__ import annotations

import json
from typing import Any

from resireg_train.record.trackers.base import Tracker, run_metrics

__all__ = ["TensorBoardTracker"]


class TensorBoardTracker(Tracker):
    """``<run>/tensorboard`` (module docstring)."""

    def end(self, record: dict[str, Any], failed: bool) -> None:
        if self.training:
            return  # Lightning's TensorBoardLogger wrote the curves
        from torch.utils.tensorboard import SummaryWriter

        with SummaryWriter(str(self.record.folder / "tensorboard")) as writer:
            for key, value in run_metrics(record).items():
                writer.add_scalar(key, value, 0)
            writer.add_text("provenance", "```\n" + json.dumps(record.get("provenance") or {},
                                                               indent=2) + "\n```")  # fmt: skip
