"""Optuna searches (hparams_search=..., resireg_train.search and the project's Hydra sweeper) on
the synthetic set: pruning of a bad training trial, workers sharing one study (journal file and
PostgreSQL), a worker killed mid-trial, a whole search killed and run again, two searches started
at once on one folder, a metric the validation data never logs, the report and optuna-dashboard.
Every count is read back from Optuna's own storage and the jobs' results.json files.

One idea: an Optuna search as a user runs it, end to end; every test reads its counts back
from the same storage and the same shared fixtures (the tiny export, the PostgreSQL server)."""

from __future__ import annotations

import json
import math
import os
import re
import shutil
import signal
import socket
import subprocess
import sys
import time
import urllib.request
import warnings
from pathlib import Path

import pandas as pd
import pytest

from helpers.paths import ROOT, TESTS
from helpers.postgres import postgres_server
from helpers.run import _command, report, run, run_side_by_side, started

optuna = pytest.importorskip("optuna")

from optuna.trial import TrialState  # noqa: E402

METRIC = "val/ovss/synthetic/miou_full"
CONF = ROOT / "conf"


def _eval_search(export, sweep, n_trials, *extra):
    """An eval-time search (resireg_optuna) of ``n_trials`` in total over alpha and the
    prototype count on 8 synthetic images."""
    return ("resireg-eval", f"model_path={export}", "dataset=synthetic", "dataset.size=8",
            "num_workers=0", "batch_size=2", "full.upscale=1", "full.tau=0.0",
            "hparams_search=resireg_optuna", f"hparams_search.n_trials={n_trials}",
            "full.n_prototypes=choice(3,4,5,6)", "full.alpha=interval(1.0,20.0)",
            f"hydra.sweep.dir={sweep}", *extra)  # fmt: skip


def _study(sweep, name="resireg_optuna", storage=None):
    from resireg_train.search.storage import load_study

    return load_study(sweep, storage, name)


def _counted(study):
    from resireg_train.search.trials import counted_trials

    return counted_trials(study.get_trials())


def _records(sweep):
    return {p.parent.name: json.loads(p.read_text()) for p in Path(sweep).glob("*/results.json")}


def _check_total(sweep, n_trials, storage=None):
    """Exactly ``n_trials`` finished trials, distinct numbers, each with its own run folder
    that holds its results.json, and no finished parameter set run twice."""
    study = _study(sweep, storage=storage)
    done = _counted(study)
    assert len(done) == n_trials, [(t.number, t.state.name) for t in study.get_trials()]
    numbers = [t.number for t in done]
    assert len(set(numbers)) == n_trials
    folders = [Path(t.user_attrs["run_dir"]) for t in done]
    assert len(set(folders)) == n_trials and all(f.parent == Path(sweep) for f in folders)
    records = _records(sweep)
    for trial, folder in zip(done, folders, strict=True):
        record = records[folder.name]
        assert record["status"] == "completed", record
        assert record["final"][METRIC] == pytest.approx(trial.value, rel=1e-12)
        assert record["params"]["full"]["alpha"] == pytest.approx(trial.params["full.alpha"])
    params = [tuple(sorted(t.params.items())) for t in done]
    assert len(set(params)) == n_trials, params
    return study


def _started(command, log):
    """``command`` (``(script, *args)``) started in its own process group, output to the file
    ``log`` (see :func:`helpers.run.started`)."""
    script, *args = command
    return started(_command(script, args), stdout=log, threads=1)


def _wait_for(predicate, timeout=300, what="condition", alive=()):
    """``predicate()``'s first true value, polled; an AssertionError after ``timeout`` seconds,
    or as soon as a process of ``alive`` (the ones that could bring the state about) exited."""
    end = time.monotonic() + timeout
    while time.monotonic() < end:
        value = predicate()
        if value:
            return value
        for proc in alive:
            assert proc.poll() is None, f"{proc} exited ({proc.returncode}) before {what}"
        time.sleep(0.2)
    raise AssertionError(f"timed out waiting for {what}")


def _running_trial_of(sweep, group):
    """A RUNNING trial whose worker process belongs to process group ``group``."""
    study = _study(sweep)
    if study is None:
        return None
    for trial in study.get_trials(states=(TrialState.RUNNING,)):
        try:
            if os.getpgid(int(trial.user_attrs["worker_pid"])) == group:
                return trial
        except (KeyError, ProcessLookupError):
            continue
    return None


