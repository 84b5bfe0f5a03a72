"""The report of an Optuna search (``hparams_search=...``; docs/design.md section 9, Optuna searches): the
trials table (each trial's state and value as Optuna recorded them, beside its job's folder,
status and error), the best trial, and the optimisation-history and parameter-importance
plots, drawn from Optuna's trials and its importance evaluator."""

from __future__ import annotations

import warnings
from pathlib import Path
from typing import Any

import pandas as pd
import yaml

from resireg_train.report.jobs import Job
from resireg_train.results import flat
from resireg_train.search import STUDY_FILE, load_study, storage_url

__all__ = ["is_optuna_sweep", "optuna_study", "trials_table", "write_optuna_report"]

OPTUNA_FILES = {
    "optuna_csv": "optuna_trials.csv",
    "optuna_history": "optuna_history.png",
    "optuna_importance": "optuna_importance.png",
}


def is_optuna_sweep(sweep_dir: str | Path) -> bool:
    """Whether the sweep folder holds an Optuna study (``optuna.db``, conf/hparams_search/)."""
    return (Path(sweep_dir) / STUDY_FILE).is_file()


def _study_name(sweep_dir: Path, jobs: list[Job], names: list[str]) -> str:
    """The study of the sweep: the database's only one, else the one its jobs' sweeper names."""
    if len(names) == 1:
        return names[0]
    for job in jobs:
        hydra_file = job.path / ".hydra" / "hydra.yaml"
        if hydra_file.is_file():
            sweeper = (yaml.safe_load(hydra_file.read_text()) or {}).get("hydra", {})
            name = (sweeper.get("sweeper") or {}).get("study_name")
            if name in names:
                return name
    raise ValueError(f"{sweep_dir / STUDY_FILE} holds studies {names}; none is named by its jobs")


def optuna_study(sweep_dir: str | Path, jobs: list[Job]) -> Any:
    """The sweep's ``optuna.Study``."""
    import optuna

    storage = storage_url(sweep_dir)
    # get_all_study_summaries: in optuna 2.10 (hydra-optuna-sweeper's pin) and 3.x alike
    names = [s.study_name for s in optuna.get_all_study_summaries(storage)]
    return load_study(storage, _study_name(Path(sweep_dir), jobs, names))


def _match_jobs(trials: list[Any], jobs: list[Job]) -> dict[int, Job]:
    """``{trial number: job}``: a trial's job is the one whose overrides hold every parameter
    the sweeper passed it (``name=value`` as it formats them, ``str(value)``), in the order
    the jobs started (a resumed search's job numbers start again from 0). A trial without a
    job was asked but not run (its search was stopped)."""
    order = sorted(jobs, key=lambda j: (j.path / ".hydra").stat().st_mtime)
    taken: set[Path] = set()
    matched = {}
    for trial in sorted(trials, key=lambda t: t.number):
        wanted = {k: str(v) for k, v in trial.params.items()}
        for job in order:
            if job.path not in taken and all(job.overrides.get(k) == v for k, v in wanted.items()):
                matched[trial.number] = job
                taken.add(job.path)
                break
    return matched


def trials_table(study: Any, jobs: list[Job]) -> pd.DataFrame:
    """One row per trial: number, Optuna's state and value, the parameters, its job's folder,
    status and error (why it failed; Optuna marks a NaN-scored trial failed too)."""
    trials = study.get_trials(deepcopy=False)
    matched = _match_jobs(trials, jobs)
    rows = []
    for trial in trials:
        job = matched.get(trial.number)
        row: dict[str, Any] = {"trial": trial.number, "state": trial.state.name,
                               "value": trial.value, **trial.params}  # fmt: skip
        row["job"] = job.path.name if job else None
        row["job status"] = job.status if job else "not run"
        error = job.error if job and job.status != "completed" else None
        if error is None and trial.state.name == "FAIL" and job is not None:
            error = "the job completed but its optimized_metric is not finite (NaN)"
        row["error"] = flat(error) if error else None
        rows.append(row)
    return pd.DataFrame(rows)


def _save(fig: Any, path: Path) -> Path:
    import matplotlib.pyplot as plt

    fig.savefig(path, dpi=120, bbox_inches="tight")
    plt.close(fig)
    return path


