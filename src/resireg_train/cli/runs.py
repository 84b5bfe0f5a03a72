"""``resireg-runs``: list, filter, show, compare and trace the runs under some folders.

    resireg-runs ls [ROOT ...] [--where KEY=VALUE ...] [--sort=[-]KEY] [--columns a,b]
                    [--format table|csv|json]
    resireg-runs show RUN [--root ROOT ...]
    resireg-runs diff RUN_A RUN_B [--root ROOT ...]
    resireg-runs lineage RUN_OR_EXPORT [--root ROOT ...]
    resireg-runs card EXPORT [--add EVAL_RUN ...]
    resireg-runs register EXPORT --name NAME [--alias ALIAS] [--tracking-uri URI]
    resireg-runs plot RUN... --metric NAME [--metric ...] [--out PNG] [--html PAGE]
    resireg-runs plot SEARCH_FOLDER [--out FOLDER]
    resireg-runs gc FOLDER... --keep N --by METRIC [--mode min|max] [--dry-run]
    resireg-runs rerun RUN [--out DIR] [--allow-drift] [--rtol X] [--root ROOT] [OVERRIDE ...]
    resireg-runs reproduce table1/<encoder> [--paper FILE] [--out DIR] [OVERRIDE ...]

RUN is a run folder or a run id (a unique prefix of ``results.json``'s
``provenance.run_id``). ROOT defaults to ``outputs`` (``paths.log_dir``'s default).
Filters: ``--where status=completed``, ``--where "val/ovss/ade20k/miou_full>0.25"``,
``--where model.optimizer.lr<=1e-3`` (metrics, config keys, ``provenance.*`` paths).

A folder whose ``results.json`` is not a run record (another tool's file, a JSON list,
damaged) or whose ``.hydra/overrides.yaml`` cannot be read is named once on stderr; the other
runs are listed. A bad option or filter exits with status 2 and one line.
"""

from __future__ import annotations

import argparse
import csv
import json
import sys
from pathlib import Path
from typing import Any

__all__ = ["main"]

DEFAULT_ROOT = "outputs"


def _cell(value: Any) -> str:
    if value is None:
        return ""
    if isinstance(value, float):
        return f"{value:.4g}"
    return str(value)


def _print_rows(rows: list[dict[str, Any]], columns: list[str], fmt: str) -> None:
    if fmt == "json":
        json.dump(rows, sys.stdout, indent=2, default=str)
        sys.stdout.write("\n")
    elif fmt == "csv":
        writer = csv.DictWriter(sys.stdout, fieldnames=columns)
        writer.writeheader()
        writer.writerows({k: _cell(v) for k, v in row.items()} for row in rows)
    else:
        from tabulate import tabulate

        print(tabulate([[_cell(r[c]) for c in columns] for r in rows], headers=columns,
                       disable_numparse=True))  # fmt: skip


def _pairs(rows: list[tuple[str, Any, Any]], a: str, b: str) -> str:
    from tabulate import tabulate

    if not rows:
        return "  (no difference)"
    return tabulate([[k, _cell(x), _cell(y)] for k, x, y in rows], headers=["key", a, b],
                    disable_numparse=True)  # fmt: skip


class _Parser(argparse.ArgumentParser):
    """argparse with a usage error on one line (``resireg-runs: error: ...``), exit status 2."""

    def error(self, message: str) -> None:  # type: ignore[override]
        self.exit(2, f"resireg-runs: error: {message} (resireg-runs --help)\n")


def _say(lines: list[str], said: set[str], prefix: str = "") -> None:
    """Each line on stderr once, URL passwords masked."""
    from resireg.secrets import mask_text

    for line in lines:
        if line not in said:
            said.add(line)
            sys.stderr.write(f"resireg-runs: {prefix}{mask_text(line)}\n")


