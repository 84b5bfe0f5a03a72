"""One tracker for every run: a real `mlflow server` (SQLite backend, 127.0.0.1) receives a
training run, an evaluation (two jobs of a multirun, grouped under one parent) and a map, read
back with MlflowClient; TensorBoard and CSV record an evaluation; W&B (offline) a map."""

from __future__ import annotations

import csv
import json
from pathlib import Path

import pytest

from _run import evaluate_export, run
from resireg_train.runs.trackers import mlflow_key, run_metrics

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

    track = ["logger=mlflow", f"logger.mlflow.tracking_uri={uri}"]
    train = tmp_path / "train"
    evals = tmp_path / "evals"
    mapped = tmp_path / "map"
    run("resireg-train", "experiment=smoke", "trainer.max_epochs=1", "data.steps_per_epoch=2",
        f"hydra.run.dir={train}", *track, threads=1)  # fmt: skip
    run("resireg-eval", "-m", f"model_path={tiny_export}", "dataset=synthetic", "dataset.size=8",
        "num_workers=0", "variants=[bb,full]", "full.n_prototypes=4,6", *track,
        f"hydra.sweep.dir={evals}", threads=1)  # fmt: skip
    run("resireg-map", f"model_path={tiny_export}", "device=cpu", *_room_bag(tmp_path),
        "configuration=bb", "window=2", f"hydra.run.dir={mapped}", *track, threads=1)  # fmt: skip

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
    final = evaluate_export(tiny_export, out, "logger=[tensorboard,csv]",
                            "dataset.size=6", "variants=[bb,full]")  # fmt: skip
    events = EventAccumulator(str(out / "tensorboard"))
    events.Reload()
    scalars = {tag: events.Scalars(tag)[0].value for tag in events.Tags()["scalars"]}
    finite = {k: v for k, v in final.items() if v is not None}
    assert scalars == pytest.approx(finite, rel=1e-6)
    with open(out / "metrics.csv", newline="") as f:
        (row,) = list(csv.DictReader(f))
    assert {k: float(v) for k, v in row.items()} == pytest.approx(finite)