# ----------------------------------------------------------------------------- search space
@pytest.mark.parametrize("name", ["stage1_optuna", "resireg_optuna"])
def test_shipped_search_spaces_are_exact_and_warn_nothing(name, caplog):
    """Each range(...) axis becomes Optuna's distribution over exactly Python's range of the
    same arguments (the old sweeper turned range(0, 9, 2) into [0, 9] step 2: "not
    divisible" warnings); building the spaces warns nothing."""
    from omegaconf import OmegaConf

    from resireg_train.search.space import distributions

    params = OmegaConf.load(CONF / "hparams_search" / f"{name}.yaml").hydra.sweeper.params
    params = OmegaConf.to_container(params)
    with warnings.catch_warnings(record=True) as caught:
        warnings.simplefilter("always")
        space = distributions(params)
    assert not caught, [str(w.message) for w in caught]
    assert "divisible" not in caplog.text
    ranges = {k: v for k, v in params.items() if v.startswith("range(")}
    assert ranges
    for key, expr in ranges.items():
        values = list(eval(expr))  # Python's own range of the same arguments
        dist = space[key]
        grid = list(range(dist.low, dist.high + 1, dist.step))
        assert grid == values, (key, grid, values)


def test_a_metric_the_validation_data_never_logs_is_refused_before_the_first_trial(tmp_path):
    """stage1_optuna on the smoke experiment optimises the first validation dataset's metric
    (synthetic); an optimized_metric of a dataset that is not validated is refused before any
    trial, in one message naming the key and what is logged."""
    sweep = tmp_path / "sweep"
    proc = run("resireg-train", "experiment=smoke", "hparams_search=stage1_optuna",
               "optimized_metric=val/ovss/ade20k/miou_full", f"hydra.sweep.dir={sweep}",
               check=False)  # fmt: skip
    assert proc.returncode != 0
    assert "optimized_metric='val/ovss/ade20k/miou_full' is never logged" in proc.stderr
    assert "val/ovss/synthetic/miou_full" in proc.stderr and "Traceback" not in proc.stderr
    assert not list(sweep.glob("*/results.json"))  # no trial ran
    # The default metric follows val_data=: accepted (a search of 0 trials ends at once).
    ok = run("resireg-train", "experiment=smoke", "hparams_search=stage1_optuna",
             "hparams_search.n_trials=0", f"hydra.sweep.dir={tmp_path / 'ok'}")  # fmt: skip
    assert "never logged" not in ok.stderr


# ----------------------------------------------------------------------------- pruning
@pytest.mark.slow
def test_a_bad_training_trial_is_pruned_and_reported(tmp_path):
    """Two stage-1 trials of 3 epochs on the smoke experiment, the first with a learning rate
    that learns, the second with one that cannot (1e-9): the median pruner stops the second
    after its first epoch; the trial is PRUNED with that epoch's value, its folder says
    pruned, and the report lists it PRUNED. The output holds no colour codes and no
    "not divisible" warning; the end names the sweep and the report command."""
    sweep = tmp_path / "sweep"
    proc = run("resireg-train", "experiment=smoke", "hparams_search=stage1_optuna",
               "hparams_search.n_trials=2", "trainer.max_epochs=3",
               "model.optimizer.lr=choice(0.003,1.0e-9)", "model.scheduler.min_lr=1.0e-10",
               "hydra.sweeper.enqueue=[{model.optimizer.lr:0.003},{model.optimizer.lr:1.0e-9}]",
               "hydra.sweeper.pruner.n_startup_trials=1", "hydra.sweeper.pruner.n_warmup_steps=0",
               f"hydra.sweep.dir={sweep}")  # fmt: skip
    said = proc.stdout + proc.stderr
    assert "\x1b[" not in said and "divisible" not in said
    assert f"(sweep {sweep}; resireg-report {sweep} lists every job)" in proc.stderr
    study = _study(sweep, "stage1_optuna")
    first, second = study.get_trials()
    assert first.state == TrialState.COMPLETE and second.state == TrialState.PRUNED
    assert second.params["model.optimizer.lr"] == 1.0e-9
    assert list(first.intermediate_values) == [0, 1, 2]
    assert list(second.intermediate_values) == [0]  # stopped before its last epoch
    # Its last reported value is the one its run recorded for that epoch, below the first's.
    record = json.loads((Path(second.user_attrs["run_dir"]) / "results.json").read_text())
    assert record["status"] == "pruned" and "pruned by MedianPruner" in record["error"]
    assert [row["epoch"] for row in record["history"]] == [0]
    assert record["history"][0][METRIC] == pytest.approx(second.intermediate_values[0])
    assert second.intermediate_values[0] < first.intermediate_values[0]
    report(sweep)
    table = pd.read_csv(sweep / "optuna_trials.csv")
    assert list(table["state"]) == ["COMPLETE", "PRUNED"]
    assert list(table["job status"]) == ["completed", "pruned"]
    assert table["last epoch"].tolist() == [2, 0]
    assert (sweep / "optuna_intermediate.png").stat().st_size > 10_000


