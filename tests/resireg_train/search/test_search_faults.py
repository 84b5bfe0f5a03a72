"""The search's records under hostile files and faults (resireg_train.search): a worker runs no
command line read from ``search.json`` and refuses every override that could make it one; the
storage's password is in no file of the sweep folder and not on the console; a torn journal is
repaired and a damaged one named; under ``umask 077`` everything a search writes is private.
Each search here is a real ``resireg-eval`` search of a tiny random-init export."""

from __future__ import annotations

import json
import logging
import os
import secrets
import shutil
import stat
import subprocess
import sys
from pathlib import Path

import pytest

from helpers.postgres import postgres_server
from helpers.run import _command, _env, report

optuna = pytest.importorskip("optuna")

from optuna.trial import TrialState  # noqa: E402

#: Made at run time: a constant would be in this file, so in the checkout's code.diff too.
PASSWORD = "pw-" + secrets.token_hex(8)


def _eval_search(export, sweep, n_trials, *extra):
    """An eval-time search (resireg_optuna) of ``n_trials`` over alpha and the prototype count
    on 8 synthetic images."""
    return ("resireg-eval", f"model_path={export}", "dataset=synthetic", "dataset.size=8",
            "num_workers=0", "batch_size=2", "full.upscale=1", "full.tau=0.0",
            "hparams_search=resireg_optuna", f"hparams_search.n_trials={n_trials}",
            "full.n_prototypes=choice(3,4,5,6)", "full.alpha=interval(1.0,20.0)",
            f"hydra.sweep.dir={sweep}", *extra)  # fmt: skip


def _worker(sweep, *args):
    """``resireg-search worker <sweep> args...`` as a command (the console script, or its
    module where the installed one is missing)."""
    exe = shutil.which("resireg-search")
    start = [exe] if exe else [sys.executable, "-m", "resireg_train.cli.search"]
    return [*start, "worker", str(sweep), *map(str, args)]


def _run(command, cwd=None, env=None, umask=None, timeout=600):
    """``command`` (a list) in a fresh process, its output captured; ``umask``: the child's."""

    def child():
        if umask is not None:
            os.umask(umask)

    return subprocess.run(command, capture_output=True, text=True, timeout=timeout, cwd=cwd,
                          env=_env(env, threads=1), preexec_fn=child)  # fmt: skip


def _study(sweep, storage=None):
    from resireg_train.search.storage import load_study

    return load_study(sweep, storage, "resireg_optuna")


def _counted(study):
    from resireg_train.search.trials import counted_trials

    return counted_trials(study.get_trials())


def _record(sweep, overrides, job="eval", **extra):
    """A ``search.json`` of the current format, as a search writes it, with ``overrides``."""
    record = {"format": "resireg.search/2", "job": job, "overrides": list(overrides),
              "storage": None, "study_name": "resireg_optuna", **extra}  # fmt: skip
    Path(sweep).mkdir(parents=True, exist_ok=True)
    (Path(sweep) / "search.json").write_text(json.dumps(record))


# ----------------------------------------------------------------------------- search.json
GOOD = ["model_path=/nowhere/export", "dataset=synthetic", "dataset.size=8",
        "hparams_search=resireg_optuna", "hparams_search.n_trials=3",
        "full.n_prototypes=choice(3,4,5,6)", "full.alpha=interval(1.0,20.0)",
        "hydra.sweeper.max_failure_rate=0.75", "hydra.sweeper.enqueue=[{full.n_prototypes:3}]",
        "hydra.sweeper.sampler._target_=optuna.samplers.RandomSampler"]  # fmt: skip


