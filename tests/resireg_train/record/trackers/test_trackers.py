"""One tracker for every run: a real `mlflow server` (SQLite backend, 127.0.0.1) receives a
training run, an evaluation (two jobs of a multirun, grouped under one parent) and a map, read
back with MlflowClient; TensorBoard and CSV record an evaluation; W&B (offline) a map."""

from __future__ import annotations

import csv
import json
from pathlib import Path

import pytest

from helpers.run import evaluate_export, run
from resireg_train.record.trackers.base import mlflow_key, run_metrics

pytest.importorskip("mlflow")


def _room_bag(tmp_path):
    from resireg_train.data.room_bag import TOPICS, room_frames, write_bag

    bag = write_bag(tmp_path / "room", room_frames(4))
    return [f"source.path={bag}", "source=rosbag", f"source.colour_topic={TOPICS['colour']}",
            f"source.depth_topic={TOPICS['depth']}",
            f"source.camera_info_topic={TOPICS['info']}"]  # fmt: skip


def _finite(record):
    return {mlflow_key(k): v for k, v in run_metrics(record).items()}


@pytest.mark.slow
def test_mlflow_server_gets_train_eval_multirun_and_map(tmp_path, tiny_export, mlflow_server):
    uri = mlflow_server.uri
    from mlflow import MlflowClient

    track = ["tracker=mlflow", f"tracker.mlflow.tracking_uri={uri}"]
    train = tmp_path / "train"
    evals = tmp_path / "evals"
    mapped = tmp_path / "map"
    run("resireg-train", "experiment=smoke", "trainer.max_epochs=1", "data.steps_per_epoch=2",
        f"hydra.run.dir={train}", *track, threads=1)  # fmt: skip
    run("resireg-eval", "-m", f"model_path={tiny_export}", "dataset=synthetic", "dataset.size=8",
        "num_workers=0", "variants=[bb,full]", "full.n_prototypes=4,6", *track,
        f"hydra.sweep.dir={evals}", threads=1)  # fmt: skip
    run("resireg-map", f"model_path={tiny_export}", "device=cpu", *_room_bag(tmp_path),
        "variant=bb", "window=2", f"hydra.run.dir={mapped}", *track, threads=1)  # fmt: skip

    client = MlflowClient(tracking_uri=uri)
    experiment = client.get_experiment_by_name("resireg")
    runs = {r.data.tags.get("resireg.run_dir"): r for r in client.search_runs(
        [experiment.experiment_id], max_results=100)}  # fmt: skip
    folders = [train, *sorted(p for p in evals.iterdir() if (p / "results.json").is_file()), mapped]
    assert len(folders) == 4
    for folder in folders:
        record = json.loads((folder / "results.json").read_text())
        tracked = runs[str(folder.resolve())]
        assert tracked.info.status == "FINISHED"
        assert record["tracking"]["mlflow_run_id"] == tracked.info.run_id
        expected = _finite(record)
        assert expected and {k: tracked.data.metrics[k] for k in expected} == pytest.approx(
            expected
        )
        prov = record["provenance"]
        assert tracked.data.tags["provenance.run_id"] == prov["run_id"]
        assert tracked.data.tags["provenance.code.version"] == prov["code"]["version"]
        artifacts = {a.path for a in client.list_artifacts(tracked.info.run_id)}
        assert "results.json" in artifacts
    # the training run carries its export with the model card
    trained = runs[str(train.resolve())].info.run_id
    exported = {a.path for a in client.list_artifacts(trained, "export")}
    assert {"export/README.md", "export/config.json", "export/model.safetensors"} <= exported
    # the training run is the one Lightning logged its curves to (one run, steps > 1)
    history = client.get_metric_history(runs[str(train.resolve())].info.run_id, "train/loss_step")
    assert len(history) == 2
    # the two evaluation jobs are children of one parent run named after the sweep
    parents = {runs[str(f.resolve())].data.tags["mlflow.parentRunId"] for f in folders[1:3]}
    assert len(parents) == 1
    (parent,) = parents
    assert client.get_run(parent).data.tags["resireg.sweep"] == str(evals)
    job = runs[str(folders[1].resolve())]
    assert job.data.params["full.n_prototypes"] in ("4", "6")
    assert "per_class_iou.json" in {a.path for a in client.list_artifacts(job.info.run_id)}
    table = json.loads(Path(client.download_artifacts(job.info.run_id, "per_class_iou.json",
                                                      str(tmp_path / "dl"))).read_text())  # fmt: skip
    record = json.loads((folders[1] / "results.json").read_text())
    rows = dict(zip(table["columns"], zip(*table["data"], strict=True), strict=True))
    for variant, ious in record["per_class_iou"].items():
        got = dict(zip(rows["class"], rows[variant], strict=True))
        assert got == pytest.approx({c: v for c, v in ious.items()}, nan_ok=True)
    assert runs[str(mapped.resolve())].data.metrics["map/voxels"] == json.loads(
        (mapped / "results.json").read_text())["map"]["voxels"]  # fmt: skip


