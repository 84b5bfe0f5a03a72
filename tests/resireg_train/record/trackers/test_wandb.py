"""tracker=wandb offline: one W&B run per job of a multirun, each finished, with the job's
config and results.json's final metrics, read back from the offline run files."""

from __future__ import annotations

import json
import os

import pytest

from helpers.run import run
from helpers.wandb_log import records

pytest.importorskip("wandb")

def _read_run(path):
    """``(display name, group, config, summary, exit code)`` of one offline run."""
    name = group = exit_code = None
    config, summary = {}, {}
    for record in records(path):
        kind = record.WhichOneof("record_type")
        if kind == "run":
            name, group = record.run.display_name, record.run.run_group
            config.update({i.key: json.loads(i.value_json) for i in record.run.config.update})
        elif kind == "config":
            config.update({i.key: json.loads(i.value_json) for i in record.config.update})
        elif kind == "summary":
            summary.update({i.key: json.loads(i.value_json) for i in record.summary.update})
        elif kind == "exit":
            exit_code = record.exit.exit_code
    return name, group, config, summary, exit_code


@pytest.mark.slow
def test_offline_runs_one_per_job_with_config_and_final_metrics(tmp_path):
    env = {**os.environ, "WANDB_MODE": "offline", "WANDB_SILENT": "true",
           "WANDB_CONFIG_DIR": str(tmp_path / "wandb_config"), "WANDB_CACHE_DIR": str(tmp_path)}  # fmt: skip
    run("resireg-train", "-m", "experiment=smoke", "tracker=wandb", "trainer.max_epochs=1",
        "data.steps_per_epoch=2", "~callbacks.progress_bar", "export=false",
        "model.optimizer.lr=1e-3,2e-3", f"paths.log_dir={tmp_path}", env=env)  # fmt: skip
    (sweep,) = (tmp_path / "smoke" / "multirun").iterdir()
    jobs = sorted(p for p in sweep.iterdir() if (p / "results.json").is_file())
    assert len(jobs) == 2
    names = set()
    for number, job in enumerate(jobs):
        files = list(job.glob("wandb/offline-run-*/run-*.wandb"))
        assert len(files) == 1, files  # one run per job, in the job's folder
        name, group, config, summary, exit_code = _read_run(files[0])
        run_id = sweep.name.rsplit("_", 1)[1]  # <date>_<time>_<run id>
        assert name == f"smoke-{run_id}-{number}" and group == f"smoke-{run_id}"
        names.add(name)
        assert exit_code == 0  # finished at the job's end
        lr = 1e-3 * (number + 1)
        assert config["model"]["optimizer"]["lr"] == pytest.approx(lr)
        assert config["paths"]["output_dir"] == str(job)
        results = json.loads((job / "results.json").read_text())
        assert summary["status"] == "completed" and summary["epoch"] == results["epoch"]
        final = {k: v for k, v in results["final"].items() if v is not None}
        assert final and {k: summary[f"final/{k}"] for k in final} == pytest.approx(final)
        best = results["best"]["train/loss"]
        assert summary["best/train/loss"] == pytest.approx(best["value"])
    assert len(names) == 2


@pytest.mark.slow
def test_eval_multirun_logs_one_finished_run_per_job(tmp_path, tiny_export):
    """resireg-eval tracker=wandb: a two-job grid gets two finished runs, each with its job's
    config (the swept alpha) and its results.json scores as final/<metric>."""
    env = {**os.environ, "WANDB_MODE": "offline", "WANDB_SILENT": "true",
           "WANDB_CONFIG_DIR": str(tmp_path / "wandb_config"), "WANDB_CACHE_DIR": str(tmp_path)}  # fmt: skip
    run("resireg-eval", "-m", f"model_path={tiny_export}", "dataset=synthetic", "dataset.size=4",
        "num_workers=0", "variants=[bb,full]", "full.n_prototypes=4", "tracker=wandb",
        "full.alpha=5.0,10.0", f"paths.log_dir={tmp_path}", env=env)  # fmt: skip
    (sweep,) = (tmp_path / "eval" / "multirun").iterdir()
    jobs = sorted(p for p in sweep.iterdir() if (p / "results.json").is_file())
    assert len(jobs) == 2
    run_id = sweep.name.rsplit("_", 1)[1]
    for number, job in enumerate(jobs):
        (file,) = job.glob("wandb/offline-run-*/run-*.wandb")
        name, group, config, summary, exit_code = _read_run(file)
        assert (name, group, exit_code) == (f"eval-{run_id}-{number}", f"eval-{run_id}", 0)
        assert config["full"]["alpha"] == pytest.approx(5.0 * (number + 1))
        results = json.loads((job / "results.json").read_text())
        assert summary["status"] == "completed"
        final = results["final"]
        assert final and {k: summary[f"final/{k}"] for k in final} == pytest.approx(final)


@pytest.mark.slow
def test_map_logs_one_finished_run_with_its_counts(tmp_path, tiny_export):
    """resireg-map tracker=wandb: one finished run with the config and the map's counts
    (map/voxels, frames/used...) equal to results.json's."""
    from resireg_train.data.room_bag import TOPICS, room_frames, write_bag
    from resireg_train.record.trackers.base import map_counts

    env = {**os.environ, "WANDB_MODE": "offline", "WANDB_SILENT": "true",
           "WANDB_CONFIG_DIR": str(tmp_path / "wandb_config"), "WANDB_CACHE_DIR": str(tmp_path)}  # fmt: skip
    bag = write_bag(tmp_path / "room", room_frames(4))
    out = tmp_path / "map"
    run("resireg-map", f"model_path={tiny_export}", "device=cpu", "source=rosbag",
        f"source.path={bag}", f"source.colour_topic={TOPICS['colour']}",
        f"source.depth_topic={TOPICS['depth']}", f"source.camera_info_topic={TOPICS['info']}",
        "variant=bb", "window=2", "tracker=wandb", f"hydra.run.dir={out}", env=env)  # fmt: skip
    (file,) = out.glob("wandb/offline-run-*/run-*.wandb")
    name, group, config, summary, exit_code = _read_run(file)
    assert exit_code == 0 and not group and name.startswith("map-")
    assert config["variant"] == "bb" and config["window"] == 2
    counts = map_counts(json.loads((out / "results.json").read_text()))
    assert counts["map/voxels"] > 0
    assert {k: summary[k] for k in counts} == pytest.approx(counts)
    assert summary["status"] == "completed"