def test_a_worker_never_runs_the_command_line_search_json_records(tmp_path):
    """A search.json of the earlier format whose command is ``python -c <code that creates a
    file>``, and one of the current format whose override would have Hydra create the file
    (a callback whose _target_ is builtins.open): resireg-search worker refuses each in one
    line naming search.json and the entry; the file never appears."""
    marker = tmp_path / "pwned"
    sweep = tmp_path / "sweep"
    sweep.mkdir()
    code = f"open({str(marker)!r}, 'w').write('x')"
    (sweep / "search.json").write_text(json.dumps({
        "argv": ["-c", code], "cwd": str(tmp_path), "storage": None, "study_name": "s"}))  # fmt: skip
    proc = _run(_worker(sweep), cwd=tmp_path)
    lines = proc.stderr.strip().splitlines()
    assert proc.returncode == 2 and len(lines) == 1, proc.stderr
    assert str(sweep / "search.json") in lines[0] and "format" in lines[0], lines
    assert "command line" in lines[0] and "Traceback" not in proc.stderr
    assert not marker.exists()

    planted = f"++hydra.callbacks.pwn={{_target_:builtins.open,file:{marker},mode:w}}"
    _record(sweep, [*GOOD, planted])
    proc = _run(_worker(sweep), cwd=tmp_path)
    lines = proc.stderr.strip().splitlines()
    assert proc.returncode == 2 and len(lines) == 1, proc.stderr
    assert f"{sweep / 'search.json'}: overrides[{len(GOOD)}]={planted!r} is refused" in lines[0]
    assert not marker.exists() and not list(sweep.glob("*/results.json"))


@pytest.mark.parametrize(
    "entry, why",
    [
        ("callbacks.optuna_pruning._target_=builtins.open", "names a class to instantiate"),
        ("full={_target_:os.system}", "its value names a class to instantiate"),
        ("full.alpha=choice({_target_:os.system},1.0)", "its value names a class"),
        ("hydra.sweeper.sampler._target_=os.system", "names a class to instantiate"),
        ("hydra.job.env_set.LD_PRELOAD=/tmp/x.so", "sets Hydra's own config"),
        ("hydra.run.dir=/elsewhere", "sets Hydra's own config"),
        ("hydra/launcher=submitit_local", "sets Hydra's own config"),
        ("hydra.searchpath=[file:///tmp]", "sets Hydra's own config"),
        ("no_such.key=1", "resireg-eval's config has no such key"),
        ("+full.extra=1", "adds a key absent from the composed config"),
        ("dataset=../../../tmp/evil", "is not an option of config group 'dataset'"),
        ("model_path=${oc.env:HOME}", "interpolation"),
        ("~dataset.size", "deletes a key"),
    ],
)
def test_each_kind_of_recorded_override_is_refused(tmp_path, capsys, entry, why):
    """Every kind of override a worker refuses (a _target_ key or value, Hydra's own config,
    a key the composed config lacks, a group option outside conf/, an interpolation, a
    deletion): exit 2, one line naming search.json, the entry and why. The same record
    without the entry passes the check (the refusal is the entry's)."""
    from resireg_train.cli.search import worker_main
    from resireg_train.search.workers import read_record

    sweep = tmp_path / "sweep"
    _record(sweep, GOOD)
    assert read_record(sweep).overrides == tuple(GOOD)
    _record(sweep, [*GOOD[:2], entry, *GOOD[2:]])
    with pytest.raises(SystemExit) as exit_:
        worker_main(["worker", str(sweep)])
    err = capsys.readouterr().err.strip().splitlines()
    assert exit_.value.code == 2 and len(err) == 1, err
    assert f"{sweep / 'search.json'}: overrides[2]={entry!r} is refused" in err[0]
    assert why in err[0], err[0]


@pytest.mark.parametrize(
    "record, why",
    [
        ({"job": "python"}, "job='python' is not one a worker starts"),
        ({"overrides": "rm -rf /"}, "overrides must be a list of strings"),
        ({"study_name": None}, "study_name=None is not a name"),
        ({"format": "resireg.search/1"}, "format 'resireg.search/1' is not"),
        ({"cwd": "/elsewhere"}, "unknown entry 'cwd'"),
    ],
)
def test_a_record_other_than_a_search_of_train_or_eval_is_refused(tmp_path, capsys, record, why):
    """The job kind is checked against the fixed table (resireg-train, resireg-eval); an entry
    of the wrong kind, or one the format does not have (a working folder to run in), is
    refused naming search.json and the entry."""
    from resireg_train.cli.search import worker_main

    sweep = tmp_path / "sweep"
    _record(sweep, GOOD)
    data = json.loads((sweep / "search.json").read_text())
    (sweep / "search.json").write_text(json.dumps({**data, **record}))
    with pytest.raises(SystemExit) as exit_:
        worker_main(["worker", str(sweep)])
    err = capsys.readouterr().err.strip().splitlines()
    assert exit_.value.code == 2 and len(err) == 1, err
    assert str(sweep / "search.json") in err[0] and why in err[0], err[0]


