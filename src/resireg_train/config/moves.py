"""Class paths that changed between releases, so that a run folder written by an older version
still resumes.

A run folder keeps the config it was started with (``.hydra/config.yaml``), whose ``_target_``
entries name classes by module path. When a module moves, a resume would see a difference in
every moved ``_target_`` and refuse; :func:`current_targets` rewrites the stored paths to
today's before the comparison (``resireg_train.cli.train.check_resume``). One entry per
``_target_`` that a ``conf/`` file of an earlier release named and that has moved since (a class
moved again: point its old entries at the new path, and add the path it leaves). The module
moves behind them are listed in ``CHANGELOG.md``.
"""

from __future__ import annotations

from typing import Any

__all__ = ["MOVED_TARGETS", "current_targets"]

#: ``_target_`` in an earlier release's conf/ -> today's
MOVED_TARGETS: dict[str, str] = {
    # 0.1 -> the layout by role (resireg_train.ovss -> evaluation/ovss, tracking -> runs/)
    "resireg_train.ovss.callback.ReSiRegEval": "resireg_train.evaluation.ovss.callback.ReSiRegEval",
    "resireg_train.tracking.wandb_logger": "resireg_train.runs.loggers.wandb_logger",
    # the trackers' table (resireg_train.runs.trackers): W&B's logger factory with the others
    "resireg_train.runs.tracking.wandb_logger": "resireg_train.runs.loggers.wandb_logger",
    # the pruning glue joins the search (resireg_train.training.pruning -> sweeps/pruning)
    "resireg_train.training.pruning.OptunaPruning": "resireg_train.sweeps.pruning.OptunaPruning",
}


def current_targets(tree: Any) -> Any:
    """A copy of a config tree (dicts and lists) with every moved ``_target_`` value replaced
    by today's path (:data:`MOVED_TARGETS`); other values unchanged."""
    if isinstance(tree, dict):
        return {
            key: MOVED_TARGETS.get(value, value)
            if key == "_target_" and isinstance(value, str)
            else current_targets(value)
            for key, value in tree.items()
        }
    if isinstance(tree, list):
        return [current_targets(value) for value in tree]
    return tree
