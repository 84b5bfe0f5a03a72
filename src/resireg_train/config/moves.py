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

import yaml

from resireg_train.config.paths import CONFIG_DIR

__all__ = ["MOVED_TARGETS", "current_keys", "current_targets"]

#: ``_target_`` in an earlier release's conf/ -> today's
MOVED_TARGETS: dict[str, str] = {
    # 0.1 -> the layout by role (resireg_train.ovss -> evaluation/ovss, tracking -> runs/)
    "resireg_train.ovss.callback.ReSiRegEval": "resireg_train.evaluation.ovss.callback.ReSiRegEval",
    "resireg_train.tracking.wandb_logger": "resireg_train.record.trackers.wandb.wandb_logger",
    # the trackers' table (resireg_train.runs.trackers): W&B's logger factory with the others
    "resireg_train.runs.tracking.wandb_logger": "resireg_train.record.trackers.wandb.wandb_logger",
    # the pruning glue joins the search (resireg_train.training.pruning -> sweeps/pruning)
    "resireg_train.training.pruning.OptunaPruning": "resireg_train.search.pruning.OptunaPruning",
    # the run record apart from the run tools, sweeps/ -> search/ (issue 52: record/trackers/
    # holds one module per tracker; "sweep" is a Hydra multirun, the Optuna search is search/)
    "resireg_train.runs.loggers.wandb_logger": "resireg_train.record.trackers.wandb.wandb_logger",
    "resireg_train.sweeps.pruning.OptunaPruning": "resireg_train.search.pruning.OptunaPruning",
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


#: the config group whose keys an evaluation dataset entry written before the OVSS protocols
#: (0.1) leaves out: such an entry ran the paper's 2D protocol, which that file spells out
PROTOCOL_BEFORE_KEYS = "protocol/paper.yaml"


def current_keys(tree: Any) -> Any:
    """A copy of a config tree in which every evaluation dataset entry (a mapping with a
    ``kind`` under a ``datasets`` key) that lacks a protocol key gets the value the release
    that wrote it ran with (:data:`PROTOCOL_BEFORE_KEYS`, read from ``conf/``), so a run
    written before the keys were spelled out compares equal to today's composition of the
    same command. Keys present are kept as they are."""
    before = yaml.safe_load((CONFIG_DIR / PROTOCOL_BEFORE_KEYS).read_text())

    def walk(node: Any, under_datasets: bool = False) -> Any:
        if isinstance(node, list):
            return [walk(value) for value in node]
        if not isinstance(node, dict):
            return node
        if under_datasets:
            return {
                key: {**before, **walk(entry)}
                if isinstance(entry, dict) and "kind" in entry
                else walk(entry)
                for key, entry in node.items()
            }
        return {key: walk(value, key == "datasets") for key, value in node.items()}

    return walk(tree)