# ----------------------------------------------------------------------------- workers
@pytest.mark.slow
def test_two_workers_share_one_journal_study(tmp_path, tiny_export):
    """hparams_search.workers=2: two processes on one journal-file study end with exactly
    n_trials finished trials, distinct numbers, each run folder once; the report's table
    lists each trial with its folder; the end names the sweep and the report command."""
    sweep = tmp_path / "sweep"
    proc = run(*_eval_search(tiny_export, sweep, 5, "hparams_search.workers=2"), threads=1)
    study = _check_total(sweep, 5)
    pids = {t.user_attrs["worker_pid"] for t in study.get_trials()}
    assert len(pids) == 2  # both workers ran trials
    said = proc.stdout + proc.stderr
    assert "\x1b[" not in said and "divisible" not in said
    assert f"resireg-eval: 5 jobs ran, none failed (sweep {sweep}; resireg-report" in proc.stderr
    report(sweep)
    table = pd.read_csv(sweep / "optuna_trials.csv")
    assert sorted(table["trial"]) == list(range(5))
    assert table["run folder"].nunique() == 5 and (table["job status"] == "completed").all()
    assert (sweep / "optuna_importance.png").stat().st_size > 10_000


@pytest.fixture
def postgres():
    """A PostgreSQL server of its own (tests/helpers/postgres.py); yields the environment (PGHOST /
    PGPORT / PGUSER) that reaches it."""
    with postgres_server() as env:
        yield env


@pytest.mark.slow
def test_two_workers_share_one_postgresql_study(tmp_path, tiny_export, postgres, monkeypatch):
    """The same with the study in a PostgreSQL database (hparams_search.storage=<URL>)."""
    for key, value in postgres.items():
        monkeypatch.setenv(key, value)
    url = "postgresql+psycopg://postgres@/optuna"
    sweep = tmp_path / "sweep"
    run(*_eval_search(tiny_export, sweep, 4, "hparams_search.workers=2",
                      f"hparams_search.storage={url}"), threads=1)  # fmt: skip
    assert not (sweep / "optuna.journal").exists()
    study = _check_total(sweep, 4, storage=url)
    assert len({t.user_attrs["worker_pid"] for t in study.get_trials()}) == 2
    report(sweep)  # the report finds the database through the search's record
    assert sorted(pd.read_csv(sweep / "optuna_trials.csv")["trial"]) == [0, 1, 2, 3]


@pytest.mark.slow
def test_processes_opening_a_new_database_at_once_all_open_it(tmp_path, postgres, monkeypatch):
    """Optuna makes its tables when a new database is first opened, and two first opens at once
    race (PostgreSQL: a duplicate key in its catalogue; optuna/optuna#1092): eight opens at once
    (threads, each its own connection) all succeed and see the one study made after."""
    import threading

    from resireg_train.search.storage import open_storage

    for key, value in postgres.items():
        monkeypatch.setenv(key, value)
    url = "postgresql+psycopg://postgres@/optuna"
    start, opened, failed = threading.Barrier(8), [], []

    def open_it():
        start.wait()
        try:
            opened.append(open_storage(url, tmp_path))
        except Exception as err:  # noqa: BLE001  (what the test reports)
            failed.append(err)

    threads = [threading.Thread(target=open_it) for _ in range(8)]
    for thread in threads:
        thread.start()
    for thread in threads:
        thread.join(120)
    assert not failed and len(opened) == 8, failed
    optuna.create_study(storage=opened[0], study_name="one")
    assert [s.study_name for s in optuna.get_all_study_summaries(opened[-1])] == ["one"]


@pytest.mark.slow
def test_a_worker_killed_mid_trial_fails_its_trial_and_the_search_completes(tmp_path, tiny_export):
    """A search and one more worker (resireg-search worker <sweep>, as a SLURM array task runs
    it), each its own process group; kill -9 of the worker's group while it runs a trial: its
    trial becomes FAIL (its process is gone), and the search still ends with n_trials
    finished trials."""
    sweep = tmp_path / "sweep"
    with _started(_eval_search(tiny_export, sweep, 5), tmp_path / "a.log") as search:
        _wait_for(lambda: (sweep / "search.json").is_file(), what="search.json", alive=[search])
        with started([shutil.which("resireg-search") or sys.executable, *(
            [] if shutil.which("resireg-search") else ["-m", "resireg_train.cli.search"]),
            "worker", sweep], stdout=tmp_path / "b.log", threads=1) as worker:  # fmt: skip

            def victim_trial():
                assert worker.poll() is None, (tmp_path / "b.log").read_text()[-3000:]
                return _running_trial_of(sweep, worker.pid)

            victim = _wait_for(victim_trial, what="a trial of the worker")
            worker.kill()  # kill -9 of its process group
        assert search.wait(timeout=600) == 0, (tmp_path / "a.log").read_text()[-3000:]
    dead = _study(sweep).trials[victim.number]
    assert dead.state == TrialState.FAIL and dead.system_attrs.get("resireg:stale") is True
    _check_total(sweep, 5)
    report(sweep)
    table = pd.read_csv(sweep / "optuna_trials.csv").set_index("trial")
    assert "died mid-trial" in table.loc[victim.number, "error"]


def _trial_processes(sweep, group):
    """The live processes of process group ``group`` that have run a trial of the search."""
    study = _study(sweep)
    found = set()
    for trial in study.get_trials() if study is not None else ():
        try:
            pid = int(trial.user_attrs["worker_pid"])
            if os.getpgid(pid) == group:
                found.add(pid)
        except (KeyError, ProcessLookupError):
            continue
    return found


