"""Optuna searches through Hydra (``hparams_search=...``, docs/design.md section 9, Optuna searches): where a
search keeps its study, how many trials a resumed search still runs, and the study as the
report reads it.

The study lives in SQLite inside the sweep folder (``${optuna_storage:${hydra.sweep.dir}}``),
so the same command with ``hydra.sweep.dir=<that folder>`` resumes it: the sweeper loads the
study (``load_if_exists``), and ``hydra.sweeper.n_trials`` is the search's total
(``${optuna_trials:...}``), less the trials already finished, so finished trials are neither
run again nor counted twice, and the sampler's seed moves on by as many
(``${optuna_seed:...}``) so that the resumed search does not draw their parameters again. Optuna itself loads only when a search runs or is reported.
"""

from __future__ import annotations

from pathlib import Path
from typing import Any

__all__ = [
    "STUDY_FILE",
    "finished_trials",
    "load_study",
    "register_search_resolvers",
    "remaining_trials",
    "resumed_seed",
    "storage_url",
]

#: The study's SQLite file in the sweep folder.
STUDY_FILE = "optuna.db"

_SQLITE = "sqlite:///"


def storage_url(sweep_dir: str | Path) -> str:
    """``sqlite:///<sweep_dir>/optuna.db``, creating the sweep folder (the sweeper opens the
    study before Hydra's launcher creates the folder for the first job)."""
    folder = Path(str(sweep_dir))
    folder.mkdir(parents=True, exist_ok=True)
    return f"{_SQLITE}{folder / STUDY_FILE}"


def load_study(storage: str, study_name: str) -> Any:
    """The stored ``optuna.Study``, or ``None`` if the database or the study does not exist
    (a database is never created here)."""
    if storage.startswith(_SQLITE) and not Path(storage[len(_SQLITE) :]).is_file():
        return None
    import optuna

    optuna.logging.set_verbosity(optuna.logging.WARNING)
    try:
        return optuna.load_study(study_name=study_name, storage=storage)
    except KeyError:  # no study of that name in the database
        return None


def finished_trials(study: Any) -> int:
    """Trials that ran to an end (complete, failed or pruned); a trial left ``RUNNING`` by a
    killed search is not finished and is run again as a new trial."""
    if study is None:
        return 0
    from optuna.trial import TrialState

    done = (TrialState.COMPLETE, TrialState.FAIL, TrialState.PRUNED)
    return sum(t.state in done for t in study.get_trials(deepcopy=False))


def remaining_trials(storage: str, study_name: str, total: int) -> int:
    """``total`` less the study's finished trials (``total`` for a new study), at least 0."""
    return max(0, int(total) - finished_trials(load_study(str(storage), str(study_name))))


def resumed_seed(seed: int, storage: str, study_name: str) -> int:
    """The sampler's seed: ``seed`` plus the study's finished trials. A new search is
    reproducible from ``seed``; a resumed one does not replay the random draws (TPE's startup
    trials) that gave its finished trials their parameters."""
    return int(seed) + finished_trials(load_study(str(storage), str(study_name)))


def register_search_resolvers() -> None:
    """``optuna_storage``, ``optuna_trials`` and ``optuna_seed`` for ``conf/hparams_search/``."""
    from omegaconf import OmegaConf

    if not OmegaConf.has_resolver("optuna_storage"):
        OmegaConf.register_new_resolver("optuna_storage", storage_url)
    if not OmegaConf.has_resolver("optuna_trials"):
        OmegaConf.register_new_resolver("optuna_trials", remaining_trials)
    if not OmegaConf.has_resolver("optuna_seed"):
        OmegaConf.register_new_resolver("optuna_seed", resumed_seed)