# ----------------------------------------------------------------------------- the journal
def _made_journal(folder, n, worker=None):
    """A journal study named like the eval search's, of ``n`` told trials (Optuna's API);
    ``worker``: the ``{worker_host, worker_pid}`` a search's worker marks its trials with."""
    from resireg_train.search.storage import open_storage

    study = optuna.create_study(storage=open_storage(None, folder), study_name="resireg_optuna",
                                direction="maximize", sampler=optuna.samplers.RandomSampler(0))  # fmt: skip
    for _ in range(n):
        trial = study.ask()
        for key, value in (worker or {}).items():
            trial.set_user_attr(key, value)
        study.tell(trial, trial.suggest_float("full.alpha", 1.0, 20.0))
    return {t.number: (t.value, t.params) for t in study.get_trials()}


def _lines(path):
    return Path(path).read_bytes().splitlines(keepends=True)


@pytest.mark.parametrize("damage", ["cut mid-write", "newline lost"])
def test_a_torn_last_line_is_recovered_and_the_study_goes_on(tmp_path, caplog, damage):
    """A crash while appending leaves a last line without its newline: either part of a new
    entry (cut off) or a whole entry that lost its newline (kept). Opening the study warns
    naming the journal, keeps every finished trial, and what is appended next is readable:
    one more trial, and the study reopens with all of them (no JSONDecodeError)."""
    from resireg_train.search.storage import open_storage

    before = _made_journal(tmp_path, 3)
    journal = tmp_path / "optuna.journal"
    whole = journal.read_bytes()
    if damage == "cut mid-write":
        partial = _lines(journal)[-1][:25]  # the first bytes of another entry
        journal.write_bytes(whole + partial)
    else:
        journal.write_bytes(whole[:-1])
    with caplog.at_level(logging.WARNING):
        study = optuna.load_study(study_name="resireg_optuna", storage=open_storage(None, tmp_path))
    warned = [r.getMessage() for r in caplog.records if "cut mid-write" in r.getMessage()]
    assert len(warned) == 1 and str(journal) in warned[0], caplog.text
    assert journal.read_bytes() == whole  # exactly the complete entries, nothing else
    assert {t.number: (t.value, t.params) for t in study.get_trials()} == before
    trial = study.ask()
    study.tell(trial, 1.0)
    for line in _lines(journal):
        assert isinstance(json.loads(line), dict)
    reopened = optuna.load_study(study_name="resireg_optuna", storage=open_storage(None, tmp_path))
    assert [t.state for t in reopened.get_trials()] == [TrialState.COMPLETE] * 4


@pytest.mark.parametrize("where", ["inside", "last"])
def test_a_damaged_journal_line_is_refused_naming_the_journal_and_line(tmp_path, tiny_export,
                                                                        where):  # fmt: skip
    """A line that is not a journal entry (what the old resume made of a torn line: a partial
    entry with the next one appended to it), inside the journal or as its last complete line
    (which Optuna's reader would skip): resuming the search and reporting it are refused in
    one line naming the journal and the line; the journal is left as it was."""
    sweep = tmp_path / "sweep"
    _made_journal(sweep, 3)
    journal = sweep / "optuna.journal"
    lines = _lines(journal)
    bad = lines[-1][:30] + lines[1]
    number = 4 if where == "inside" else len(lines) + 1
    damaged = b"".join([*lines[: number - 1], bad, *lines[number - 1 :]])
    journal.write_bytes(damaged)
    expected = f"{journal}: line {number} is not an Optuna journal entry"
    proc = _run(_command("resireg-eval", _eval_search(tiny_export, sweep, 5)[1:]))
    assert proc.returncode != 0 and expected in proc.stderr, proc.stderr[-2000:]
    assert "Traceback" not in proc.stderr and "JSONDecodeError" not in proc.stderr
    assert journal.read_bytes() == damaged
    assert not list(sweep.glob("*/results.json"))
    with pytest.raises(SystemExit) as exit_:
        report(sweep)
    assert exit_.value.code == 2


