"""``resireg-runs plot`` and ``resireg-runs gc`` (issue 47, items 5 and 6) on a real training
multirun: the plotted curves are the runs' own metrics.csv and history, read back from the
figure; gc keeps the best run's checkpoints, removes only the others' checkpoints (records,
exports and cards stay) and never touches a running or locked run. A search folder's plots
are Optuna's, on a study the test writes."""

from __future__ import annotations

import contextlib
import csv
import fcntl
import hashlib
import io
import json
import shutil
from pathlib import Path

import pytest

from helpers.run import run
from resireg_train.cli.runs import main as runs_main

METRIC = "val/ovss/synthetic/miou_full"


@pytest.fixture(scope="module")
def sweep(tmp_path_factory):
    """Three smoke trainings (2 epochs of 2 steps, three learning rates) as one multirun."""
    root = tmp_path_factory.mktemp("runs")
    run("resireg-train", "-m", "experiment=smoke", "trainer.max_epochs=2",
        "data.steps_per_epoch=2", "~callbacks.progress_bar",
        "model.optimizer.lr=1e-3,3e-3,3e-2", f"hydra.sweep.dir={root / 'sweep'}",
        threads=1)  # fmt: skip
    jobs = sorted(p.parent for p in (root / "sweep").glob("*/results.json"))
    assert len(jobs) == 3
    return root / "sweep", jobs


def _cli(*args: str) -> str:
    out = io.StringIO()
    with contextlib.redirect_stdout(out):
        runs_main([str(a) for a in args])
    return out.getvalue()


def _without_csv(job: Path, tmp_path: Path):
    from resireg_train.runs.index import read_run

    copy = tmp_path / f"nocsv-{job.name[:1]}"
    copy.mkdir()
    shutil.copy(job / "results.json", copy / "results.json")
    return read_run(copy)


def _csv_series(folder: Path, column: str) -> tuple[list[float], list[float]]:
    with open(folder / "metrics.csv", newline="") as f:
        rows = [r for r in csv.DictReader(f) if r.get(column)]
    return [float(r["step"]) for r in rows], [float(r[column]) for r in rows]


@pytest.mark.slow
def test_plot_draws_each_runs_own_curves(sweep, tmp_path):
    from PIL import Image

    from resireg_train.runs.index import read_run
    from resireg_train.runs.plots import metric_curve, plot_runs, run_labels

    folder, jobs = sweep
    runs = [read_run(j) for j in jobs]
    png = tmp_path / "curves.png"
    result = plot_runs(runs, ["train/loss", "val/ovss/*/miou_full"], png, tmp_path / "c.html")
    assert list(result.curves) == ["train/loss", METRIC]
    labels = run_labels(runs)
    for job, r, label in zip(jobs, runs, labels, strict=True):
        lr = job.name.split("model.optimizer.lr=")[1].split(",")[0]
        assert label == f"{r.run_id} smoke model.optimizer.lr={lr}"  # the swept value
        # train/loss: every step of metrics.csv (read here with the csv module)
        assert result.curves["train/loss"][label] == _csv_series(job, "train/loss_step")
        assert len(result.curves["train/loss"][label][0]) == 4  # 2 epochs x 2 steps
        # the validation mIoU: metrics.csv's epoch rows (at each epoch's last step, where
        # train/loss_epoch is too), the record's history values
        record = json.loads((job / "results.json").read_text())
        x, y = result.curves[METRIC][label]
        assert x == _csv_series(job, "train/loss_epoch")[0] == [1.0, 3.0]
        assert y == pytest.approx([h[METRIC] for h in record["history"]])
        # a run whose metrics.csv is gone is drawn from its record's history, at the same x
        assert metric_curve(_without_csv(job, tmp_path), METRIC)[:2] == (x, y)
    with Image.open(png) as image:
        assert image.format == "PNG" and image.size[0] >= 900 and image.size[1] >= 600
    page = (tmp_path / "c.html").read_text()
    assert "plotly" in page and METRIC.replace("/", "\\u002f") in page  # JSON escapes /
    assert all(label in page for label in labels)

    # the command: a sweep folder stands for its runs; a metric nobody logged is named
    printed = _cli("plot", folder, "--metric", "train/loss", "--out", tmp_path / "cli.png")
    assert printed.split() == [str(tmp_path / "cli.png")]
    with pytest.raises(SystemExit) as code:
        _cli("plot", folder, "--metric", "val/nothing")
    assert code.value.code == 2


def _digests(folder: Path) -> dict[str, str]:
    return {str(p.relative_to(folder)): hashlib.sha256(p.read_bytes()).hexdigest()
            for p in sorted(folder.rglob("*")) if p.is_file() and p.name != ".run.lock"}  # fmt: skip


def _bytes(folder: Path) -> int:
    return sum(p.stat().st_size for p in folder.rglob("*") if p.is_file())