@pytest.mark.slow
def test_sigterm_to_a_search_or_a_worker_ends_the_processes_it_started(tmp_path, tiny_export):
    """``kill <pid>`` (SIGTERM, not to the group) of a `resireg-search worker` and of a search
    that started a second worker (hparams_search.workers=2), each once its workers run
    trials: each exits by the signal at once and leaves none of its processes running
    (``started`` fails the test naming any still running when its block ends); before, the
    worker's job and the search's worker went on, orphaned."""
    sweep = tmp_path / "sweep"
    command = _eval_search(tiny_export, sweep, 500, "hparams_search.workers=2")
    with _started(command, tmp_path / "a.log") as search:
        _wait_for(lambda: (sweep / "search.json").is_file(), what="search.json", alive=[search])
        with started([shutil.which("resireg-search") or sys.executable, *(
            [] if shutil.which("resireg-search") else ["-m", "resireg_train.cli.search"]),
            "worker", sweep], stdout=tmp_path / "b.log", threads=1) as worker:  # fmt: skip
            _wait_for(lambda: _trial_processes(sweep, worker.pid) and _trial_processes(
                sweep, search.pid) - {search.pid}, what="trials of both workers",
                alive=[search, worker])  # fmt: skip
            assert worker.stop(signal.SIGTERM, timeout=30) == -signal.SIGTERM
        assert search.stop(signal.SIGTERM, timeout=30) == -signal.SIGTERM


@pytest.mark.slow
def test_a_killed_search_run_again_reruns_no_finished_trial(tmp_path, tiny_export):
    """kill -9 of a whole 2-worker search (its process group) once a trial has finished, then
    the same command: the finished trials and their run folders are untouched, the trials
    the kill interrupted are FAIL, and the study reaches its total of finished trials."""
    sweep = tmp_path / "sweep"
    command = _eval_search(tiny_export, sweep, 5, "hparams_search.workers=2")
    with _started(command, tmp_path / "first.log") as first:
        _wait_for(lambda: (s := _study(sweep)) is not None and any(
            t.state == TrialState.COMPLETE for t in s.get_trials())
            and s.get_trials(states=(TrialState.RUNNING,)), what="a finished and a running "
            "trial", alive=[first])  # fmt: skip
        first.kill()  # kill -9 of its process group
    before = {t.number: t for t in _study(sweep).get_trials() if t.state == TrialState.COMPLETE}
    interrupted = [t.number for t in _study(sweep).get_trials(states=(TrialState.RUNNING,))]
    assert before and interrupted
    kept = {
        n: Path(t.user_attrs["run_dir"], "results.json").read_bytes() for n, t in before.items()
    }
    run(*command, threads=1)
    study = _check_total(sweep, 5)
    after = {t.number: t for t in study.get_trials()}
    for number, trial in before.items():
        assert after[number].state == TrialState.COMPLETE
        assert (after[number].value, after[number].params) == (trial.value, trial.params)
        assert Path(trial.user_attrs["run_dir"], "results.json").read_bytes() == kept[number]
    assert all(after[n].state == TrialState.FAIL for n in interrupted)


@pytest.mark.slow
def test_two_searches_started_at_once_on_one_folder_cooperate(tmp_path, tiny_export):
    """The same search command twice at once on one sweep folder: both end without error and
    share the study: exactly n_trials finished trials, no parameter set finished twice, each
    run folder once (no raw database error)."""
    sweep = tmp_path / "sweep"
    command = _eval_search(tiny_export, sweep, 4)
    procs = run_side_by_side(command, command, threads=1)
    for proc in procs:
        assert "Error" not in proc.stderr.replace("optimized_metric", ""), proc.stderr[-2000:]
    study = _check_total(sweep, 4)
    assert len({t.user_attrs["worker_pid"] for t in study.get_trials()}) == 2


# ----------------------------------------------------------------------------- report, dashboard
def _made_study(sweep, n):
    """A journal study of ``n`` trials (values from a quadratic) made through Optuna's API in
    the sweep folder, with the search record the report reads."""
    from resireg_train.search.storage import open_storage

    study = optuna.create_study(storage=open_storage(None, sweep), study_name="made",
                                direction="maximize", sampler=optuna.samplers.RandomSampler(0))  # fmt: skip
    for _ in range(n):
        trial = study.ask()
        x = trial.suggest_float("model.optimizer.lr", 0.0, 1.0)
        y = trial.suggest_int("full.n_prototypes", 1, 10)
        for step in range(3):
            trial.report(-((x - 0.3) ** 2) + step * 0.01, step)
        study.tell(trial, -((x - 0.3) ** 2) - 0.001 * y)
    (Path(sweep) / "search.json").write_text(json.dumps({"study_name": "made", "storage": None}))
    return study


