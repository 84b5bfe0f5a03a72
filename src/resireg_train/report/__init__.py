"""Sweep reports (``resireg-report SWEEP_DIR``): one table (and plots) from a Hydra multirun folder.

Reads every job folder of the sweep (``<n>_<overrides>/``): its overrides
(``.hydra/overrides.yaml``) and ``results.json``. A job that failed, was interrupted
(Ctrl-C; resumable), is still running or never wrote ``results.json`` stays in the table
with its status and error. Which sections beyond the summary it writes, the sweep config names
(``report: [table1]`` etc. in ``conf/sweep/``, saved in every job's ``.hydra/config.yaml``); an
ad hoc ``-m`` sweep, which names none, gets those its jobs show (:func:`report_sections`). The
sections are the entries of one table, :data:`resireg_train.report.specs.SECTION_SPECS`
(its docstring: adding a section). Writes, into the sweep folder (or ``--out``):

- ``summary.csv`` and ``summary.md``: one row per job; the overrides that vary across
  jobs, status, the scores (final values; for training runs also the best of the chosen
  metric) and the error.
- For the prototype/batch ablation (jobs varying ``batch_size`` and ``full.n_prototypes``,
  2D or 3D: the metric is whichever ``.../miou_full`` the jobs recorded, ``val/ovss/...`` or
  ``val/scannet3d/...``): ``heatmap.png`` (batch size x prototype count, mIoU of ReSiReg Full) and
  ``prototype_heuristic.json``: ``n(B)`` fitted to the best prototype count of every
  batch size, loadable by ``ReSiRegFull(n_prototypes="auto", heuristic=PATH)``.
- For encoder sweeps (the encoder varies, or ``sweep=table1`` / ``table2`` cut to one
  encoder): ``table1.md`` / ``.csv`` (2D OVSS, the paper's Table 1) or, for
  ``task=scannet3d`` jobs, ``table2.md`` / ``.csv`` (3D mapping, the paper's Table 2).
- For training sweeps (jobs with a per-epoch history): ``curves.png``, the chosen metric
  per epoch for every run.
- For an Optuna search (``hparams_search=...``: ``optuna.journal`` or ``search.json``):
  ``optuna_trials.csv`` (every trial's state, value, parameters, job and error), the best
  trial in ``summary.md``, and ``optuna_history.png`` / ``optuna_intermediate.png`` / ``optuna_importance.png``.
- For the CLIP layer sweep (configurations ``<variant>@layer:<block>``, ``sweep=clip_layers``):
  ``layer_sweep.csv`` / ``.md`` / ``.png``, mIoU of each variant against the block index.
- For the OVSS field's eight benchmarks (``sweep=ovss8``): ``ovss8.csv`` / ``.md``, encoder x
  variant against VOC21 ... ADE and their average, beside the published peers
  (:mod:`resireg_train.report.ovss8`).

An explicit metric must be one the sweep's results hold (a ``final`` or ``best`` key of
some job); anything else is a :class:`ValueError` that lists them.

The package: :mod:`~resireg_train.report.writer` (:func:`report`), :mod:`.specs` (the
section table), :mod:`.jobs` (a sweep's job folders), :mod:`.summary`, :mod:`.tables` (Tables 1
and 2, the layer sweep, the Markdown renderer), :mod:`.prototype_batch` (the batch x prototype
grid, the heuristic), :mod:`.figures`, :mod:`.paper` (the published figures beside ours),
:mod:`.ovss8` (the eight OVSS benchmarks beside the published peers).
Imported by the CLIs (``resireg-report``) and by ``resireg_train.search`` (its search report
reads the jobs); it imports ``resireg_train.evaluation``'s torch-free task table and protocol
record, ``runs`` and ``config``. The names below load on first use (PEP 562), so reading the
section table (the config check) loads neither pandas nor matplotlib.
"""

from __future__ import annotations

from resireg import lazy_names

_NAMES = {
    **dict.fromkeys(("DPI", "curves_figure", "heatmap_figure", "layer_sweep_figure",
                     "plot_curves", "plot_heatmap"), "resireg_train.report.figures"),
    **dict.fromkeys(("STATUSES", "Job", "check_metric", "collect", "count_statuses",
                     "default_metric", "known_metrics", "named_sections", "varying_keys"),
                    "resireg_train.report.jobs"),
    "DEFAULT_TOLERANCE": "resireg_train.report.paper",
    **dict.fromkeys(("is_ovss8_sweep", "ovss8_table", "write_ovss8_table"),
                    "resireg_train.report.ovss8"),
    **dict.fromkeys(("elbo_table", "fit_heuristic", "grid_statuses", "is_prototype_sweep",
                     "prototype_grid"), "resireg_train.report.prototype_batch"),
    "summary_table": "resireg_train.report.summary",
    **dict.fromkeys(("LAYER_SWEEP_FILES", "encoder_table", "is_encoder_sweep", "is_layer_sweep",
                     "is_mapping_sweep", "layer_sweep_table", "mapping_table", "markdown",
                     "method_means", "protocol_lines", "write_encoder_table",
                     "write_layer_sweep", "write_mapping_table"), "resireg_train.report.tables"),
    **dict.fromkeys(("report", "report_sections"), "resireg_train.report.writer"),
}  # fmt: skip
__all__ = sorted(_NAMES)
__getattr__ = lazy_names("resireg_train.report", _NAMES)
