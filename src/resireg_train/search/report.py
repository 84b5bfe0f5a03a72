"""The report of an Optuna search (``hparams_search=...``; docs/runs.md#run-records-and-faults, Optuna
searches): the trials table (each trial's state, value, last reported epoch and value as
Optuna recorded them, beside its run folder, status and error), the best trial, and Optuna's
own matplotlib plots (optimisation history, intermediate values, parameter importances),
made readable at 100+ trials (integer trial ticks, no per-trial legend, short labels)."""

from __future__ import annotations

import warnings
from pathlib import Path
from typing import TYPE_CHECKING, Any

import pandas as pd

from resireg_train.record.run_record import flat
from resireg_train.search.storage import STUDY_FILE, load_study
from resireg_train.search.trials import ATTR_STALE, stale_reason
from resireg_train.search.workers import SEARCH_FILE, study_location

if TYPE_CHECKING:  # the report package imports this module: no import back at run time
    from resireg_train.report.jobs import Job

__all__ = [
    "is_optuna_sweep",
    "optuna_study",
    "readable_axes",
    "short_param",
    "trials_table",
    "write_optuna_report",
]

OPTUNA_FILES = {
    "optuna_csv": "optuna_trials.csv",
    "optuna_history": "optuna_history.png",
    "optuna_intermediate": "optuna_intermediate.png",
    "optuna_importance": "optuna_importance.png",
}


def is_optuna_sweep(sweep_dir: str | Path) -> bool:
    """Whether the sweep folder is an Optuna search's (its journal or ``search.json``)."""
    return (Path(sweep_dir) / STUDY_FILE).is_file() or (Path(sweep_dir) / SEARCH_FILE).is_file()


def optuna_study(sweep_dir: str | Path, jobs: list[Job] | None = None) -> Any:
    """The sweep's ``optuna.Study`` (in its journal, or the database its command named)."""
    storage, name = study_location(sweep_dir)
    study = load_study(sweep_dir, storage, name)
    if study is None:
        raise ValueError(
            f"{sweep_dir} holds no Optuna study (or more than one and no {SEARCH_FILE})"
        )
    return study


def _job_of(trial: Any, jobs: list[Job]) -> Job | None:
    """A trial's run folder: the one the search recorded (``run_dir``), else the job folder
    named after its number (job number = trial number)."""
    recorded = trial.user_attrs.get("run_dir")
    for job in jobs:
        if recorded and Path(recorded).resolve() == job.path.resolve():
            return job
    named = [j for j in jobs if j.path.name.startswith(f"{trial.number}_")]
    return named[0] if len(named) == 1 else None


def trials_table(study: Any, jobs: list[Job]) -> pd.DataFrame:
    """One row per trial: number, Optuna's state and value, its last reported epoch and value
    (a pruned trial's), the parameters, its run folder, the folder's status and error."""
    rows = []
    for trial in study.get_trials(deepcopy=False):
        job = _job_of(trial, jobs)
        steps = trial.intermediate_values
        last = max(steps) if steps else None
        row: dict[str, Any] = {"trial": trial.number, "state": trial.state.name,
                               "value": trial.value, "last epoch": last,
                               "last value": steps[last] if steps else None,
                               **trial.params}  # fmt: skip
        row["run folder"] = job.path.name if job else trial.user_attrs.get("run_dir")
        row["job status"] = job.status if job else "no run folder"
        error = job.error if job and job.status not in ("completed", "pruned") else None
        if trial.system_attrs.get(ATTR_STALE):
            error = stale_reason(trial)
        elif error is None and trial.state.name == "FAIL" and job is not None:
            error = "the job completed but its optimized_metric is not finite (NaN)"
        row["error"] = flat(error) if error else None
        rows.append(row)
    return pd.DataFrame(rows)


def _save(fig: Any, path: Path) -> Path:
    import matplotlib.pyplot as plt

    fig.savefig(path, dpi=120, bbox_inches="tight")
    plt.close(fig)
    return path


