"""What a search pays to open its journal safely, and to check its record.

Builds a journal study through Optuna's API (``--trials`` trials, each with two parameters and
``--reports`` intermediate values, as a pruned training search writes them), then times, the
median of ``--repeats`` runs in this process:

- Optuna's own open (``JournalStorage(JournalFileBackend(path))``: it replays every entry);
- :func:`resireg_train.search.journal.open_journal` on the intact file (the tail check first);
- ``open_journal`` on the file with a torn last line (the repair under the lock, then the open);
- the two steps ``open_journal`` adds, alone, 50 times as often: the tail check of an intact
  file, and the repair of a torn one (lock, cut, fsync);

and the check of a ``search.json`` (:func:`resireg_train.search.workers.read_record`: the job's
config composed with Hydra's compose API, every override checked), once per worker start:

    python benchmarks/bench_journal.py --trials 500 --reports 10 --repeats 5
"""

from __future__ import annotations

import argparse
import logging
import statistics
import tempfile
import time
from pathlib import Path


def make_journal(folder: Path, trials: int, reports: int) -> Path:
    import optuna

    from resireg_train.search.storage import open_storage

    study = optuna.create_study(storage=open_storage(None, folder), study_name="bench",
                                sampler=optuna.samplers.RandomSampler(0))  # fmt: skip
    for _ in range(trials):
        trial = study.ask()
        x = trial.suggest_float("lr", 1e-5, 1e-2, log=True)
        trial.suggest_int("depth", 1, 8)
        for step in range(reports):
            trial.report(x * step, step)
        study.tell(trial, x)
    return folder / "optuna.journal"


def timed(function, repeats: int, before=None) -> float:
    times = []
    for _ in range(repeats):
        if before is not None:
            before()
        start = time.perf_counter()
        function()
        times.append(time.perf_counter() - start)
    return statistics.median(times)


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    parser.add_argument("--trials", type=int, default=500)
    parser.add_argument("--reports", type=int, default=10)
    parser.add_argument("--repeats", type=int, default=5)
    args = parser.parse_args()
    logging.disable(logging.WARNING)  # the repair's warning, once per repeat
    import optuna
    from optuna.storages.journal import JournalFileBackend

    from resireg_train.search import journal as checks
    from resireg_train.search.journal import open_journal
    from resireg_train.search.workers import read_record, write_record

    with tempfile.TemporaryDirectory() as tmp:
        path = make_journal(Path(tmp), args.trials, args.reports)
        whole = path.read_bytes()
        lines = whole.count(b"\n")

        def tear() -> None:
            path.write_bytes(whole + whole.splitlines(keepends=True)[-1][:40])

        plain = timed(lambda: optuna.storages.JournalStorage(JournalFileBackend(str(path))),
                      args.repeats)  # fmt: skip
        checked = timed(lambda: open_journal(path), args.repeats)
        repaired = timed(lambda: open_journal(path), args.repeats, before=tear)
        assert path.read_bytes() == whole
        tail = timed(lambda: checks._needs_repair(path), 50 * args.repeats)
        repair = timed(lambda: checks._repair(path), 50 * args.repeats, before=tear)
        write_record(Path(tmp), "eval", ["dataset=synthetic", "hparams_search=resireg_optuna",
                     "hparams_search.n_trials=40", "full.alpha=interval(1.0,20.0)"], None, "b")  # fmt: skip
        record = timed(lambda: read_record(tmp), args.repeats)
    print(f"journal: {args.trials} trials, {lines} entries, {len(whole) / 1e6:.2f} MB")
    print(f"Optuna's open:              {plain * 1e3:8.1f} ms")
    print(f"open_journal, intact:       {checked * 1e3:8.1f} ms  ({checked / plain:.3f}x)")
    print(f"open_journal, torn tail:    {repaired * 1e3:8.1f} ms  ({repaired / plain:.3f}x)")
    print(f"the tail check alone:       {tail * 1e3:8.3f} ms")
    print(f"the repair alone:           {repair * 1e3:8.3f} ms")
    print(f"search.json check:          {record * 1e3:8.1f} ms  (once per worker start)")


if __name__ == "__main__":
    main()