# The two figures are drawn here from Optuna's own data (its trials, its importance evaluator)
# rather than by optuna.visualization.matplotlib: the sweeper pins optuna < 3, and optuna 2.10's
# plotting calls matplotlib.cm.get_cmap, removed in matplotlib 3.9.
def _history_figure(study: Any, complete: list[Any]) -> Any:
    """Objective value per trial number and the best so far (Optuna's optimisation history)."""
    import matplotlib.pyplot as plt
    import numpy as np

    numbers = np.array([t.number for t in complete])
    values = np.array([t.value for t in complete], dtype=float)
    order = np.argsort(numbers)
    best = (np.maximum if study.direction.name == "MAXIMIZE" else np.minimum).accumulate(
        values[order]
    )
    fig, ax = plt.subplots(figsize=(8, 5))
    ax.scatter(numbers, values, label="objective value", zorder=3)
    ax.step(numbers[order], best, where="post", color="tab:red", label="best value")
    ax.set(
        xlabel="trial", ylabel="objective value", title=f"Optimisation history: {study.study_name}"
    )
    ax.legend()
    return fig


def _importance_figure(importances: dict[str, float]) -> Any:
    """Horizontal bars of the parameters' importances (Optuna's importance plot)."""
    import matplotlib.pyplot as plt

    names = sorted(importances, key=importances.get)
    fig, ax = plt.subplots(figsize=(8, 5))
    ax.barh(names, [importances[n] for n in names])
    ax.set(xlabel="importance (mean decrease in impurity)", title="Parameter importances")
    return fig


def write_optuna_report(
    sweep_dir: str | Path, jobs: list[Job], out: Path
) -> tuple[dict[str, Path], list[str]]:
    """Write ``optuna_trials.csv``, ``optuna_history.png`` and (with two or more completed
    trials) ``optuna_importance.png`` into ``out``; returns the files and the lines of
    ``summary.md``'s Optuna section."""
    import matplotlib

    matplotlib.use("Agg")  # no display
    import optuna

    # Mean decrease in impurity (scikit-learn's forest): optuna 2.10's own fANOVA tree (the
    # sweeper's pin) cannot read scikit-learn >= 1.4's tree values; this one reads both.
    from optuna.importance import MeanDecreaseImpurityImportanceEvaluator, get_param_importances

    study = optuna_study(sweep_dir, jobs)
    table = trials_table(study, jobs)
    files = {"optuna_csv": out / OPTUNA_FILES["optuna_csv"]}
    table.to_csv(files["optuna_csv"], index=False)
    states = table["state"].value_counts().to_dict()
    direction = study.direction.name.lower()
    lines = ["", f"## Optuna search: study `{study.study_name}` ({direction})", "",
             f"{len(table)} trials: " + ", ".join(f"{n} {s.lower()}" for s, n in states.items())]  # fmt: skip
    complete = [t for t in study.get_trials(deepcopy=False)
                if t.state == optuna.trial.TrialState.COMPLETE]  # fmt: skip
    if complete:
        best = study.best_trial
        params = ", ".join(f"`{k}={v}`" for k, v in best.params.items())
        lines += ["", f"Best trial: {best.number}, value {best.value:.4f}: {params}"]
    with warnings.catch_warnings():
        warnings.simplefilter("ignore", optuna.exceptions.ExperimentalWarning)
        if complete:
            files["optuna_history"] = _save(
                _history_figure(study, complete), out / OPTUNA_FILES["optuna_history"]
            )
        if len(complete) >= 2 and len(complete[0].params) >= 1:
            evaluator = MeanDecreaseImpurityImportanceEvaluator(seed=0)
            try:
                importances = get_param_importances(study, evaluator=evaluator)
            except RuntimeError as err:  # every completed trial scored the same
                lines += ["", f"No parameter importance: {err}"]
            else:
                files["optuna_importance"] = _save(
                    _importance_figure(importances), out / OPTUNA_FILES["optuna_importance"]
                )
    lines += ["", f"Trials (`{files['optuna_csv'].name}`):", "",
              table.to_markdown(index=False, floatfmt=".4f")]  # fmt: skip
    return files, lines
