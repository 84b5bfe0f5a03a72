"""Hydra's ``Sweeper`` interface over :func:`resireg_train.search.loop.run_search`: each trial
one job of Hydra's configured launcher (its own run folder). A door, no more: the search's
settings, checks, record, workers and loop live in :mod:`resireg_train.search`. Imports
nothing heavy at module level (Hydra imports every plugin module when it starts)."""

from __future__ import annotations

from typing import Any

from hydra.core.plugins import Plugins
from hydra.errors import CompactHydraException
from hydra.plugins.sweeper import Sweeper
from hydra.types import HydraContext, TaskFunction
from omegaconf import DictConfig, OmegaConf


class SearchRefused(CompactHydraException):
    """A search refused or stopped with a message that says everything (Hydra prints it
    without a traceback)."""


class ResiregOptunaSweeper(Sweeper):
    """``conf/hydra/sweeper/resireg_optuna.yaml``: its fields are the search's settings."""

    def __init__(self, **settings: Any) -> None:
        self.settings = OmegaConf.create(settings)
        self.config: DictConfig | None = None
        self.launcher: Any = None

    def setup(
        self, *, hydra_context: HydraContext, task_function: TaskFunction, config: DictConfig
    ) -> None:
        self.config = config
        self.launcher = Plugins.instance().instantiate_launcher(
            hydra_context=hydra_context, task_function=task_function, config=config
        )

    def sweep(self, arguments: list[str]) -> Any:
        from resireg_train.search.loop import REFUSALS, run_search

        assert self.config is not None

        def run_job(overrides: list[str], number: int) -> Any:
            return self.launcher.launch([tuple(overrides)], initial_job_idx=number)[0]

        try:
            run_search(self.config, self.settings, arguments, run_job)
        except REFUSALS as err:
            raise SearchRefused(str(err)) from None
        return None