@pytest.mark.slow
def test_gc_keeps_the_best_runs_checkpoints_and_removes_only_checkpoints(sweep, tmp_path):
    source, _ = sweep
    folder = tmp_path / "sweep"
    shutil.copytree(source, folder)
    jobs = sorted(p.parent for p in folder.glob("*/results.json"))
    records = {j: json.loads((j / "results.json").read_text()) for j in jobs}
    ranked = sorted(jobs, key=lambda j: -records[j]["best"][METRIC]["value"])
    best, others = ranked[0], ranked[1:]
    assert all((j / "checkpoints" / "last.ckpt").is_file() for j in jobs)
    assert all((j / "export" / "README.md").is_file() for j in jobs)
    before = {j: _digests(j) for j in jobs}
    freed = sum(_bytes(j / "checkpoints") for j in others)

    listing = _cli("gc", folder, "--keep", "1", "--by", METRIC, "--dry-run")
    lines = listing.splitlines()
    assert lines[0].startswith("keep") and str(best) in lines[0]
    assert all(line.startswith("would remove") for line in lines[1:3])
    assert {line.split(" (")[0].split()[-1] for line in lines[1:3]} == {str(j) for j in others}
    from resireg_train.runs.gc import human

    assert lines[-1] == f"would free {human(freed)} in 2 run(s) (--dry-run: nothing removed)"
    assert {j: _digests(j) for j in jobs} == before  # nothing removed

    # a locked run (its job holds .run.lock) and a running one are never touched
    locked, running = others
    record = {**records[running], "status": "running"}
    record["provenance"]["machine"]["host"] = "another-host"  # not this host: stays running
    (running / "results.json").write_text(json.dumps(record))
    before[running] = _digests(running)
    with open(locked / ".run.lock", "a+") as held:
        fcntl.flock(held.fileno(), fcntl.LOCK_EX | fcntl.LOCK_NB)
        held.truncate(0)  # as the job holding it writes its PID (cli/job.py)
        held.write("4242\n")
        held.flush()
        listing = _cli("gc", folder, "--keep", "1", "--by", METRIC)
    assert "skip" in listing and "locked by PID 4242" in listing and "[running]" in listing
    assert {j: _digests(j) for j in jobs} == before
    assert listing.splitlines()[-1] == "freed 0 B in 0 run(s)"

    # both released: gc removes their checkpoints and nothing else
    (running / "results.json").write_text(json.dumps(records[running]))
    before[running] = _digests(running)
    listing = _cli("gc", folder, "--keep", "1", "--by", METRIC)
    assert listing.splitlines()[-1] == f"freed {human(freed)} in 2 run(s)"
    assert _digests(best) == before[best]
    for job in others:
        assert not (job / "checkpoints").exists()
        kept = {k: v for k, v in before[job].items() if not k.startswith("checkpoints/")}
        assert _digests(job) == kept  # results.json, metrics.csv, export/, its card, .hydra
    # a loss ranks lowest first: --keep 0 by train/loss removes the best's too
    assert "removed" in _cli("gc", folder, "--keep", "0", "--by", "train/loss")
    assert not (best / "checkpoints").exists() and (best / "export" / "README.md").is_file()


def test_gc_refuses_an_unknown_direction_and_a_metric_nobody_logged(tmp_path, capsys):
    from helpers.sweeps import make_job

    make_job(tmp_path, 0, {"x": 1}, {"status": "completed", "final": {"my/score": 1.0}})
    for args, message in ((["--by", "my/score"], "give --mode min or --mode max"),
                          (["--by", "train/loss"], "no run under")):  # fmt: skip
        with pytest.raises(SystemExit) as code:
            runs_main(["gc", str(tmp_path), "--keep", "1", *args])
        assert code.value.code == 2 and message in capsys.readouterr().err


def test_a_search_folder_plots_optunas_own_figures(tmp_path):
    optuna = pytest.importorskip("optuna")
    from PIL import Image

    from resireg_train.runs.search_plots import plot_search
    from resireg_train.search.storage import open_storage

    study = optuna.create_study(study_name="search", direction="maximize",
                                storage=open_storage(None, tmp_path))  # fmt: skip
    space = {"full.alpha": optuna.distributions.FloatDistribution(1.0, 20.0),
             "full.n_prototypes": optuna.distributions.IntDistribution(12, 132, step=12)}  # fmt: skip
    values = []
    for i in range(6):
        params = {"full.alpha": 1.0 + 3 * i, "full.n_prototypes": 12 * (1 + i % 3)}
        value = 0.1 + 0.01 * i - 0.002 * (i % 3)
        values.append(value)
        study.add_trial(optuna.trial.create_trial(params=params, distributions=space, value=value))
    result = plot_search(tmp_path, tmp_path / "plots")
    names = sorted(p.name for p in result.files)
    assert names == ["optuna_history.png", "optuna_importance.png", "optuna_parallel.png",
                     "optuna_plots.html"]  # fmt: skip
    points = result.curves["optuna_history"]["Objective Value"]
    assert points == ([0.0, 1.0, 2.0, 3.0, 4.0, 5.0], pytest.approx(values))
    for png in (p for p in result.files if p.suffix == ".png"):
        with Image.open(png) as image:
            assert image.format == "PNG"
    page = (tmp_path / "plots" / "optuna_plots.html").read_text()
    assert page.count("plotly") > 3 and "Optimization History Plot" in page
    assert "Parallel Coordinate Plot" in page and "Hyperparameter Importances" in page
