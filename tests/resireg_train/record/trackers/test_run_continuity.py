"""Runs that stay one run (issue 47 item 7): a resumed training continues its MLflow run (a
local SQLite store) and its W&B run (offline) under the recorded id, its curves going on at
the resumed step; a run folder written on another host is listed as `running` while its
heartbeat is recent and as `died` once it is stale."""

from __future__ import annotations

import contextlib
import datetime as dt
import io
import json
import socket
import time

import lightning as L
import pytest
from hydra import compose, initialize_config_dir

from resireg_train.cli.train import train
from resireg_train.config.paths import CONFIG_DIR
from resireg_train.record.heartbeat import Heartbeat, heartbeat_stale
from resireg_train.record.run_record import RunRecord
from resireg_train.runs.index import scan

STEPS = 2  # steps per epoch


class _CrashAt(L.Callback):
    """A crash at the start of epoch ``epoch`` (the checkpoint of the epoch before is kept)."""

    def __init__(self, epoch):
        self.epoch = epoch

    def on_train_epoch_start(self, trainer, pl_module):
        if trainer.current_epoch == self.epoch:
            raise RuntimeError("simulated crash")


def _cfg(out, *extra):
    with initialize_config_dir(str(CONFIG_DIR), version_base="1.3"):
        return compose("train", overrides=["experiment=smoke", f"paths.output_dir={out}",
                                           "trainer.max_epochs=2", f"data.steps_per_epoch={STEPS}",
                                           "~callbacks.progress_bar", "~callbacks.resireg_eval",
                                           "export=false", *extra])  # fmt: skip


def _crash_then_resume(out, *extra):
    """Epoch 0, a crash at epoch 1's start, then ``ckpt_path=last``: the record before the
    resume and after it."""
    with pytest.raises(RuntimeError, match="simulated crash"):
        train(_cfg(out, *extra), callbacks=[_CrashAt(1)])
    crashed = RunRecord.read(out)
    assert crashed["status"] == "failed" and crashed["global_step"] == STEPS
    resumed = train(_cfg(out, *extra, "ckpt_path=last"))
    assert resumed["status"] == "completed" and resumed["global_step"] == 2 * STEPS
    return crashed, resumed


@pytest.mark.slow
def test_a_resumed_training_continues_its_mlflow_run(tmp_path):
    from mlflow import MlflowClient

    uri = f"sqlite:///{tmp_path / 'mlflow.db'}"
    crashed, resumed = _crash_then_resume(tmp_path / "run", "tracker=mlflow",
                                          f"tracker.mlflow.tracking_uri={uri}")  # fmt: skip
    run_id = crashed["tracking"]["mlflow_run_id"]
    assert resumed["tracking"]["mlflow_run_id"] == run_id  # the same run, not a new one
    client = MlflowClient(tracking_uri=uri)
    (experiment,) = [e for e in client.search_experiments() if e.name == "resireg"]
    runs = client.search_runs([experiment.experiment_id])
    assert [r.info.run_id for r in runs] == [run_id]  # one MLflow run for the whole training
    assert client.get_run(run_id).info.status == "FINISHED"  # ended with the resumed job
    # The step curve: epoch 0's steps, then the resumed ones, each step once, in order.
    steps = [m.step for m in client.get_metric_history(run_id, "train/loss_step")]
    assert sorted(steps) == list(range(2 * STEPS)), steps
    # ... equal to what metrics.csv (the run's own record) holds, value for value
    import csv

    with open(tmp_path / "run" / "metrics.csv", newline="") as f:
        rows = {int(r["step"]): float(r["train/loss_step"]) for r in csv.DictReader(f)
                if r.get("train/loss_step")}  # fmt: skip
    logged = {m.step: m.value for m in client.get_metric_history(run_id, "train/loss_step")}
    assert logged == pytest.approx(rows)
    epochs = sorted(m.step for m in client.get_metric_history(run_id, "train/loss_epoch"))
    assert len(epochs) == 2 and epochs[1] > epochs[0] >= STEPS - 1


