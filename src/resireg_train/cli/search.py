"""``resireg-search``: the command line of the searches (``hparams_search=<name>``).

``resireg-search worker <sweep>`` runs one more worker of the search in ``<sweep>`` (e.g. one
per SLURM array task, the sweep folder on a shared file system or the study in a database):
it starts the search's own entry point with the overrides ``<sweep>/search.json`` records,
once they are checked (:mod:`resireg_train.search.workers`), and pulls trials until the study
holds ``hparams_search.n_trials``. A database URL's password is never recorded: the worker
takes the whole URL from ``--storage`` or the environment variable ``RESIREG_SEARCH_STORAGE``.
"""

from __future__ import annotations

import logging
import subprocess
import sys
from collections.abc import Sequence
from pathlib import Path

from resireg.errors import ConfigError
from resireg.secrets import mask_text, mask_url
from resireg_train.search.storage import STORAGE_ENV, storage_url
from resireg_train.search.workers import (
    SearchRecordError,
    read_record,
    sigterm_ends,
    worker_command,
    worker_env,
)

__all__ = ["main", "worker_main"]

log = logging.getLogger(__name__)


def worker_main(argv: Sequence[str] | None = None) -> int:
    """``resireg-search worker <sweep> [--storage URL] [overrides...]``; returns the worker's
    exit code (2, with one line, for a refused ``search.json`` or storage)."""
    import argparse
    import os

    parser = argparse.ArgumentParser(
        prog="resireg-search",
        description="Run one more worker of an Optuna search (hparams_search=...): it pulls "
        "trials from the search's study until the study holds hparams_search.n_trials.",
    )
    sub = parser.add_subparsers(dest="command", required=True)
    worker = sub.add_parser("worker", help="run one worker of the search in SWEEP")
    worker.add_argument("sweep", type=Path, help="the search's sweep folder (hydra.sweep.dir)")
    worker.add_argument(
        "--storage", metavar="URL",
        help="the study's database URL with its password (search.json holds it masked); "
        f"default: the environment variable {STORAGE_ENV}",
    )  # fmt: skip
    worker.add_argument("overrides", nargs="*", help="extra overrides (e.g. device=cuda:0)")
    # (known args, then the rest: overrides may follow --storage, which parse_args refuses)
    args, rest = parser.parse_known_args(argv)
    if any(r.startswith("-") for r in rest):
        parser.error(f"unrecognized arguments: {' '.join(rest)}")
    overrides = [*args.overrides, *rest]
    try:
        record = read_record(args.sweep)
        whole = None
        if record.storage is not None:
            given = args.storage or os.environ.get(STORAGE_ENV)
            if given and mask_url(given) != record.storage:
                raise ConfigError(
                    f"--storage / {STORAGE_ENV}: {mask_url(given)!r} is not the search's storage "
                    f"{record.storage!r} ({args.sweep / 'search.json'})"
                )
            if given:
                os.environ[STORAGE_ENV] = given
            whole = storage_url(record.storage)  # a masked one needs the whole URL
    except (SearchRecordError, ConfigError) as err:
        parser.exit(2, f"resireg-search: {err}\n")
    cmd = worker_command(args.sweep, record) + overrides
    log.info("%s", mask_text(" ".join(cmd)))
    proc = subprocess.Popen(cmd, env=worker_env(whole))
    with sigterm_ends([proc]):  # kill <pid> of the worker ends its job too
        try:
            return proc.wait()
        except BaseException:  # Ctrl-C: as subprocess.call, the job is killed after its grace
            proc.kill()
            proc.wait()
            raise


def main() -> None:
    sys.exit(worker_main())


if __name__ == "__main__":  # python -m resireg_train.cli.search worker <sweep>
    main()
