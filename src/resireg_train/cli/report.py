"""``resireg-report SWEEP_DIR [--metric NAME] [--out DIR]``: the console entry point of
:mod:`resireg_train.report`."""

from __future__ import annotations

import argparse

__all__ = ["main"]

DESCRIPTION = "Sweep reports: one table (and plots) from a Hydra multirun folder."


def main(argv: list[str] | None = None) -> None:
    """Console entry point ``resireg-report SWEEP_DIR [--metric NAME] [--out DIR]``."""
    parser = argparse.ArgumentParser(prog="resireg-report", description=DESCRIPTION)
    parser.add_argument("sweep_dir", help="a multirun folder: outputs/<name>/multirun/<time>")
    parser.add_argument("--metric", help="metric of the heatmap / curves / best column, one "
                        "the jobs' results hold (default: the first ReSiReg Full mIoU, else "
                        "train/loss); an unknown one is an error listing those")  # fmt: skip
    parser.add_argument("--out", help="where to write (default: the sweep folder)")
    parser.add_argument("--paper-tolerance", type=float, metavar="POINTS",
                        help="flag Table 1 / Table 2 cells further than this many points from "
                        "the paper's published value (default: one point, "
                        "resireg_train.report.paper.DEFAULT_TOLERANCE)")  # fmt: skip
    args = parser.parse_args(argv)
    if args.paper_tolerance is not None and not args.paper_tolerance >= 0:
        parser.error(f"--paper-tolerance={args.paper_tolerance}: expected a number >= 0")
    # pandas, matplotlib and the heuristic load after the arguments parse (--help stays fast).
    import pandas as pd

    from resireg_train import report as _report

    try:
        tolerance = (
            {"paper_tolerance": args.paper_tolerance} if args.paper_tolerance is not None else {}
        )
        files = _report.report(args.sweep_dir, args.out, args.metric, **tolerance)
    except (FileNotFoundError, ValueError) as err:
        parser.exit(2, f"resireg-report: error: {err}\n")
    for kind, path in files.items():
        print(f"{kind:>9}: {path}")
    table = pd.read_csv(files["csv"])
    print(f"{len(table)} jobs, {_report.count_statuses(table['status'])}")


if __name__ == "__main__":
    main()