def test_eval_tensorboard_and_csv_record_the_final_metrics(tmp_path, tiny_export):
    from tensorboard.backend.event_processing.event_accumulator import EventAccumulator

    out = tmp_path / "eval"
    final = evaluate_export(tiny_export, out, "tracker=[tensorboard,csv]",
                            "dataset.size=6", "variants=[bb,full]")  # fmt: skip
    events = EventAccumulator(str(out / "tensorboard"))
    events.Reload()
    scalars = {tag: events.Scalars(tag)[0].value for tag in events.Tags()["scalars"]}
    finite = {k: v for k, v in final.items() if v is not None}
    assert scalars == pytest.approx(finite, rel=1e-6)
    with open(out / "metrics.csv", newline="") as f:
        (row,) = list(csv.DictReader(f))
    assert {k: float(v) for k, v in row.items()} == pytest.approx(finite)


def _digests(folder):
    """``{path: sha256}`` of every file under ``folder``."""
    import hashlib

    return {p.relative_to(folder): hashlib.sha256(p.read_bytes()).hexdigest()
            for p in sorted(folder.rglob("*")) if p.is_file()}  # fmt: skip


#: MLflow's telemetry session: its import starts a thread that sets, and without a network
#: later removes, this variable whenever it gets to it, whatever runs meanwhile.
_TELEMETRY = "_MLFLOW_TELEMETRY_SESSION_ID"


def _process(mlflow, setup):
    """What a run may leave in this process, read directly: the environment, MLflow's set
    tracking URI and active run, W&B's singleton (its service connection)."""
    import os
    import sys

    active = mlflow.active_run()
    return ({k: v for k, v in os.environ.items() if k != _TELEMETRY},
            sys.modules["mlflow.tracking._tracking_service.utils"]._tracking_uri,
            active.info.run_id if active else None, setup._singleton)  # fmt: skip


@pytest.mark.slow  # (an MLflow server's start)
def test_eval_in_process_leaves_no_credential_uri_run_or_service_behind(
    tmp_path, tiny_export, mlflow_server, monkeypatch
):
    """Issue 51, item 11: resireg-eval's entry point called twice in this process, with MLflow
    on a server whose URI holds a user and password, then W&B offline: after each call the
    environment (no MLFLOW_TRACKING_USERNAME / _PASSWORD), MLflow's tracking URI and active run
    (the caller's own) and W&B's service (none) are as before; each run was recorded; the
    export and the caller's store are unchanged."""
    import mlflow
    from wandb.sdk import wandb_setup

    from helpers.run import evaluate

    monkeypatch.setenv("WANDB_MODE", "offline")
    for key in ("MLFLOW_TRACKING_USERNAME", "MLFLOW_TRACKING_PASSWORD", "MLFLOW_TRACKING_URI"):
        monkeypatch.delenv(key, raising=False)
    mine = f"sqlite:///{tmp_path / 'mine' / 'mlflow.db'}"
    (tmp_path / "mine").mkdir()
    mlflow.set_tracking_uri(mine)
    caller = mlflow.start_run()  # the caller's own run, active across the calls
    try:
        before = _process(mlflow, wandb_setup)
        assert before[1:] == (mine, caller.info.run_id, None)
        export = _digests(tiny_export)
        url = mlflow_server.uri.replace("http://", "http://someone:s3cret@")
        runs = {"mlflow": ["tracker=mlflow", f"tracker.mlflow.tracking_uri={url}"],
                "wandb": ["tracker=wandb"]}  # fmt: skip
        for name, tracker in runs.items():
            out = tmp_path / name
            record = evaluate(f"model_path={tiny_export}", "dataset=synthetic", "dataset.size=4",
                              "num_workers=0", "full.n_prototypes=4", f"paths.output_dir={out}",
                              *tracker)  # fmt: skip
            assert record["status"] == "completed"
            assert _process(mlflow, wandb_setup) == before, name
        assert "MLFLOW_TRACKING_PASSWORD" not in __import__("os").environ
        from mlflow import MlflowClient

        tracked = json.loads((tmp_path / "mlflow" / "results.json").read_text())["tracking"]
        server_run = MlflowClient(mlflow_server.uri).get_run(tracked["mlflow_run_id"])
        assert server_run.info.status == "FINISHED"
        assert list((tmp_path / "wandb" / "wandb").glob("offline-run-*/run-*.wandb"))
        assert _digests(tiny_export) == export
        assert mlflow.active_run().info.run_id == caller.info.run_id
    finally:
        mlflow.end_run()


