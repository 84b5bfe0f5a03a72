"""``resireg-report``'s sections by name: one entry each, the only list of them
(docs/architecture.md#adding-a-report-section).

Beyond the summary (``summary.csv`` / ``.md``, every report), a sweep's report writes the
sections its sweep config names (``report: [table1]`` in ``conf/sweep/table1.yaml``, saved in
every job's ``.hydra/config.yaml``); an ad hoc ``-m`` sweep, which names none, gets those whose
``detect`` finds them in its jobs; an ``always`` section is written whenever its ``detect``
finds it, named or not (the training curves, an Optuna search's trials). The writer
(:func:`resireg_train.report.writer.report`) goes through the entries in table order.

Torch- and pandas-free, like the other tables: the config check
(:func:`resireg_train.checks.eval.validate_eval`, ``report: [...]``) reads the names before
anything heavy loads; an entry names its code lazily (``"module:function"``).

Adding a report section:

1. a writer, a function that takes any of ``jobs`` (the sweep's
   :class:`~resireg_train.report.jobs.Job` list), ``out`` (the folder to write into),
   ``sweep_dir``, ``metric`` and ``paper_tolerance`` by name, writes its files and returns
   ``(files, lines)``: ``{key: path}`` of what it wrote and the lines it adds to
   ``summary.md``; and, unless the section is only ever chosen by name, a detector taking the
   same names and returning whether the jobs show it;
2. a :class:`SectionSpec` below;
3. the sweep config that asks for it: ``report: [<name>]`` in ``conf/sweep/<sweep>.yaml``.

``tests/resireg_train/report/test_report.py`` checks every entry (its writer and detector load and take only those
names; every ``report:`` of ``conf/sweep/`` names entries).
"""

from __future__ import annotations

from dataclasses import dataclass
from typing import Any

from resireg.specs.table import SpecTable

__all__ = ["ENCODER_SWEEPS", "SECTION_SPECS", "SECTION_INPUTS", "SectionSpec", "section_names"]

#: What a section's writer and detector may take, by name (:func:`resireg_train.report.writer.
#: report` passes the ones their signature names).
SECTION_INPUTS = ("jobs", "out", "sweep_dir", "metric", "paper_tolerance")


@dataclass(frozen=True)
class SectionSpec:
    """One section of a sweep's report.

    Attributes:
        name: what ``report: [...]`` calls it.
        target: its writer, ``"module:function"`` (module docstring).
        summary: one line: what it writes.
        detect: ``"module:function"``, whether a sweep's jobs show the section (an ad hoc
            sweep's report writes those found); ``None``: only written when named.
        always: written whenever ``detect`` finds it, whether the sweep names it or not (and
            not itself a name for ``report: [...]``).
        encoders: an encoder table: the sweep of the same name (``conf/sweep/table1.yaml``)
            runs every encoder of the encoder table (:data:`ENCODER_SWEEPS`).
    """

    name: str
    target: str
    summary: str
    detect: str | None = None
    always: bool = False
    encoders: bool = False

    def load(self) -> Any:
        """The writer (imports pandas, matplotlib and what it reads)."""
        from resireg.specs.table import load

        return load(self.target)

    def detector(self) -> Any:
        """The detector, or ``None``."""
        from resireg.specs.table import load

        return load(self.detect) if self.detect else None


_TABLES = "resireg_train.report.tables"

#: The sections, in the order the report writes them (``summary.md`` follows it).
SECTION_SPECS: SpecTable[SectionSpec] = SpecTable(
    "report section",
    (
        SectionSpec(
            "table1", f"{_TABLES}:table1_section",
            "the paper's Table 1 (2D OVSS, encoder x dataset): table1.csv / .md",
            detect=f"{_TABLES}:is_table1", encoders=True,
        ),
        SectionSpec(
            "table2", f"{_TABLES}:table2_section",
            "the paper's Table 2 (3D mapping, encoder x variant): table2.csv / .md",
            detect=f"{_TABLES}:is_table2", encoders=True,
        ),
        SectionSpec(
            "table3d", "resireg_train.report.mapping3d:table3d_section",
            "3D mapping on Replica / TartanAir (encoder x variant) beside RayFronts' published "
            "figures (conf/paper/rayfronts3d.yaml): table3d.csv / .md",
            detect="resireg_train.report.mapping3d:is_table3d",
        ),
        SectionSpec(
            "prototype_grid", "resireg_train.report.prototype_batch:prototype_grid_section",
            "batch size x prototype count of ReSiReg Full (heatmap.png) and the fitted "
            "prototype heuristic (prototype_heuristic.json)",
            detect="resireg_train.report.prototype_batch:is_prototype_sweep",
        ),
        SectionSpec(
            "curves", "resireg_train.report.figures:curves_section",
            "the chosen metric per epoch of every training run (curves.png)",
            detect="resireg_train.report.figures:has_history", always=True,
        ),
        SectionSpec(
            "layer_sweep", f"{_TABLES}:layer_sweep_section",
            "mIoU against the intermediate block (layer_sweep.csv / .md / .png)",
            detect=f"{_TABLES}:is_layer_sweep",
        ),
        SectionSpec(
            "ovss8", "resireg_train.report.ovss8:ovss8_section",
            "the OVSS field's eight benchmarks (encoder x variant) beside the published peers: "
            "ovss8.csv / .md",
            detect="resireg_train.report.ovss8:is_ovss8_sweep",
        ),
        SectionSpec(
            "optuna", "resireg_train.search.report:write_optuna_report",
            "an Optuna search's trials (optuna_trials.csv), best trial and plots",
            detect="resireg_train.search.report:is_optuna_sweep", always=True,
        ),
    ),
    where="resireg_train.report.specs",
)  # fmt: skip


def section_names() -> tuple[str, ...]:
    """The names a sweep config may list in ``report: [...]`` (the sections not ``always``)."""
    return tuple(name for name, spec in SECTION_SPECS.items() if not spec.always)


#: The sweeps (``conf/sweep/``, also their run ``name``) over every encoder: those named after
#: an encoder table section (their report is that table).
ENCODER_SWEEPS: tuple[str, ...] = tuple(n for n, s in SECTION_SPECS.items() if s.encoders)
