"""``resireg-runs plot`` of a search folder (an Optuna search's sweep folder): Optuna's own
optimisation history, parameter importances and parallel-coordinate plot, as PNGs
(``optuna.visualization.matplotlib``) and together as one HTML page (``optuna.visualization``,
plotly; it works offline: plotly's script is inside). Runs' curves: :mod:`resireg_train.runs.plots`.
"""

from __future__ import annotations

import warnings
from pathlib import Path

from resireg_train.runs.plots import PlotResult, axes_lines

__all__ = ["SEARCH_PLOTS", "plot_search"]


#: The search plots: Optuna's function name -> the file stem.
SEARCH_PLOTS = {
    "plot_optimization_history": "optuna_history",
    "plot_param_importances": "optuna_importance",
    "plot_parallel_coordinate": "optuna_parallel",
}


def plot_search(folder: str | Path, out: str | Path) -> PlotResult:
    """Optuna's history, parameter-importance and parallel-coordinate plots of the search in
    ``folder``: a PNG each and one HTML page (``optuna_plots.html``) in the folder ``out``.
    A plot Optuna cannot draw (importances need two completed trials that differ) is left
    out with a warning."""
    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt
    import optuna
    import optuna.visualization as ovp
    from optuna.visualization import matplotlib as ovm

    from resireg_train.search.report import optuna_study, readable_axes, short_param

    study = optuna_study(folder)
    complete = [t for t in study.get_trials(deepcopy=False)
                if t.state == optuna.trial.TrialState.COMPLETE]  # fmt: skip
    if not complete:
        raise ValueError(f"{folder}: its study {study.study_name!r} has no completed trial yet")
    out = Path(out)
    out.mkdir(parents=True, exist_ok=True)
    result, pages = PlotResult(files=[]), []
    # Optuna's matplotlib plots switch the process's style (plt.style.use('ggplot')): kept
    # inside this block, so the figures drawn after it keep matplotlib's defaults
    with warnings.catch_warnings(), matplotlib.rc_context():
        warnings.simplefilter("ignore", optuna.exceptions.ExperimentalWarning)
        for function, stem in SEARCH_PLOTS.items():
            try:
                ax = getattr(ovm, function)(study)
                figure = getattr(ovp, function)(study)
            except (RuntimeError, ValueError) as err:  # e.g. every trial scored the same
                warnings.warn(f"{stem}: {err}", stacklevel=2)
                continue
            if function == "plot_param_importances":
                ax.set_yticklabels([short_param(t.get_text()) for t in ax.get_yticklabels()])
            fig = readable_axes(ax, integer_x=function == "plot_optimization_history")
            result.curves[stem] = axes_lines(ax)
            fig.savefig(out / f"{stem}.png", dpi=110, bbox_inches="tight")
            plt.close(fig)
            result.files.append(out / f"{stem}.png")
            pages.append(figure.to_html(full_html=False, include_plotlyjs=not pages))
    if pages:
        page = out / "optuna_plots.html"
        page.write_text(f"<html><head><meta charset='utf-8'><title>{study.study_name}</title>"
                        "</head><body>" + "\n".join(pages) + "</body></html>")  # fmt: skip
        result.files.append(page)
    return result