@pytest.mark.slow
def test_a_sqlite_store_keeps_the_artifacts_next_to_its_database(tmp_path, tiny_export,
                                                                  monkeypatch):  # fmt: skip
    """Issue 51, item 13: with tracker.mlflow.tracking_uri=sqlite:///<db> and no artifact
    location, the run's files go to mlartifacts/ next to the database, never to ./mlruns of
    the folder the call started from (which stays empty)."""
    from mlflow import MlflowClient

    from helpers.run import evaluate

    here = tmp_path / "started_here"
    here.mkdir()
    monkeypatch.chdir(here)
    db = tmp_path / "store" / "mlflow.db"
    out = tmp_path / "eval"
    record = evaluate(f"model_path={tiny_export}", "dataset=synthetic", "dataset.size=4",
                      "num_workers=0", "full.n_prototypes=4", f"paths.output_dir={out}",
                      "tracker=mlflow", f"tracker.mlflow.tracking_uri=sqlite:///{db}")  # fmt: skip
    assert record["status"] == "completed"
    assert list(here.iterdir()) == []
    tracked = json.loads((out / "results.json").read_text())["tracking"]
    run = MlflowClient(f"sqlite:///{db}").get_run(tracked["mlflow_run_id"])
    artifacts = db.parent / "mlartifacts"
    assert run.info.artifact_uri.startswith(artifacts.as_uri() + "/")
    stored = Path(run.info.artifact_uri.removeprefix("file://"))
    assert stored.is_relative_to(artifacts)
    assert (stored / "per_class_iou.json").is_file()
    logged = json.loads((stored / "results.json").read_text())
    assert logged["final"] == record["final"]


def test_an_mlflow_store_that_cannot_be_made_is_refused_in_one_line(tmp_path, tiny_export):
    """Issue 51, item 14: resireg-eval with tracker=mlflow on a SQLite store whose folder cannot
    be made (under /proc, under a regular file) stops before any work in the one line the
    closed-port case gives, naming the tracker, the store and why; the export and the file in
    the way are unchanged."""
    from helpers.run import run_side_by_side

    blocker = tmp_path / "afile"
    blocker.write_text("not a folder")
    stores = {"proc": ("/proc/x/mlflow.db", "cannot write in /proc/x: No such file or directory"),
              "file": (f"{blocker}/mlflow.db", f"{blocker} is a file, not a folder")}  # fmt: skip
    before = _digests(tmp_path), _digests(tiny_export)
    procs = run_side_by_side(*(
        ("resireg-eval", f"model_path={tiny_export}", "dataset=synthetic", "tracker=mlflow",
         f"tracker.mlflow.tracking_uri=sqlite:///{db}", f"hydra.run.dir={tmp_path / 'runs' / n}")
        for n, (db, _) in stores.items()
    ), check=False)  # fmt: skip
    for (name, (db, why)), proc in zip(stores.items(), procs, strict=True):
        line = (f"resireg_train.record.trackers.base.TrackerUnreachable: tracker.mlflow: cannot reach "
                f"sqlite:///{db} ({why}); fix its address, or set tracker.mlflow.unreachable=warn "
                "to run with local records only")  # fmt: skip
        assert proc.returncode == 1, proc.stderr[-2000:]
        assert "Traceback" not in proc.stdout + proc.stderr, name
        assert line in proc.stderr.splitlines(), (name, proc.stderr[-2000:])
        record = json.loads((tmp_path / "runs" / name / "results.json").read_text())
        assert record["status"] == "failed" and record["error"] == line
        assert "final" not in record  # stopped before any work
    after = {p: d for p, d in _digests(tmp_path).items() if p.parts[0] != "runs"}
    assert (after, _digests(tiny_export)) == before


def test_the_artifact_location_of_each_kind_of_store(tmp_path, monkeypatch):
    """Issue 51, item 13, the rule itself: given, it is kept; a SQLite store's is mlartifacts/
    next to the database (a relative database path: from the current folder, as SQLite reads
    it); a server chooses its own; another database store needs one given, refused naming the
    key with its password masked."""
    from resireg.errors import ConfigError
    from resireg_train.record.trackers.mlflow import artifact_location

    monkeypatch.chdir(tmp_path)
    assert artifact_location("sqlite:///db/m.db", "s3://bucket/x") == "s3://bucket/x"
    assert artifact_location("sqlite:///db/m.db") == (tmp_path / "db" / "mlartifacts").as_uri()
    assert artifact_location(f"sqlite:///{tmp_path}/a/m.db") == (
        tmp_path / "a" / "mlartifacts").as_uri()  # fmt: skip
    assert artifact_location("http://user:pw@host:5000") is None
    with pytest.raises(ConfigError, match=r"^tracker\.mlflow\.artifact_location: required with the "
                       r"database store 'postgresql://u:\*\*\*@db/mlflow'") as err:  # fmt: skip
        artifact_location("postgresql://u:pw@db/mlflow")
    assert "pw" not in str(err.value).replace("postgresql", "")
