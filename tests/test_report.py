"""Sweep configs, multiruns and `resireg-report`: table, heatmap, heuristic, curves, failures."""

import csv
import json

import pytest
import torch
from hydra import compose, initialize_config_dir
from PIL import Image

from _run import run
from resireg.heuristic import PrototypeHeuristic
from resireg.reconstruct import ReSiRegFull
from resireg_train.cli.task import CONFIG_DIR, safe_dirname
from resireg_train.report import collect, report


def _rows(path):
    with open(path, newline="") as f:
        return list(csv.DictReader(f))


def test_prototype_batch_sweep_is_the_papers_full_factorial():
    with initialize_config_dir(str(CONFIG_DIR), version_base="1.3"):
        cfg = compose("eval", overrides=["sweep=prototype_batch", "model_path=x"],
                      return_hydra_config=True)  # fmt: skip
    params = cfg.hydra.sweeper.params
    assert [int(b) for b in params.batch_size.split(",")] == [2, 4, 6, 8, 16, 24, 32]
    start, stop, step = (int(v) for v in params["full.n_prototypes"][6:-1].split(","))
    assert list(range(start, stop, step)) == [24, 36, 48, 60, 72, 84, 96, 108, 120, 132]
    assert cfg.hydra.mode.name == "MULTIRUN" and cfg.variants == ["full"]
    assert cfg.full.n_components is None  # tied: ReSiRegFull uses n_components = n_prototypes


def test_prototype_batch_multirun_report_lists_failures_and_fits_the_heuristic(
    prototype_sweep, tmp_path
):
    sweep, proc = prototype_sweep
    # Hydra's basic sweeper runs every job, then exits with the first failure.
    assert proc.returncode != 0 and "exceeds the number of points" in proc.stderr
    jobs = sorted(p.name for p in sweep.iterdir() if p.is_dir())
    assert len(jobs) == 6 and jobs[0].startswith("0_batch_size=2,")
    assert all("/" not in j for j in jobs)  # the model path's slashes did not nest folders

    out = run("resireg-report", sweep).stdout
    assert "6 jobs, 4 completed, 2 not completed" in out
    rows = _rows(sweep / "summary.csv")
    assert [(r["batch_size"], r["full.n_prototypes"], r["status"]) for r in rows] == [
        ("2", "4", "completed"), ("2", "8", "completed"), ("2", "1000", "failed"),
        ("4", "4", "completed"), ("4", "8", "completed"), ("4", "1000", "failed"),
    ]  # fmt: skip
    metric = "val/ovss/synthetic/miou_full"
    for r in rows:
        if r["status"] == "failed":
            assert "n_prototypes=1000 exceeds" in r["error"] and r[metric] == ""
        else:
            assert 0.0 <= float(r[metric]) <= 1.0 and r["error"] == ""
            own = json.loads((sweep / jobs[int(r["job"])] / "results.json").read_text())
            assert float(r[metric]) == pytest.approx(own["final"][metric], rel=1e-12)
    markdown = (sweep / "summary.md").read_text()
    assert "## Jobs that did not complete" in markdown and markdown.count("**failed**") == 2

    with Image.open(sweep / "heatmap.png") as image:
        assert image.format == "PNG" and image.size[0] > 100
    # The heuristic follows the best prototype count of each batch size ...
    best = {}
    for r in rows:
        if r["status"] == "completed":
            b, n, v = int(r["batch_size"]), int(r["full.n_prototypes"]), float(r[metric])
            if v > best.get(b, (None, -1.0))[1]:
                best[b] = (n, v)
    heuristic = PrototypeHeuristic.load(sweep / "prototype_heuristic.json")
    assert {b: heuristic(b) for b in best} == {b: n for b, (n, _) in best.items()}
    # ... and ReSiRegFull(n_prototypes="auto") loads it.
    full = ReSiRegFull(n_prototypes="auto", heuristic=str(sweep / "prototype_heuristic.json"))
    out = full(torch.randn(2, 16, 4, 5), torch.randn(2, 8, 4, 5))
    assert out.shape == (2, 8, 8, 10)


def test_report_keeps_jobs_without_results_and_rejects_non_sweeps(prototype_sweep, tmp_path):
    import shutil

    sweep = tmp_path / "sweep"
    shutil.copytree(prototype_sweep[0], sweep)
    (victim,) = [p for p in sweep.iterdir() if p.name.startswith("3_")]
    (victim / "results.json").unlink()
    files = report(sweep, out=tmp_path / "report")
    rows = _rows(files["csv"])
    assert rows[3]["status"] == "missing" and "no results.json" in rows[3]["error"]
    assert len(collect(sweep)) == 6
    with pytest.raises(FileNotFoundError, match="holds no job folders"):
        report(tmp_path / "report")
    proc = run("resireg-report", tmp_path / "nowhere", check=False)
    assert proc.returncode == 2 and "does not exist" in proc.stderr


@pytest.mark.slow
def test_training_sweep_report_plots_the_metric_per_epoch(tmp_path):
    run("resireg-train", "experiment=smoke", "sweep=train_hparams", "model.optimizer.lr=1e-3,3e-3",
        "model.loss.distill.scale=0.1", "trainer.max_epochs=2", "data.steps_per_epoch=2",
        "~callbacks.progress_bar", f"paths.log_dir={tmp_path}")  # fmt: skip
    (sweep,) = (tmp_path / "smoke" / "multirun").iterdir()
    files = report(sweep)
    rows = _rows(files["csv"])
    assert [r["model.optimizer.lr"] for r in rows] == ["0.001", "0.003"]
    assert all(r["status"] == "completed" for r in rows)
    folders = sorted(p for p in sweep.iterdir() if p.is_dir())
    metric = "val/ovss/synthetic/miou_full"
    for r in rows:  # the best value and its epoch, recomputed from each job's own history
        history = json.loads((folders[int(r["job"])] / "results.json").read_text())["history"]
        best = max(history, key=lambda h: h[metric])
        assert float(r[f"best {metric}"]) == pytest.approx(best[metric], rel=1e-12)
        assert int(r["best epoch"]) == best["epoch"]
    with Image.open(files["curves"]) as image:
        assert image.format == "PNG"


def test_safe_dirname_flattens_paths_and_keeps_long_names_unique():
    assert (
        safe_dirname("model_path=/a/b/export,batch_size=2") == "model_path=_a_b_export,batch_size=2"
    )
    a, b = safe_dirname("x=" + "1" * 300), safe_dirname("x=" + "1" * 299 + "2")
    assert len(a) == 200 and a != b