def test_the_report_of_a_large_search_is_readable(tmp_path):
    """120 trials: the history's trial axis has integer ticks, at most a dozen; the
    intermediate-values plot has no 120-entry legend; importance labels are short."""
    import matplotlib

    matplotlib.use("Agg")
    from optuna.visualization import matplotlib as ov

    from resireg_train.search.report import readable_axes, write_optuna_report

    warnings.simplefilter("ignore", optuna.exceptions.ExperimentalWarning)
    study = _made_study(tmp_path, 120)
    with matplotlib.rc_context():  # Optuna's plots set the ggplot style for the process
        ax = ov.plot_optimization_history(study)
        readable_axes(ax)
        ticks = [t for t in ax.get_xticks() if ax.get_xlim()[0] <= t <= ax.get_xlim()[1]]
        assert 2 <= len(ticks) <= 13 and all(float(t).is_integer() for t in ticks)
        ax = ov.plot_intermediate_values(study)
        readable_axes(ax)
        assert ax.get_legend() is None
    before = dict(matplotlib.rcParams)
    files, lines = write_optuna_report(tmp_path, [], tmp_path)
    # the report keeps Optuna's style to itself: later figures of the process (the report's
    # heatmaps, a user's own) are drawn with the settings they had
    assert {k: v for k, v in matplotlib.rcParams.items() if before[k] != v} == {}
    best = max(study.get_trials(), key=lambda t: t.value)
    assert any(f"Best trial: {best.number}, value {best.value:.4f}" in line for line in lines)
    for key in ("optuna_history", "optuna_intermediate", "optuna_importance"):
        assert files[key].stat().st_size > 10_000
    assert len(pd.read_csv(files["optuna_csv"])) == 120


@pytest.mark.slow
def test_optuna_dashboard_lists_the_trials_of_a_search(tmp_path):
    """optuna-dashboard <sweep>/optuna.journal on 127.0.0.1: its API (/api/studies,
    /api/studies/<id>) lists the study and every trial with its value."""
    exe = shutil.which("optuna-dashboard")
    if exe is None:
        pytest.skip("optuna-dashboard is not installed (the optuna extra)")
    study = _made_study(tmp_path, 4)
    with socket.socket() as s:
        s.bind(("127.0.0.1", 0))
        port = s.getsockname()[1]
    dashboard = started([exe, "--host", "127.0.0.1", "--port", port, "--storage-class",
                         "JournalFileStorage", tmp_path / "optuna.journal"])  # fmt: skip
    opener = urllib.request.build_opener(urllib.request.ProxyHandler({}))  # no proxy
    base = f"http://127.0.0.1:{port}"

    def get(path):
        with opener.open(base + path, timeout=5) as response:
            return json.loads(response.read())

    def studies():
        try:
            return get("/api/studies")
        except OSError:
            return None

    with dashboard as proc:
        listed = _wait_for(studies, timeout=60, what="optuna-dashboard", alive=[proc])
        assert [s["study_name"] for s in listed["study_summaries"]] == ["made"]
        detail = get(f"/api/studies/{listed['study_summaries'][0]['study_id']}")
        proc.stop(signal.SIGTERM, timeout=30)
    trials = {t["number"]: t for t in detail["trials"]}
    assert sorted(trials) == [0, 1, 2, 3]
    for trial in study.get_trials():
        assert trials[trial.number]["values"][0] == pytest.approx(trial.value)


# ----------------------------------------------------------------------------- scores
@pytest.mark.parametrize("stored", [float("nan"), None, float("inf")])
def test_a_job_scoring_nan_fails_its_trial(stored):
    """A NaN (or ``null`` in results.json) score raises in the job, and a job whose value is
    not finite is told FAIL: the search goes on (up to max_failure_rate)."""
    from hydra.core.utils import JobReturn, JobStatus
    from omegaconf import OmegaConf

    from resireg_train.cli.job import optimized_value
    from resireg_train.search.trials import outcome

    cfg = OmegaConf.create({"optimized_metric": "miou_full"})
    with pytest.raises(ValueError, match=r"optimized_metric='miou_full' is .*not finite"):
        optimized_value(cfg, {"final": {"miou_full": stored}})
    assert optimized_value(cfg, {"final": {"miou_full": 0.25}}) == 0.25
    assert optimized_value(cfg, {"best": {"miou_full": {"value": 0.5, "epoch": 2}}}) == 0.5
    nan = JobReturn(status=JobStatus.COMPLETED, _return_value=float("nan"))
    assert outcome(nan) == (TrialState.FAIL, None)
    raised = JobReturn(status=JobStatus.FAILED, _return_value=ValueError("x"))
    assert outcome(raised) == (TrialState.FAIL, None)
    pruned = JobReturn(status=JobStatus.FAILED, _return_value=optuna.TrialPruned("p"))
    assert outcome(pruned) == (TrialState.PRUNED, None)
    assert outcome(JobReturn(status=JobStatus.COMPLETED, _return_value=0.5)) == (
        TrialState.COMPLETE, 0.5)  # fmt: skip
    assert math.isfinite(0.5)