# ----------------------------------------------------------------------------- permissions
def _not_private(folder):
    """Every path under ``folder`` (and itself) whose mode lets the group or others in."""
    paths = [Path(folder), *Path(folder).rglob("*")]
    return [(str(p), oct(stat.S_IMODE(p.lstat().st_mode))) for p in paths
            if not p.is_symlink() and stat.S_IMODE(p.lstat().st_mode) & 0o077]  # fmt: skip


@pytest.mark.slow
def test_a_search_and_a_worker_moved_with_its_folder_write_only_private_files(tmp_path,
                                                                              tiny_export):  # fmt: skip
    """Under umask 077: a search of one trial, then (its process killed while appending to
    the journal: a torn last line) the sweep folder moved elsewhere, and one more worker,
    started from another folder, extends it to two trials. The worker warns about the torn
    line naming the journal, keeps the finished trial, runs the new one in the sweep folder's
    own (new) location, and every file and folder of the sweep is private to its owner."""
    first, sweep = tmp_path / "first", tmp_path / "moved" / "sweep"
    proc = _run(_command("resireg-eval", _eval_search(tiny_export, first, 1)[1:]), umask=0o077)
    assert proc.returncode == 0, proc.stderr[-3000:]
    before = {t.number: (t.value, t.params) for t in _counted(_study(first))}
    journal = first / "optuna.journal"
    journal.write_bytes(journal.read_bytes() + _lines(journal)[-1][:40])  # a torn append
    sweep.parent.mkdir()
    first.rename(sweep)
    elsewhere = tmp_path / "elsewhere"
    elsewhere.mkdir()
    proc = _run(_worker(sweep, "hparams_search.n_trials=2"), cwd=elsewhere, umask=0o077)
    said = proc.stdout + proc.stderr
    assert proc.returncode == 0, said[-3000:]
    assert f"{sweep / 'optuna.journal'}: its last line was cut mid-write" in said
    study = _study(sweep)
    done = _counted(study)
    assert len(done) == 2 and all(t.state == TrialState.COMPLETE for t in done)
    assert {t.number: (t.value, t.params) for t in done if t.number in before} == before
    new = [t for t in done if t.number not in before]
    assert len(new) == 1 and Path(new[0].user_attrs["run_dir"]).parent == sweep
    assert len({tuple(sorted(t.params.items())) for t in done}) == 2  # no trial repeated
    assert all(isinstance(json.loads(line), dict) for line in _lines(sweep / "optuna.journal"))
    assert not list(elsewhere.iterdir())  # nothing written where the worker was started
    assert _not_private(sweep) == []


# ----------------------------------------------------------------------------- the password
@pytest.fixture
def postgres_with_password():
    """A PostgreSQL server of its own that asks for a password (tests/helpers/postgres.py); yields
    the environment (PGHOST / PGPORT / PGUSER) that reaches it, without the password
    (:data:`PASSWORD`)."""
    with postgres_server(PASSWORD) as env:
        yield env


