"""Hydra's ``Sweeper`` interface over :class:`resireg_train.sweeps.search.OptunaSearch`: ask-and-tell
on an Optuna study, each trial one job of Hydra's configured launcher (its own run folder).
Imports nothing heavy at module level (Hydra imports every plugin module when it starts)."""

from __future__ import annotations

import logging
import os
from pathlib import Path
from typing import Any

from hydra.core.plugins import Plugins
from hydra.errors import CompactHydraException
from hydra.plugins.sweeper import Sweeper
from hydra.types import HydraContext, TaskFunction
from omegaconf import DictConfig, OmegaConf

log = logging.getLogger(__name__)


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
        import sys

        from hydra.core.override_parser.overrides_parser import OverridesParser

        from resireg.errors import ConfigError
        from resireg_train.sweeps import search

        assert self.config is not None
        sweep_dir = Path(str(self.config.hydra.sweep.dir)).resolve()
        sweep_dir.mkdir(parents=True, exist_ok=True)
        fixed, params = [], dict(self.settings.get("params") or {})
        for override in OverridesParser.create().parse_overrides(arguments):
            if override.is_sweep_override():  # a search axis given on the command line
                params[override.key_or_group] = override.input_line.split("=", 1)[1]
            else:  # a fixed value; one for a search axis takes it out of the search
                fixed.append(override.input_line)
                params.pop(override.key_or_group, None)
        try:
            for key in ("workers", "n_trials"):
                value = self.settings.get(key)
                if not isinstance(value, int) or value < (1 if key == "workers" else 0):
                    raise ConfigError(f"hparams_search.{key}={value!r}: expected an integer >= "
                                      f"{1 if key == 'workers' else 0}")  # fmt: skip
            space = search.distributions(params)
            search.check_metric(self.config)  # before the first trial
        except ConfigError as err:
            raise SearchRefused(f"refused before the first trial: {err}") from None
        worker = os.environ.get(search.WORKER_ENV) == "1"
        procs = []
        if not worker:
            search.save_command(sweep_dir, sys.argv, self.settings.get("storage"),
                                str(self.settings.study_name))  # fmt: skip
            procs = search.start_workers(sweep_dir, int(self.settings.workers) - 1)

        def run_job(overrides: list[str], number: int) -> Any:
            return self.launcher.launch([tuple(overrides)], initial_job_idx=number)[0]

        try:
            ran = search.OptunaSearch(self.config, sweep_dir, self.settings).run(
                fixed, space, run_job
            )
        except BaseException as err:
            for proc in procs:
                proc.terminate()
            if isinstance(err, (ConfigError, search.SearchError)):
                raise SearchRefused(str(err)) from None
            raise
        codes = [proc.wait() for proc in procs]
        log.info("this worker ran %d trials; %d other workers ended with %s", ran, len(procs),
                 codes)  # fmt: skip
        if any(codes):
            raise RuntimeError(f"a worker of the search in {sweep_dir} failed (exit codes {codes})")
        return None