def test_a_successful_multirun_names_its_sweep_and_the_report_command(tmp_path, tiny_export):
    """A grid multirun whose jobs all complete ends, as a failed one does, with a line naming
    its sweep folder and the resireg-report command (it said nothing before)."""
    sweep = tmp_path / "grid"
    proc = run("resireg-eval", "-m", f"model_path={tiny_export}", "dataset=synthetic",
               "dataset.size=2", "num_workers=0", "batch_size=2", "variants=[full]",
               "full.n_prototypes=3", "full.alpha=2.0,4.0", f"hydra.sweep.dir={sweep}")  # fmt: skip
    assert proc.stderr.strip().splitlines()[-1] == (
        f"resireg-eval: 2 jobs ran, none failed (sweep {sweep}; resireg-report {sweep} lists "
        "every job)"
    )


@pytest.mark.slow
def test_failed_trials_are_recorded_and_the_search_goes_on_up_to_max_failure_rate(
    tmp_path, tiny_export
):
    """A trial whose job fails (5000 prototypes exceed a batch's points) is FAIL with its
    folder's error and the search goes on; when more than max_failure_rate of the finished
    trials failed the search stops with one line saying so (no traceback)."""
    sweep = tmp_path / "mixed"
    run(*_eval_search(tiny_export, sweep, 2, "full.n_prototypes=choice(3,5000)",
                      "hydra.sweeper.enqueue=[{full.n_prototypes:5000},{full.n_prototypes:3}]",
                      "hydra.sweeper.max_failure_rate=0.75"))  # fmt: skip
    trials = _study(sweep).get_trials()
    assert [t.state.name for t in trials] == ["FAIL", "COMPLETE"]
    failed = json.loads(Path(trials[0].user_attrs["run_dir"], "results.json").read_text())
    assert failed["status"] == "failed" and "n_prototypes=5000" in failed["error"]
    report(sweep)
    table = pd.read_csv(sweep / "optuna_trials.csv")
    assert table.loc[0, "job status"] == "failed" and "5000" in table.loc[0, "error"]

    sweep = tmp_path / "bad"
    proc = run(*_eval_search(tiny_export, sweep, 4, "full.n_prototypes=choice(5000)"),
               check=False)  # fmt: skip
    assert proc.returncode != 0 and "Traceback" not in proc.stderr
    assert ("2 of 2 trials failed, more than hydra.sweeper.max_failure_rate=0.5: the search "
            "stops") in proc.stderr  # fmt: skip
    assert [t.state.name for t in _study(sweep).get_trials()] == ["FAIL", "FAIL"]


def test_stale_trials_are_those_of_dead_processes_or_silent_heartbeats(tmp_path):
    """fail_stale_trials on a journal study: a RUNNING trial of another host whose heartbeat is
    older than the grace period is FAIL, one with a recent heartbeat is not; one of this host
    whose process has exited is FAIL at once; with retries, Optuna's RetryHeartbeatStaleTrialCallback
    enqueues the failed trial's parameters again."""
    from resireg_train.search.storage import open_storage
    from resireg_train.search.trials import (
        ATTR_HEARTBEAT,
        ATTR_HOST,
        ATTR_PID,
        counted_trials,
        fail_stale_trials,
    )  # fmt: skip

    study = optuna.create_study(storage=open_storage(None, tmp_path), study_name="s")
    storage = study._storage
    gone = subprocess.Popen([sys.executable, "-c", "pass"])
    gone.wait()
    now = time.time()
    cases = {"silent": ("other-host", 1, now - 500), "beating": ("other-host", 1, now - 5),
             "exited": (socket.gethostname(), gone.pid, now)}  # fmt: skip
    numbers = {}
    for name, (host, pid, beat) in cases.items():
        trial = study.ask({"x": optuna.distributions.FloatDistribution(0, 1)})
        trial.set_user_attr(ATTR_HOST, host)
        trial.set_user_attr(ATTR_PID, pid)
        storage.set_trial_system_attr(trial._trial_id, ATTR_HEARTBEAT, beat)
        numbers[name] = trial.number
    failed = fail_stale_trials(study, grace_period=60, retries=1)
    assert sorted(failed) == sorted([numbers["silent"], numbers["exited"]])
    trials = study.get_trials()
    assert trials[numbers["beating"]].state == TrialState.RUNNING
    assert not counted_trials(trials)  # a dead worker's FAIL does not count towards the total
    waiting = study.get_trials(states=(TrialState.WAITING,))
    assert sorted(t.params["x"] for t in waiting) == sorted(
        trials[numbers[n]].params["x"] for n in ("silent", "exited")
    )


# ----------------------------------------------------------------------------- DDP trials


def _with_tests(env=None):
    """This environment with tests/ importable (helpers/ddp.py: a pruner and a dying rank)."""
    env = dict(os.environ if env is None else env)
    env["PYTHONPATH"] = os.pathsep.join([str(TESTS), env.get("PYTHONPATH", "")])
    return env