@pytest.mark.slow
def test_the_storage_password_is_in_no_file_and_on_no_console(tmp_path, tiny_export,
                                                               postgres_with_password,
                                                               monkeypatch):  # fmt: skip
    """A 2-worker search whose study is in a PostgreSQL database that asks for a password,
    typed in hparams_search.storage; then one more worker, refused in one line without the
    password and run with --storage; then the report, with the URL in RESIREG_SEARCH_STORAGE.
    Every trial reached the database (3 finished), and the password is in no file of the
    sweep folder (search.json, each trial's config, overrides and results.json, the logs) and
    in no output; search.json holds the URL masked."""
    env = {k: v for k, v in os.environ.items() if not k.startswith("PG")}
    env.update(postgres_with_password)
    url = f"postgresql+psycopg://postgres:{PASSWORD}@/optuna"
    masked = "postgresql+psycopg://postgres:***@/optuna"
    sweep = tmp_path / "sweep"
    said = []
    proc = _run(_command("resireg-eval", _eval_search(tiny_export, sweep, 2,
                "hparams_search.workers=2", f"hparams_search.storage={url}")[1:]), env=env)  # fmt: skip
    said.append(proc.stdout + proc.stderr)
    assert proc.returncode == 0, said[-1][-3000:]
    assert json.loads((sweep / "search.json").read_text())["storage"] == masked

    proc = _run(_worker(sweep, "hparams_search.n_trials=3"), env=env)
    said.append(proc.stdout + proc.stderr)
    lines = proc.stderr.strip().splitlines()
    assert proc.returncode == 2 and len(lines) == 1, proc.stderr[-3000:]
    assert "RESIREG_SEARCH_STORAGE" in lines[0] and masked in lines[0]

    proc = _run(_worker(sweep, "--storage", url, "hparams_search.n_trials=3"), env=env)
    said.append(proc.stdout + proc.stderr)
    assert proc.returncode == 0, said[-1][-3000:]

    for key, value in {**postgres_with_password, "RESIREG_SEARCH_STORAGE": url}.items():
        monkeypatch.setenv(key, value)  # this process reports the search
    said.append(report(sweep))
    study = _study(sweep, masked)
    assert len(_counted(study)) == 3
    assert len({t.user_attrs["worker_pid"] for t in study.get_trials()}) >= 2  # the last worker's
    leaks = [
        str(p) for p in sweep.rglob("*") if p.is_file() and PASSWORD.encode() in p.read_bytes()
    ]
    assert leaks == [], leaks
    assert not any(PASSWORD in text for text in said)
    assert any(masked in p.read_text() for p in sweep.glob("*/.hydra/overrides.yaml"))


def test_a_lost_trial_result_is_named_on_the_console_when_the_search_resumes(tmp_path,
                                                                             tiny_export):  # fmt: skip
    """Issue 51, item 15: a journal whose last line, a trial's completion, was cut mid-write:
    resuming the search with resireg-eval says on its console which journal and which trial
    lost its result (by the trial's number, although the cut came before the entry named it),
    and failing that trial it says its result was lost, not that its worker died mid-trial;
    every complete entry of the journal is kept byte for byte, and the finished trials too."""
    import socket

    from resireg_train.search.trials import ATTR_HOST, ATTR_PID

    gone = subprocess.Popen([sys.executable, "-c", ""])  # the worker, ended since
    gone.wait()
    sweep = tmp_path / "sweep"
    before = _made_journal(sweep, 3, {ATTR_HOST: socket.gethostname(), ATTR_PID: gone.pid})
    journal = sweep / "optuna.journal"
    lines = _lines(journal)
    assert json.loads(lines[-1])["op_code"] == 6  # trial 2's state and value
    kept = b"".join(lines[:-1])
    journal.write_bytes(kept + lines[-1][:40])  # cut inside its worker id: no trial_id
    # 2 trials asked for: 2 finished already, so the resumed search runs none
    proc = _run(_command("resireg-eval", _eval_search(tiny_export, sweep, 2)[1:]))
    said = proc.stdout + proc.stderr
    assert proc.returncode == 0, said[-3000:]
    assert (f"{journal}: its last line was cut mid-write (a process stopped while writing): "
            "removed (40 bytes), which held trial 2's result (its state and value), now lost: "
            "trial 2 reads RUNNING until the search marks it failed") in said, said[-3000:]
    assert (f"trial 2: its result was lost: the last line of {journal}, which held it, was cut "
            "mid-write: marked FAIL") in said, said[-3000:]
    assert "died mid-trial" not in said, said[-3000:]
    assert journal.read_bytes().startswith(kept)
    study = _study(sweep)
    assert {t.number: (t.value, t.params) for t in study.get_trials()
            if t.number < 2} == {n: before[n] for n in (0, 1)}  # fmt: skip
    assert study.trials[2].state != TrialState.COMPLETE  # its result is not made up
    from resireg_train.search.report import trials_table

    table = trials_table(study, []).set_index("trial")  # the search report says it the same
    assert table.loc[2, "error"] == (f"its result was lost: the last line of {journal}, which "
                                     "held it, was cut mid-write")  # fmt: skip
