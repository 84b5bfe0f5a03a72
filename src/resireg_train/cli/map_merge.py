"""``resireg-map-merge``: one map of several mapping runs (Hydra main; ``conf/map_merge.yaml``,
docs/mapping.md#merging-maps). The merge itself: :mod:`resireg_train.jobs.map_merge`.

    resireg-map-merge A B --out C            # A, B: map folders or resireg-map run folders
    resireg-map-merge A B --out C 'transform=[[0,-1,0,2.0],[1,0,0,0],[0,0,1,0],[0,0,0,1]]'

``--out`` is checked before anything is written into it (:class:`MergeFolderCheck`, before
Hydra writes its ``.hydra/`` files and the log; :func:`resireg_train.checks.map.check_merge_out`):
a folder that holds a map, or the record of any other run (a ``resireg-map`` run, an evaluation,
another merge), or lies inside such a folder, is refused in one line and left as it was; the
folder of this same merge that did not complete (interrupted, killed, failed) is taken again,
the temporary files a killed save left in ``<out>/map`` removed.
"""

from __future__ import annotations

import sys
from pathlib import Path
from typing import Any

from hydra.experimental.callback import Callback
from omegaconf import DictConfig

from resireg.errors import ConfigError
from resireg_train.checks.map import MERGE as PROG
from resireg_train.checks.map import check_merge_out, merge_names
from resireg_train.cli.job import hydra_entry_point, run_task
from resireg_train.jobs.console import error_text
from resireg_train.jobs.map_merge import merge_job

__all__ = ["PROG", "MergeFolderCheck", "hydra_arguments", "main", "run_merge"]


class MergeFolderCheck(Callback):
    """Hydra callback (``conf/map_merge.yaml``, before the folder's lock): the ``--out`` check
    before Hydra writes anything into ``--out`` (``.hydra/``, the log file), so a refused
    merge leaves another run's folder exactly as it was."""

    def on_run_start(self, config: DictConfig, **kwargs: Any) -> None:
        out = Path(str(config.hydra.run.dir))
        try:
            check_merge_out(out, merge_names(config))
        except ConfigError as err:
            # Hydra turns a callback's exception into a warning and runs the job anyway: exit.
            sys.stderr.write(f"{PROG}: refused: {error_text(err)}\n")
            raise SystemExit(1) from None


def run_merge(cfg: DictConfig) -> dict[str, Any]:
    """Merge from a composed ``map_merge.yaml`` config; returns the ``results.json`` content.
    ``--out`` is checked first (from the command line, before Hydra wrote into it)."""
    check_merge_out(Path(cfg.paths.output_dir), merge_names(cfg))
    return run_task(cfg, merge_job, fresh=True)


def _quoted(text: str) -> str:
    """A value as a quoted string of Hydra's override grammar (any path stays one value)."""
    return "'" + text.replace("\\", "\\\\").replace("'", "\\'") + "'"


def hydra_arguments(argv: list[str]) -> list[str]:
    """``A B --out C key=value ...`` as Hydra's arguments: ``maps=[A,B]``,
    ``hydra.run.dir=C``, the overrides as they are (Hydra's own flags too)."""
    maps, rest, out = [], [], None
    args = iter(argv)
    for arg in args:
        if arg == "--out" or arg.startswith("--out="):
            out = arg.split("=", 1)[1] if "=" in arg else next(args, None)
            if not out:
                raise SystemExit(f"{PROG}: error: --out needs a folder")
        elif arg.startswith("-") or "=" in arg:
            rest.append(arg)
        else:
            maps.append(arg)
    front = [f"maps=[{','.join(map(_quoted, maps))}]"] if maps else []
    if out is not None:
        front.append(f"hydra.run.dir={_quoted(out)}")
    return [*front, *rest]


_main = hydra_entry_point("map_merge", run_merge)


def main() -> float | None:
    sys.argv = [sys.argv[0], *hydra_arguments(sys.argv[1:])]
    return _main()


if __name__ == "__main__":
    main()