def _ddp_search(sweep, strategy, *extra, n_trials=3):
    """A stage-1 search of ``n_trials`` on the smoke experiment, 2 epochs of 2 steps, each
    trial on 2 CPU processes over gloo with ``strategy``; the pruner prunes trial 2 at its
    first report (helpers.ddp.PruneNumber: whatever the scores)."""
    return ("resireg-train", "experiment=smoke", "hparams_search=stage1_optuna",
            f"hparams_search.n_trials={n_trials}", "trainer.max_epochs=2", "data.steps_per_epoch=2",
            "callbacks.resireg_eval.batch_size=3", f"+trainer.strategy={strategy}",
            "trainer.devices=2", "hydra.sweeper.pruner._target_=helpers.ddp.PruneNumber",
            "+hydra.sweeper.pruner.number=2", "~hydra.sweeper.pruner.n_startup_trials",
            "~hydra.sweeper.pruner.n_warmup_steps", f"hydra.sweep.dir={sweep}", *extra)  # fmt: skip


def _processes_of(sweep):
    """The live processes whose command line names ``sweep`` (a trial's ranks do)."""
    import psutil

    found = []
    for proc in psutil.process_iter(["cmdline", "status"]):
        if proc.info["status"] != psutil.STATUS_ZOMBIE and str(sweep) in " ".join(
            proc.info["cmdline"] or ()
        ):
            found.append(proc)
    return found


def _check_ddp_search(sweep, states):
    """The trials' states; COMPLETE ones reported both epochs, the PRUNED one its first only
    (every rank stopped after it: its record has one epoch), folders recording the same."""
    study = _study(sweep, "stage1_optuna")
    trials = study.get_trials()
    assert [t.state.name for t in trials] == states
    records = {t.number: json.loads((Path(t.user_attrs["run_dir"]) / "results.json").read_text())
               for t in trials}  # fmt: skip
    for trial in trials:
        record = records[trial.number]
        if trial.state == TrialState.COMPLETE:
            assert list(trial.intermediate_values) == [0, 1]
            assert record["status"] == "completed" and record["history"][-1]["step"] == 4
            assert record["best"][METRIC]["value"] == pytest.approx(trial.value)
        elif trial.state == TrialState.PRUNED:
            assert list(trial.intermediate_values) == [0]
            assert record["status"] == "pruned" and "pruned by PruneNumber after epoch 0" in (
                record["error"])  # fmt: skip
            assert [row["epoch"] for row in record["history"]] == [0]
            assert record["history"][0]["step"] == 2  # both ranks stopped after epoch 0
    return trials, records


@pytest.mark.slow
def test_a_search_of_ddp_trials_prunes_on_every_rank_and_survives_a_dead_rank(tmp_path):
    """trainer=ddp (Lightning's re-launching strategy) under a search, 2 ranks per trial: the
    worker starts each trial's ranks (the search's command line is never re-launched). Trial
    1's rank 1 dies mid-epoch (os._exit): the trial is FAIL with one line naming rank 1, the
    search goes on; trial 2 is pruned after epoch 0 on both ranks; trial 0 completes; trial
    3's rank 0 dies before the ranks meet, so its rank 1 cannot reach the master: FAIL naming
    rank 0, rank 1 stopped (not left waiting for the rendezvous). No rank of any trial is
    left running."""
    sweep = tmp_path / "sweep"
    die = ("+callbacks.die._target_=helpers.ddp.DieAt", "+callbacks.die.rank=1",
           "+callbacks.die.trial=1", "+callbacks.die.number=${hparams_search.trial}",
           "+callbacks.lost._target_=helpers.ddp.DieAt", "+callbacks.lost.rank=0",
           "+callbacks.lost.batch=null", "+callbacks.lost.trial=3",
           "+callbacks.lost.number=${hparams_search.trial}")  # fmt: skip
    proc = run(*_ddp_search(sweep, "ddp", *die, n_trials=4), env=_with_tests(), threads=1,
               timeout=1800)  # fmt: skip
    assert not _processes_of(sweep)
    trials, records = _check_ddp_search(sweep, ["COMPLETE", "FAIL", "PRUNED", "FAIL"])
    for number, rank in ((1, 1), (3, 0)):
        error = records[number]["error"]
        assert records[number]["status"] == "failed" and "\n" not in error
        assert re.search(rf"TrialRankFailed: trial {number}: rank {rank} \(PID \d+\) of its DDP "
                         r"run exited with code 3; the other ranks were stopped", error), error  # fmt: skip
        # the search's last lines: one per failed job, naming the rank
        lines = [line for line in proc.stderr.splitlines() if line.startswith(f"  job {number} (")]
        assert len(lines) == 1 and f"rank {rank} (PID" in lines[0], proc.stderr[-3000:]
    assert "2 of 4 jobs failed" in proc.stderr


