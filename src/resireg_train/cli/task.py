"""Deprecated: the Hydra job wrapper of the CLIs moved to :mod:`resireg_train.cli.job`. This module re-exports its names, with a
``DeprecationWarning``, for one release."""

from __future__ import annotations

import importlib
import warnings
from typing import Any

_NAMES = (
    "CONFIG_DIR",
    "RUN_ID",
    "LOCK_FILE",
    "JobFailed",
    "RunFolderBusy",
    "RunFolderLock",
    "SweepRecords",
    "added_keys",
    "hydra_entry_point",
    "instantiate_group",
    "hold_run_folder",
    "optimized_value",
    "process_rank",
    "register_resolvers",
    "run_task",
    "safe_dirname",
    "top_level_keys",
)


def __getattr__(name: str) -> Any:
    if name in _NAMES:
        warnings.warn(f"resireg_train.cli.task.{name} moved to resireg_train.cli.job.{name}",
                      DeprecationWarning, stacklevel=2)  # fmt: skip
        return getattr(importlib.import_module("resireg_train.cli.job"), name)
    raise AttributeError(f"module 'resireg_train.cli.task' has no attribute {name!r}")