def short_param(name: str) -> str:
    """A parameter's label: its last two dotted parts (``distill.scale``)."""
    return ".".join(str(name).split(".")[-2:])


def readable_axes(ax: Any, integer_x: bool = True) -> Any:
    """Integer ticks on the trial / epoch axis (at most ~12 of them), no per-trial legend."""
    from matplotlib.ticker import MaxNLocator

    if integer_x:
        ax.xaxis.set_major_locator(MaxNLocator(integer=True, nbins=12))
    legend = ax.get_legend()
    if legend is not None and len(legend.get_texts()) > 8:
        legend.remove()
    return ax.figure


def write_optuna_report(
    sweep_dir: str | Path, jobs: list[Job], out: Path
) -> tuple[dict[str, Path], list[str]]:
    """Write ``optuna_trials.csv`` and Optuna's plots (history, intermediate values when
    trials reported any, importances with two or more completed trials) into ``out``;
    returns the files and the lines of ``summary.md``'s Optuna section."""
    import matplotlib

    matplotlib.use("Agg")  # no display
    import matplotlib.pyplot as plt
    import optuna
    from optuna.visualization import matplotlib as ov

    study = optuna_study(sweep_dir, jobs)
    table = trials_table(study, jobs)
    files = {"optuna_csv": out / OPTUNA_FILES["optuna_csv"]}
    table.to_csv(files["optuna_csv"], index=False)
    states = table["state"].value_counts().to_dict() if len(table) else {}
    direction = study.direction.name.lower()
    lines = ["", f"## Optuna search: study `{study.study_name}` ({direction})", "",
             f"{len(table)} trials: " + ", ".join(f"{n} {s.lower()}" for s, n in states.items())]  # fmt: skip
    trials = study.get_trials(deepcopy=False)
    complete = [t for t in trials if t.state == optuna.trial.TrialState.COMPLETE]
    if complete:
        best = study.best_trial
        params = ", ".join(f"`{k}={v}`" for k, v in best.params.items())
        folder = table.loc[table["trial"] == best.number, "run folder"].iloc[0]
        lines += ["", f"Best trial: {best.number}, value {best.value:.4f}: {params} "
                  f"(run folder `{folder}`)"]  # fmt: skip
    # Optuna's matplotlib plots switch the process's style (plt.style.use('ggplot')): kept
    # inside this block, so the figures drawn after it keep matplotlib's defaults
    with warnings.catch_warnings(), matplotlib.rc_context():
        warnings.simplefilter("ignore", optuna.exceptions.ExperimentalWarning)
        if complete:
            ax = ov.plot_optimization_history(study)
            ax.set_title(f"Optimisation history: {study.study_name}")
            files["optuna_history"] = _save(readable_axes(ax), out / OPTUNA_FILES["optuna_history"])
        if any(t.intermediate_values for t in trials):
            ax = ov.plot_intermediate_values(study)
            ax.set_xlabel("epoch")
            path = out / OPTUNA_FILES["optuna_intermediate"]
            files["optuna_intermediate"] = _save(readable_axes(ax), path)
        if len(complete) >= 2 and complete[0].params:
            try:
                ax = ov.plot_param_importances(study)
            except (RuntimeError, ValueError) as err:  # every completed trial scored the same
                lines += ["", f"No parameter importance: {err}"]
            else:
                ax.set_yticklabels([short_param(t.get_text()) for t in ax.get_yticklabels()])
                path = out / OPTUNA_FILES["optuna_importance"]
                files["optuna_importance"] = _save(readable_axes(ax, integer_x=False), path)
    plt.close("all")
    shown = table.rename(columns={k: short_param(k) for k in trials[0].params} if trials else {})
    lines += ["", f"Trials (`{files['optuna_csv'].name}`):", "",
              shown.to_markdown(index=False, floatfmt=".4g")]  # fmt: skip
    return files, lines