@pytest.mark.slow
def test_a_search_of_ddp_spawn_trials_prunes_on_every_rank(tmp_path):
    """The same search with ddp_spawn (Lightning spawns the ranks in the trial's job): the
    pruned trial is PRUNED (rank 0's decision reaches the spawning process through the
    trial), the others complete; nothing is left running."""
    sweep = tmp_path / "sweep"
    run(*_ddp_search(sweep, "ddp_spawn"), env=_with_tests(), threads=1, timeout=1500)
    assert not _processes_of(sweep)
    _check_ddp_search(sweep, ["COMPLETE", "COMPLETE", "PRUNED"])


def test_a_worker_whose_trainer_differs_from_the_study_is_refused(tmp_path):
    """A search's first process notes its trainer in the study; a worker started on the same
    study with another trainer setting is refused in one line naming the key and both values,
    before it asks a trial (no trial asked: n_trials=0 runs none)."""
    sweep = tmp_path / "sweep"
    run("resireg-train", "experiment=smoke", "hparams_search=stage1_optuna",
        "hparams_search.n_trials=0", f"hydra.sweep.dir={sweep}", threads=1)  # fmt: skip
    proc = subprocess.run(
        [shutil.which("resireg-search") or sys.executable,
         *([] if shutil.which("resireg-search") else ["-m", "resireg_train.cli.search"]),
         "worker", str(sweep), "trainer.max_epochs=3", "trainer.devices=2"],
        capture_output=True, text=True, timeout=300,
        env={**os.environ, "HF_HUB_OFFLINE": "1", "OMP_NUM_THREADS": "1"},
    )  # fmt: skip
    assert proc.returncode != 0 and "Traceback" not in proc.stderr
    refusal = [line for line in proc.stderr.splitlines() if "differs from the one study" in line]
    assert refusal == [
        "this worker's trainer differs from the one study 'stage1_optuna' trains its trials "
        "with: trainer.devices=2 (the study's: 1); trainer.max_epochs=3 (the study's: 6); every "
        "worker of a search trains alike: start it with the search's trainer settings, or start "
        "a new search (another hydra.sweep.dir or study)"
    ], proc.stderr
    assert _study(sweep, "stage1_optuna").get_trials() == []


def test_a_trial_launcher_that_is_no_program_is_refused_before_the_first_trial(tmp_path):
    """RESIREG_SEARCH_TRIAL_LAUNCHER naming no program on PATH, or no command line at all: the
    search refuses in one line naming the variable, before any trial or study is made."""
    for launcher, why in (("no-such-srun --nodes=2", "no program 'no-such-srun' on PATH"),
                          ("srun 'unclosed", "not a command line")):  # fmt: skip
        sweep = tmp_path / launcher.split()[0]
        env = _with_tests({**os.environ, "RESIREG_SEARCH_TRIAL_LAUNCHER": launcher})
        proc = run(*_ddp_search(sweep, "ddp"), check=False, env=env, threads=1, timeout=300)
        assert proc.returncode != 0 and "Traceback" not in proc.stderr, proc.stderr
        refusal = [x for x in proc.stderr.splitlines() if "RESIREG_SEARCH_TRIAL_LAUNCHER" in x]
        assert len(refusal) == 1 and why in refusal[0], proc.stderr
        assert "refused before the first trial" in refusal[0]
        assert not list(sweep.rglob("results.json"))  # no trial ran


@pytest.mark.slow
def test_a_search_of_trials_on_two_nodes_through_a_launcher(tmp_path):
    """trainer.num_nodes=2 under a search: refused before the first trial without a launcher;
    with one (RESIREG_SEARCH_TRIAL_LAUNCHER: here helpers/fake_srun.py, which starts each trial's 2
    tasks with SLURM's variables as srun starts one task per node) each trial runs on its 2
    "nodes" (Lightning's SLURM environment), trial 1 is pruned on both, trial 0 completes."""
    sweep = tmp_path / "sweep"
    search = [*_ddp_search(sweep, "ddp"), "trainer.devices=1", "+trainer.num_nodes=2",
              "hparams_search.n_trials=2", "+hydra.sweeper.pruner.number=1"]  # fmt: skip
    search = [a for a in search if a not in ("trainer.devices=2", "+hydra.sweeper.pruner.number=2",
                                             "hparams_search.n_trials=3")]  # fmt: skip
    refused = run(*search, check=False, env=_with_tests(), threads=1, timeout=300)
    assert refused.returncode != 0 and "Traceback" not in refused.stderr
    assert ("refused before the first trial: trainer.num_nodes=2: a trial on several nodes "
            "needs a launcher") in refused.stderr  # fmt: skip
    launcher = f"{sys.executable} {TESTS / 'helpers' / 'fake_srun.py'} 2"
    env = _with_tests({**os.environ, "RESIREG_SEARCH_TRIAL_LAUNCHER": launcher})
    run(*search, env=env, threads=1, timeout=1500)
    assert not _processes_of(sweep)
    trials, records = _check_ddp_search(sweep, ["COMPLETE", "PRUNED"])
    for record in records.values():
        assert record["history"][0]["step"] == 2  # 2 steps per epoch on each node