def main(argv: list[str] | None = None) -> None:
    parser = _Parser(prog="resireg-runs", description=__doc__.split("\n\n")[0],
                     formatter_class=argparse.RawDescriptionHelpFormatter)  # fmt: skip
    sub = parser.add_subparsers(dest="command", required=True)
    ls = sub.add_parser("ls", help="one row per run under the roots")
    ls.add_argument("roots", nargs="*", default=[DEFAULT_ROOT], metavar="ROOT")
    ls.add_argument("--where", action="append", default=[], metavar="KEY[OP]VALUE",
                    help="keep runs whose KEY (metric, config key, provenance.*, status, cli, "
                    "name) compares so: =, !=, >, <, >=, <= (repeatable)")  # fmt: skip
    ls.add_argument("--sort", metavar="[-]KEY", help="sort by KEY (--sort=-KEY: descending); "
                    "default: start time")  # fmt: skip
    ls.add_argument("--columns", metavar="A,B,...", help="the columns (default: "
                    "run_id,cli,name,status,start,duration,overrides,metric,value)")  # fmt: skip
    ls.add_argument("--format", choices=("table", "csv", "json"), default="table")
    for name, helptext in (("show", "one run: provenance, overrides, metrics"),
                           ("lineage", "data -> training runs -> export -> evaluations")):  # fmt: skip
        one = sub.add_parser(name, help=helptext)
        one.add_argument("run", metavar="RUN" if name == "show" else "RUN_OR_EXPORT")
        one.add_argument("--root", action="append", metavar="ROOT")
    card = sub.add_parser("card", help="an export's model card (README.md); --add: an "
                          "evaluation's results into it")  # fmt: skip
    card.add_argument("export", metavar="EXPORT")
    card.add_argument(
        "--add",
        action="append",
        default=[],
        metavar="EVAL_RUN",
        help="a resireg-eval run folder of this export (repeatable)",
    )
    two = sub.add_parser("diff", help="config, provenance and metric differences of two runs")
    two.add_argument("a", metavar="RUN_A")
    two.add_argument("b", metavar="RUN_B")
    two.add_argument("--root", action="append", metavar="ROOT")
    # register, plot, gc: their logic in resireg_train.runs.registry, .plots (a search's:
    # resireg_train.runs.search_plots), .gc
    reg = sub.add_parser("register", help="an export into MLflow's model registry "
                         "(model_path=models:/NAME@ALIAS loads it)")  # fmt: skip
    reg.add_argument("export", metavar="EXPORT")
    reg.add_argument("--name", required=True, help="the registered model's name")
    reg.add_argument("--alias", help="point this alias at the new version (e.g. champion)")
    reg.add_argument("--tracking-uri", help="the MLflow server or store (default: "
                     "MLFLOW_TRACKING_URI, else MLflow's sqlite:///mlflow.db)")  # fmt: skip
    reg.add_argument("--experiment", default="resireg", help="the registration run's experiment")
    plot = sub.add_parser("plot", help="curves of runs in one PNG; a search folder: Optuna's "
                          "plots")  # fmt: skip
    plot.add_argument("runs", nargs="+", metavar="RUN", help="run folders, run ids or folders "
                      "holding runs (a sweep), or one search folder")  # fmt: skip
    plot.add_argument("--metric", action="append", default=[], metavar="NAME", help="a metric "
                      "(or a pattern: 'val/ovss/*/miou_full'), one panel each (repeatable)")  # fmt: skip
    plot.add_argument("--out", help="the PNG (default runs.png); a search: the folder "
                      "(default <search>/plots)")  # fmt: skip
    plot.add_argument("--html", metavar="PATH", help="also an interactive plotly page")
    plot.add_argument("--root", action="append", metavar="ROOT")
    gc = sub.add_parser("gc", help="remove the checkpoints of runs outside the best N")
    gc.add_argument("folders", nargs="+", metavar="FOLDER", help="sweep folders (ranked together)")
    gc.add_argument("--keep", type=int, required=True, metavar="N")
    gc.add_argument("--by", required=True, metavar="METRIC")
    gc.add_argument("--mode", choices=("min", "max"), help="default: min for losses, max for "
                    "scores")  # fmt: skip
    gc.add_argument("--dry-run", action="store_true", help="list, remove nothing")
    again = sub.add_parser("rerun", help="a run again from its record, in a new folder, and "
                           "one verdict: identical, within tolerance or differs")  # fmt: skip
    again.add_argument("run", metavar="RUN")
    again.add_argument("overrides", nargs="*", metavar="OVERRIDE",
                       help="key=value: replaces the run's own override of that key")  # fmt: skip
    again.add_argument("--out", metavar="DIR", help="the new run's folder (default: "
                       "outputs/rerun/<run id>_<time>)")  # fmt: skip
    again.add_argument("--allow-drift", action="store_true", help="run even though the code, "
                       "data, models or config differ from the run's (recorded in the new run)")  # fmt: skip
    again.add_argument("--rtol", type=float, metavar="X", help="relative tolerance of 'within "
                       "tolerance' (default: provenance.rerun_rtol)")  # fmt: skip
    again.add_argument("--root", action="append", metavar="ROOT")
    paper = sub.add_parser("reproduce", help="the jobs behind one row of the paper's Table 1 "
                           "or 2, your figures beside the paper's")  # fmt: skip
    paper.add_argument("row", metavar="TABLE/ROW", help="e.g. table1/radseg, table2/otas")
    paper.add_argument("overrides", nargs="*", metavar="OVERRIDE",
                       help="key=value for every job (model_path=..., paths.data_dir=...)")  # fmt: skip
    paper.add_argument("--paper", metavar="FILE", help="the paper's figures (default: "
                       "conf/paper/results.yaml)")  # fmt: skip
    paper.add_argument("--out", metavar="DIR", help="the jobs' sweep folder (default: "
                       "outputs/reproduce/<table>_<row>/<time>)")  # fmt: skip
    # (overrides may follow the options: argparse leaves those after an option unparsed)
    args, extra = parser.parse_known_args(argv)
    if extra and (args.command not in ("rerun", "reproduce") or any(e[:1] == "-" for e in extra)):
        parser.error(f"unrecognized arguments: {' '.join(extra)}")
    if args.command in ("rerun", "reproduce"):  # their own modules (runs/rerun/, runs/reproduce.py)
        from resireg_train.runs import reproduce
        from resireg_train.runs.rerun import command as rerun

        args.overrides += extra
        args.root = getattr(args, "root", None) or [DEFAULT_ROOT]
        from resireg.errors import ResiregError

        try:
            code = (rerun.main if args.command == "rerun" else reproduce.main)(args)
        except (ValueError, ResiregError) as err:  # refused before any job started
            parser.exit(2, f"resireg-runs {args.command}: refused: {err}\n")
        sys.exit(code)

    from resireg.errors import ResiregError
    from resireg.secrets import mask_text
    from resireg.specs.tree import flatten
    from resireg_train.runs import index

    said: set[str] = set()
    try:
        if args.command == "ls":
            from resireg_train.runs.index import COLUMNS

            columns = args.columns.split(",") if args.columns else list(COLUMNS)
            for where in args.where:  # a bad filter exits 2 before any folder is walked
                index.parse_where(where)
            bad: list[str] = []
            runs = index.scan(args.roots, bad)
            _say(bad, said, prefix="skipped ")
            found = index.sort_runs(index.filter_runs(runs, args.where), args.sort)
            rows = [{c: r.value(c) for c in columns} for r in found]
            _say([p for r in runs for p in r.problems], said)
            _print_rows(rows, columns, args.format)
            if args.format == "table":
                print(f"{len(found)} run(s)")
            return
        if args.command == "card":
            from pathlib import Path

            from resireg_train.record.cards import CARD_FILE, add_evaluation

            for run in args.add:
                add_evaluation(args.export, run)
            path = Path(args.export) / CARD_FILE
            if not path.is_file():
                raise ValueError(f"{args.export}: no {CARD_FILE}")
            print(path.read_text())
            return
        if args.command == "plot":
            _plot(args)
            return
        if args.command in ("register", "gc"):
            from importlib import import_module

            module = {"register": "registry", "gc": "gc"}[args.command]
            import_module(f"resireg_train.runs.{module}").command(args)
            return
        roots = args.root or [DEFAULT_ROOT]
        if args.command == "show":
            run = index.find_run(args.run, roots)
            prov = run.provenance
            metric, value = run.headline
            # (a record written before URL passwords were masked is masked as it is shown)
            lines = [f"run {run.run_id} ({run.cli or '?'}) at {run.path}: {run.status}"]
            if run.results.get("error"):
                lines.append(f"error: {run.results['error']}")
            lines.append("overrides: " + (" ".join(run.overrides) or "none"))
            flat = flatten(prov, "provenance")
            lines += [f"  {key} = {_cell(flat[key])}" for key in sorted(flat)
                      if not key.startswith("provenance.environment.packages.")]  # fmt: skip
            packages = (prov.get("environment") or {}).get("packages") or {}
            lines.append("  packages: " + ", ".join(f"{k}=={v}" for k, v in packages.items()))
            lines += [f"  {key} = {_cell(val)}" for key, val in sorted(run.metrics.items())]
            if metric:
                lines.append(f"headline: {metric} = {_cell(value)}")
            _say(run.problems, said)
            print("\n".join(mask_text(line) for line in lines))
        elif args.command == "diff":
            a, b = index.find_run(args.a, roots), index.find_run(args.b, roots)
            from resireg_train.runs.diff import diff_runs

            differences = diff_runs(a, b)
            print(f"A: {a.run_id} {a.path}\nB: {b.run_id} {b.path}")
            for part in ("config", "provenance", "metrics"):
                print(f"\n{part}:")
                print(mask_text(_pairs(differences[part], "A", "B")))
            _say(a.problems + b.problems, said)
        else:
            from resireg_train.runs.lineage import lineage

            for line in lineage(args.run, roots):
                print(mask_text(line))
    except (ValueError, ResiregError) as err:  # bad input, refused (resireg.errors)
        parser.exit(2, f"resireg-runs: error: {mask_text(str(err))}\n")


def _plot(args: Any) -> None:
    """``resireg-runs plot``: a search folder alone draws its study's plots
    (:mod:`resireg_train.runs.search_plots`), else the runs' curves of each ``--metric``
    (:mod:`resireg_train.runs.plots`); prints each file written."""
    from resireg_train.runs.plots import plot_runs, runs_of
    from resireg_train.runs.search_plots import plot_search
    from resireg_train.search.report import is_optuna_sweep

    if not args.metric:
        if len(args.runs) != 1 or not is_optuna_sweep(args.runs[0]):
            raise ValueError("--metric is required (a search folder alone plots its study)")
        folder = Path(args.runs[0])
        result = plot_search(folder, Path(args.out) if args.out else folder / "plots")
    else:
        runs = runs_of(args.runs, args.root or ["outputs"])
        result = plot_runs(runs, args.metric, args.out or "runs.png", args.html)
        for run in runs:
            for problem in run.problems:
                print(f"resireg-runs: {problem}", file=sys.stderr)
    for path in result.files:
        print(path)


if __name__ == "__main__":
    main()