@pytest.mark.slow
def test_a_resumed_training_continues_its_wandb_run_offline(tmp_path, monkeypatch):
    pytest.importorskip("wandb")
    from helpers.wandb_log import records

    for key, value in {"WANDB_MODE": "offline", "WANDB_SILENT": "true",
                       "WANDB_CONFIG_DIR": str(tmp_path / "wandb_config"),
                       "WANDB_CACHE_DIR": str(tmp_path)}.items():  # fmt: skip
        monkeypatch.setenv(key, value)
    out = tmp_path / "run"
    crashed, resumed = _crash_then_resume(out, "tracker=wandb")
    run_id = crashed["tracking"]["wandb_run_id"]
    assert resumed["tracking"]["wandb_run_id"] == run_id
    import wandb

    wandb.teardown()  # this process's W&B service writes the offline files out, as at exit
    # Two offline segments (one per process life), one W&B run id: `wandb sync` uploads both
    # into one run.
    folders = sorted(out.glob("wandb/offline-run-*"))
    assert len(folders) == 2 and all(f.name.endswith(f"-{run_id}") for f in folders), folders
    segments = []
    for folder in folders:
        (file,) = folder.glob(f"run-{run_id}.wandb")
        ids, steps = set(), []
        for record in records(file):
            kind = record.WhichOneof("record_type")
            if kind == "run":
                ids.add(record.run.run_id)
            elif kind == "history":
                items = {i.key or "/".join(i.nested_key): json.loads(i.value_json)
                         for i in record.history.item}  # fmt: skip
                if "train/loss_step" in items:
                    steps.append(items["trainer/global_step"])
        assert ids == {run_id}
        segments.append(steps)
    first, second = segments  # Lightning's step axis (trainer/global_step) goes on
    assert first == list(range(STEPS)) and second == list(range(STEPS, 2 * STEPS))


def _remote_run(root, name, beat_age_s, stale_after=300.0):
    """A record still `running`, written on another host, whose heartbeat is this old."""
    folder = root / name
    folder.mkdir(parents=True)
    beat = dt.datetime.now(dt.timezone.utc) - dt.timedelta(seconds=beat_age_s)
    record = {"name": name, "status": "running",
              "provenance": {"run_id": name, "cli": "resireg-train",
                             "machine": {"host": "node-17.cluster", "pid": 1}},
              "heartbeat": {"time": beat.isoformat(), "host": "node-17.cluster",
                            "interval": 30.0, "stale_after": stale_after}}  # fmt: skip
    (folder / "results.json").write_text(json.dumps(record))
    return folder


def test_a_run_of_another_host_is_running_while_its_heartbeat_is_recent(tmp_path):
    from resireg_train.cli.runs import main

    root = tmp_path / "outputs"
    _remote_run(root, "fresh", beat_age_s=20)
    _remote_run(root, "stale", beat_age_s=6 * 60)  # past the default 5 minutes
    _remote_run(root, "own_limit", beat_age_s=90, stale_after=60)  # its job's own setting
    statuses = {r.run_id: r.status for r in scan([root])}
    assert statuses == {"fresh": "running", "stale": "died", "own_limit": "died"}
    out = io.StringIO()
    with contextlib.redirect_stdout(out):
        main(["ls", str(root), "--format", "json", "--columns", "run_id,status"])
    assert {r["run_id"]: r["status"] for r in json.loads(out.getvalue())} == statuses
    # the threshold: the record's, else conf/provenance/default.yaml's heartbeat_stale
    now = dt.datetime.now(dt.timezone.utc)
    beat = {"heartbeat": {"time": (now - dt.timedelta(seconds=100)).isoformat()}}
    assert heartbeat_stale(beat, 99.0, now) is True and heartbeat_stale(beat, 101.0, now) is False
    assert heartbeat_stale({}, 1.0) is None  # no heartbeat recorded: cannot tell


def test_the_heartbeat_thread_refreshes_the_record_and_stops_with_it(tmp_path):
    record = RunRecord(tmp_path)
    record.update(status="running")
    beat = Heartbeat(record, interval=0.05, stale_after=1.0).start()
    first = None
    deadline = time.monotonic() + 10
    times = set()
    while time.monotonic() < deadline and len(times) < 3:
        stamp = (RunRecord.read(tmp_path).get("heartbeat") or {}).get("time")
        if stamp:
            first = first or stamp
            times.add(stamp)
        record.update(epoch=len(times))  # the job's own writes go on beside the thread's
        time.sleep(0.02)
    beat.stop()
    assert len(times) >= 3  # refreshed, each time a newer stamp
    written = RunRecord.read(tmp_path)
    assert written["status"] == "running" and written["heartbeat"]["host"] == socket.gethostname()
    assert written["epoch"] >= 2  # no write of the job lost to a heartbeat's
    last = written["heartbeat"]["time"]
    assert dt.datetime.fromisoformat(last) >= dt.datetime.fromisoformat(first)
    time.sleep(0.2)
    assert RunRecord.read(tmp_path)["heartbeat"]["time"] == last  # stopped: no more beats


def test_a_real_job_records_its_heartbeat_settings(tmp_path, tiny_export):
    """A run's record carries its heartbeat and the two config keys it was started with."""
    from helpers.run import evaluate

    out = tmp_path / "eval"
    results = evaluate(f"model_path={tiny_export}", "dataset=synthetic", "dataset.size=2",
                       "num_workers=0", "variants=[bb]", "provenance.heartbeat_interval=7",
                       "provenance.heartbeat_stale=70", f"paths.output_dir={out}")  # fmt: skip
    beat = results["heartbeat"]
    assert beat["interval"] == 7 and beat["stale_after"] == 70
    assert beat["host"] == socket.gethostname()
    started = dt.datetime.fromisoformat(results["provenance"]["time"]["start"])
    assert abs((dt.datetime.fromisoformat(beat["time"]) - started).total_seconds()) < 60


def test_a_training_run_written_before_the_record_split_resumes(tmp_path):
    """A run folder whose .hydra/config.yaml the code before issue 52's move wrote (commit
    439e7f0; tests/fixtures/runs/before-record-split, composed there from `experiment=smoke
    logger=wandb hparams_search=stage1_optuna`) names resireg_train.runs.loggers.wandb_logger
    and resireg_train.sweeps.pruning.OptunaPruning: the resume check finds no difference with
    today's composition of the same command (config.moves.MOVED_TARGETS maps each old path to
    the one today's conf/ files name), and every path the table maps to imports."""
    import shutil

    import yaml
    from hydra.utils import get_object

    from resireg_train.checks.resume import check_resume
    from resireg_train.config.moves import (
        MOVED_TARGETS,
        current_overrides,
        current_spelling,
        current_targets,
    )

    fixture = CONFIG_DIR.parent / "tests" / "fixtures" / "runs" / "before-record-split"
    folder = tmp_path / "run"
    shutil.copytree(fixture, folder)
    overrides = yaml.safe_load((folder / ".hydra" / "overrides.yaml").read_text())
    assert "logger=wandb" in overrides  # the group's old spelling, read as tracker= today
    overrides = current_overrides("train", overrides)
    with initialize_config_dir(str(CONFIG_DIR), version_base="1.3"):
        today = compose("train", overrides=overrides)
    check_resume(folder, today)  # a ConfigError naming the keys that differ otherwise

    stored = yaml.safe_load((folder / ".hydra" / "config.yaml").read_text())
    assert stored["logger"]["wandb"]["_target_"] == "resireg_train.runs.loggers.wandb_logger"
    moved = current_spelling(current_targets(stored))
    wandb = yaml.safe_load((CONFIG_DIR / "tracker" / "wandb.yaml").read_text())
    search = yaml.safe_load((CONFIG_DIR / "hparams_search" / "stage1_optuna.yaml").read_text())
    assert moved["tracker"]["wandb"]["_target_"] == wandb["wandb"]["_target_"]
    assert (moved["callbacks"]["optuna_pruning"]["_target_"]
            == search["callbacks"]["optuna_pruning"]["_target_"])  # fmt: skip
    for new in set(MOVED_TARGETS.values()):
        assert callable(get_object(new)), new
