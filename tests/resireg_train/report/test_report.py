"""Sweep configs, multiruns and `resireg-report`: table, heatmap, heuristic, curves, failures."""

import csv
import json
import math
import re
import shlex
import sys

import pandas as pd
import pytest
import torch
import yaml
from hydra import compose, initialize_config_dir
from hydra._internal.core_plugins.basic_sweeper import BasicSweeper
from hydra.core.global_hydra import GlobalHydra
from hydra.core.override_parser.overrides_parser import OverridesParser
from hydra.errors import ConfigCompositionException
from omegaconf import OmegaConf
from PIL import Image

from helpers.run import report as report_stdout
from helpers.run import run, run_side_by_side
from helpers.sweeps import make_job as _job
from resireg.method.full import ReSiRegFull
from resireg.method.heuristic import PrototypeHeuristic
from resireg_train.cli import report as report_cli
from resireg_train.cli.job import CONFIG_DIR, hydra_entry_point
from resireg_train.jobs.resolvers import safe_dirname
from resireg_train.report import (
    DPI,
    collect,
    curves_figure,
    grid_statuses,
    heatmap_figure,
    plot_heatmap,
    prototype_grid,
    report,
    report_sections,
)

MIOU = "val/ovss/synthetic/miou_full"


def _rows(path):
    with open(path, newline="") as f:
        return list(csv.DictReader(f))


def _tick_labels(axis):
    """The tick labels ``axis`` draws (those inside its view limits)."""
    lo, hi = sorted(axis.get_view_interval())
    i = 0 if axis.axis_name == "x" else 1
    return [t for t in axis.get_ticklabels() if lo <= t.get_position()[i] <= hi]


def _outside(artist, fig, renderer):
    """How far (px) ``artist``'s drawn extent sticks out of the figure; 0 when inside."""
    box, frame = artist.get_window_extent(renderer), fig.bbox
    return max(frame.x0 - box.x0, box.x1 - frame.x1, frame.y0 - box.y0, box.y1 - frame.y1, 0)


def test_prototype_batch_sweep_is_the_papers_full_factorial():
    """Both forms cover the paper's 7 batch sizes x 10 prototype counts, components tied: 7
    jobs of 10 configurations each (one encoder pass per batch size), or 70 jobs."""
    counts = [24, 36, 48, 60, 72, 84, 96, 108, 120, 132]
    with initialize_config_dir(str(CONFIG_DIR), version_base="1.3"):
        passes = compose("eval", overrides=["sweep=prototype_batch", "model_path=x"],
                         return_hydra_config=True)  # fmt: skip
        jobs = compose("eval", overrides=["sweep=prototype_batch_jobs", "model_path=x"],
                       return_hydra_config=True)  # fmt: skip
    for cfg in (passes, jobs):
        params = cfg.hydra.sweeper.params
        assert [int(b) for b in params.batch_size.split(",")] == [2, 4, 6, 8, 16, 24, 32]
        assert cfg.hydra.mode.name == "MULTIRUN" and cfg.name == "prototype_batch"
        assert cfg.full.n_components is None  # tied: ReSiRegFull uses n_components = n_prototypes
    assert list(passes.variants) == [f"full@n_prototypes:{n}" for n in counts]
    assert "full.n_prototypes" not in passes.hydra.sweeper.params
    start, stop, step = (
        int(v) for v in jobs.hydra.sweeper.params["full.n_prototypes"][6:-1].split(",")
    )
    assert list(range(start, stop, step)) == counts and jobs.variants == ["full"]


@pytest.mark.slow
def test_prototype_batch_multirun_report_lists_failures_and_fits_the_heuristic(
    prototype_sweep, tmp_path
):
    sweep, proc = prototype_sweep
    # Hydra's basic sweeper runs every job, then exits with the first failure.
    assert proc.returncode != 0 and "exceeds the number of points" in proc.stderr
    jobs = sorted(p.name for p in sweep.iterdir() if p.is_dir())
    assert len(jobs) == 6 and jobs[0].startswith("0_batch_size=2,")
    assert all("/" not in j for j in jobs)  # the model path's slashes did not nest folders

    out = report_stdout(sweep)  # resireg-report's main, in this process
    assert "6 jobs, 4 completed, 2 failed" in out
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


def test_report_keeps_jobs_without_results_and_rejects_non_sweeps(
    prototype_sweep, tmp_path, capsys
):
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
    capsys.readouterr()
    with pytest.raises(SystemExit) as exit:  # resireg-report's main: the console script's exit
        report_stdout(tmp_path / "nowhere")
    assert exit.value.code == 2 and "does not exist" in capsys.readouterr().err


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


def test_unknown_metric_is_a_cli_error_naming_the_metrics_the_sweep_has(tmp_path, capsys):
    sweep = tmp_path / "sweep"
    finals = [{MIOU: 0.4, "train/lr": 1e-3}, {MIOU: 0.5, "val/acc": 0.9}]
    for n, final in enumerate(finals):
        best = {"train/loss": {"value": 1.0, "epoch": 0}}  # only in "best"
        _job(sweep, n, {"batch_size": 2 + n}, {"status": "completed", "final": final, "best": best})
    with pytest.raises(SystemExit) as exit_info:
        report_cli.main([str(sweep), "--metric", "val/nope"])
    assert exit_info.value.code == 2
    err = capsys.readouterr().err
    assert "'val/nope'" in err
    listed = err.split("hold: ")[1].strip().split(", ")
    assert listed == sorted([MIOU, "train/lr", "val/acc", "train/loss"])
    assert not (sweep / "summary.csv").exists()  # nothing written
    # A metric that only some job's "best" holds is known.
    report_cli.main([str(sweep), "--metric", "train/loss"])
    assert capsys.readouterr().out.splitlines()[-1] == "2 jobs, 2 completed"


def _status_sweep(sweep):
    """A 2 x 3 batch/prototype grid, one job per status; returns {(batch, protos): status}."""
    stop = "KeyboardInterrupt: interrupted by the user (Ctrl-C); resume with ckpt_path=last"
    cells = {
        (2, 4): {"status": "completed", "final": {MIOU: 0.25}},
        (2, 8): {"status": "interrupted", "error": stop, "final": {MIOU: 0.3}},
        (2, 16): {"status": "failed", "error": "ValueError: boom"},
        (4, 4): {"status": "completed", "final": {MIOU: 0.5}},
        (4, 8): {"status": "running", "error": None, "final": {MIOU: 0.1}},
        (4, 16): None,  # never wrote results.json
    }
    for n, ((b, p), results) in enumerate(cells.items()):
        _job(sweep, n, {"batch_size": b, "full.n_prototypes": p}, results)
    return stop, {k: (v or {}).get("status", "missing") for k, v in cells.items()}


def test_report_counts_and_labels_interrupted_jobs(tmp_path, capsys):
    sweep = tmp_path / "sweep"
    stop, statuses = _status_sweep(sweep)
    report_cli.main([str(sweep)])
    last = capsys.readouterr().out.splitlines()[-1]
    assert last == "6 jobs, 2 completed, 1 running, 1 interrupted, 1 failed, 1 missing"
    rows = _rows(sweep / "summary.csv")
    assert [r["status"] for r in rows] == list(statuses.values())
    assert rows[1]["error"] == stop and rows[1][MIOU] == "0.3"  # how far it got
    markdown = (sweep / "summary.md").read_text()
    assert "6 jobs: 2 completed, 1 running, 1 interrupted, 1 failed, 1 missing" in markdown
    section = markdown.split("## Jobs that did not complete")[1]
    assert f"- job 1 (1_batch_size=2,full.n_prototypes=8): **interrupted**: {stop}" in section
    assert section.count("**") == 2 * 4
    # Heatmap cells: the value (x100) where the job completed, else the job's status.
    jobs = collect(sweep)
    grid = prototype_grid(jobs, MIOU)
    fig = heatmap_figure(grid, MIOU, grid_statuses(jobs, MIOU, grid))
    (ax,) = [a for a in fig.axes if a.get_title() == MIOU]
    texts = {tuple(t.get_position()): t.get_text() for t in ax.texts}
    expected = {
        (j, i): {(2, 4): "25.0", (4, 4): "50.0"}.get((b, p), statuses[(b, p)])
        for i, b in enumerate((2, 4))
        for j, p in enumerate((4, 8, 16))
    }
    assert texts == expected
    assert statuses[(2, 8)] == "interrupted" and texts[(1, 0)] == "interrupted"


@pytest.mark.parametrize(
    ("rows", "cols", "metric"),
    [(1, 1, "val/ovss/a_much_longer_dataset_name/miou_full"), (2, 2, MIOU), (7, 10, MIOU)],
)
def test_heatmap_keeps_title_labels_and_ticks_inside_the_figure(tmp_path, rows, cols, metric):
    batches, protos = [2, 4, 6, 8, 16, 24, 32][:rows], list(range(24, 133, 12))[:cols]
    values = torch.rand(rows, cols, dtype=torch.float64).numpy()
    values[-1, -1] = float("nan")
    grid = pd.DataFrame(values, index=batches, columns=protos)
    statuses = pd.DataFrame("completed", index=batches, columns=protos, dtype=object)
    statuses.iloc[-1, -1] = "interrupted"
    fig = heatmap_figure(grid, metric, statuses)
    fig.draw_without_rendering()  # runs constrained layout
    renderer = fig.canvas.get_renderer()
    (ax,) = [a for a in fig.axes if a.get_title() == metric]
    (cbar,) = [a for a in fig.axes if a is not ax]
    assert [t.get_text() for t in _tick_labels(ax.xaxis)] == [str(p) for p in protos]
    assert [t.get_text() for t in _tick_labels(ax.yaxis)] == [str(b) for b in batches]
    artists = [ax.title, ax.xaxis.label, ax.yaxis.label, *_tick_labels(ax.xaxis),
               *_tick_labels(ax.yaxis), cbar.yaxis.label, *_tick_labels(cbar.yaxis)]  # fmt: skip
    assert [(a.get_text(), _outside(a, fig, renderer)) for a in artists] == [
        (a.get_text(), 0) for a in artists
    ]
    assert not ax.title.get_window_extent(renderer).overlaps(ax.get_window_extent(renderer))
    # The PNG is the figure at DPI dots per inch (no cropping).
    plot_heatmap(grid, metric, tmp_path / "heatmap.png", statuses)
    with Image.open(tmp_path / "heatmap.png") as image:
        assert image.size == tuple(round(v * DPI) for v in fig.get_size_inches())
        assert image.size[0] >= 5 * DPI and image.size[1] >= 3.5 * DPI


def test_curves_of_many_runs_keep_legend_and_labels_inside_the_figure(tmp_path):
    sweep = tmp_path / "sweep"
    lrs = [f"{k}e-4" for k in range(1, 11)]
    for n, lr in enumerate(lrs):
        history = [{"epoch": e, "step": 8 * e, MIOU: 0.1 * e + 0.01 * n} for e in range(3)]
        _job(sweep, n, {"model.optimizer.lr": lr}, {"status": "completed", "history": history})
    fig = curves_figure(collect(sweep), MIOU)
    fig.draw_without_rendering()
    renderer = fig.canvas.get_renderer()
    (ax,) = fig.axes
    (legend,) = fig.legends
    # the varying key by its short name, the value in 3 significant digits (issue 36 item 7)
    assert [t.get_text() for t in legend.get_texts()] == [f"lr={float(lr):.3g}" for lr in lrs]
    assert [t.get_text() for t in _tick_labels(ax.xaxis)] == ["0", "1", "2"]  # whole epochs
    artists = [ax.xaxis.label, ax.yaxis.label, legend, *_tick_labels(ax.xaxis),
               *_tick_labels(ax.yaxis)]  # fmt: skip
    assert [_outside(a, fig, renderer) for a in artists] == [0] * len(artists)
    assert not legend.get_window_extent(renderer).overlaps(ax.get_window_extent(renderer))


def _smaller_grid_commands():
    """The resireg-eval command lines under "A smaller grid" in prototype_batch.yaml's comment."""
    text = (CONFIG_DIR / "sweep" / "prototype_batch.yaml").read_text()
    comment = [line.lstrip("#").strip() for line in text.splitlines() if line.startswith("#")]
    after = comment[next(i for i, c in enumerate(comment) if c.startswith("A smaller grid")) :]
    return [shlex.split(c)[1:] for c in after if c.startswith("resireg-eval ")]


def test_the_smaller_grid_overrides_in_the_sweep_comment_work(tmp_path, monkeypatch):
    plain, quoted = _smaller_grid_commands()
    counts = [f"full@n_prototypes:{n}" for n in range(24, 133, 12)]
    # `batch_size=2,8`: Hydra's own multirun of the documented command, a no-op task per job.
    seen = []

    def task(cfg):
        seen.append((cfg.batch_size, list(cfg.variants)))
        return {}

    documented = [a.replace("<export>", "x") for a in plain]
    logs = [f"paths.log_dir={tmp_path}", "hydra/job_logging=none", "hydra/hydra_logging=none"]
    monkeypatch.setattr(sys, "argv", ["resireg-eval", *documented, *logs])
    try:
        hydra_entry_point("eval", task)()
    finally:
        GlobalHydra.instance().clear()
    assert seen == [(2, counts), (8, counts)]  # 2 jobs, 10 configurations each
    # The quoted sweeper param composes (unquoted, the comment's old form, it does not), and
    # Hydra's basic sweeper expands the params to the same jobs.
    args = [a.replace("<export>", "x") for a in quoted]
    with initialize_config_dir(str(CONFIG_DIR), version_base="1.3"):
        cfg = compose("eval", overrides=args, return_hydra_config=True)
        with pytest.raises(ConfigCompositionException, match="Ambiguous value"):
            compose("eval", overrides=[a.replace('"', "") for a in args])
    params = cfg.hydra.sweeper.params
    parsed = OverridesParser.create().parse_overrides([f"{k}={v}" for k, v in params.items()])
    (jobs,) = BasicSweeper.split_arguments(parsed, max_batch_size=None)
    assert [tuple(int(o.split("=")[1]) for o in job) for job in jobs] == [(2,), (8,)]
    assert list(cfg.variants) == counts


@pytest.mark.slow
def test_one_job_per_batch_size_reports_what_one_job_per_setting_reports(tmp_path, tiny_export):
    """The same 2 x 2 grid as 4 jobs (full.n_prototypes swept) and as 2 jobs of two
    configurations each: equal scores cell by cell, equal heuristic."""
    common = [f"model_path={tiny_export}", "dataset=synthetic", "dataset.size=12",
              "num_workers=0", "batch_size=2,4"]  # fmt: skip
    forms = {
        "jobs": ["sweep=prototype_batch_jobs", "full.n_prototypes=4,8"],
        "passes": ["sweep=prototype_batch", "variants=[full@n_prototypes:4,full@n_prototypes:8]"],
    }
    # The two multiruns are independent: side by side, one torch thread each (same numerics).
    run_side_by_side(
        *(("resireg-eval", *common, *args, f"paths.log_dir={tmp_path / form}")
          for form, args in forms.items())
    )  # fmt: skip
    reports = {}
    for form in forms:
        (sweep,) = (tmp_path / form / "prototype_batch" / "multirun").iterdir()
        assert len([p for p in sweep.iterdir() if p.is_dir()]) == {"jobs": 4, "passes": 2}[form]
        report_stdout(sweep)  # resireg-report's main, in this process
        jobs = collect(sweep)
        reports[form] = (
            prototype_grid(jobs, "val/ovss/synthetic/miou_full"),
            json.loads((sweep / "prototype_heuristic.json").read_text()),
        )
    (grid_jobs, fit_jobs), (grid_passes, fit_passes) = reports["jobs"], reports["passes"]
    assert grid_jobs.shape == (2, 2) and not grid_jobs.isna().to_numpy().any()
    pd.testing.assert_frame_equal(grid_jobs, grid_passes, check_exact=True)
    assert fit_jobs == fit_passes


def test_a_one_encoder_table1_or_table2_sweep_still_writes_its_table(tmp_path):
    """Issue 22, case 9: `sweep=table1 encoder=clip_vit_b16` (or table2) cut to one encoder
    varies no encoder, and its table was not written."""
    encoder = {"name": "clip_vit_b16", "kind": "clip", "third_party": True, "parameters": 150e6}
    sweep = tmp_path / "table1"
    for n, dataset in enumerate(("ade20k", "orad3d")):
        final = {f"val/ovss/{dataset}/miou_{v}": 0.2 + 0.1 * i
                 for i, v in enumerate(("bb", "calib", "lite", "full"))}  # fmt: skip
        _job(sweep, n, {"sweep": "table1", "encoder": "clip_vit_b16", "dataset": dataset},
             {"name": "table1", "status": "completed", "final": final, "encoder": encoder,
              "params": {"dataset": {"name": dataset}, "encoder": encoder}})  # fmt: skip
    files = report(sweep)
    assert files["table1_md"].is_file()
    (row,) = [r for r in _rows(files["table1_csv"]) if r["encoder"] == "clip_vit_b16"]
    assert (
        float(row["ade20k Full Δ"]) == pytest.approx(30.0) and row["orad3d status"] == "completed"
    )

    sweep = tmp_path / "table2"
    final = {"val/scannet3d/scannet/miou_full": 0.3, "val/scannet3d/scannet/fmiou_full": 0.4}
    _job(sweep, 0, {"sweep": "table2", "encoder": "clip_vit_b16"},
         {"name": "table2", "status": "completed", "final": final, "encoder": encoder,
          "params": {"task": "scannet3d", "variants": ["full"], "dataset": {"name": "scannet"},
                     "encoder": encoder}})  # fmt: skip
    files = report(sweep)
    (row,) = _rows(files["table2_csv"])
    assert row["model"] == "clip_vit_b16 + Full" and float(row["scannet mIoU"]) == 30.0
    # A one-encoder sweep of another kind (the prototype ablation) gets no encoder table.
    sweep = tmp_path / "ablation"
    for n, b in enumerate((2, 4)):
        _job(sweep, n, {"sweep": "prototype_batch", "batch_size": b},
             {"name": "prototype_batch", "status": "completed", "final": {MIOU: 0.1 * n}})  # fmt: skip
    assert "table1_md" not in report(sweep) and "table2_md" not in report(sweep)


def test_reports_render_errors_on_one_line_failures_alike_and_say_what_means_cover(tmp_path):
    """Issue 22, case 10: a multi-line error (with a `|`) stays in its summary.md row; a
    failed job's cells are empty in every table (never `nan`); the mean rows name the
    encoders they average over."""
    sweep = tmp_path / "table1"
    error = ("resireg.errors.ConfigError: invalid config:\n  full.alpha=0: expected a "
             "number > 0\n  lite.tau=2: expected a number in [0, 1] | or null")  # fmt: skip
    jobs = [("ours", False, 0.25, None), ("clip", True, 0.5, None), ("radio", True, None, error)]
    for n, (name, third, bb, err) in enumerate(jobs):
        encoder = {"name": name, "third_party": third, "parameters": 1e6}
        results = {"name": "table1", "encoder": encoder, "params": {"dataset": {"name": "ade20k"}}}
        if err is None:
            final = {
                f"val/ovss/ade20k/miou_{v}": bb + 0.1 * i for i, v in enumerate(("bb", "full"))
            }
            results.update(status="completed", final=final)
        else:
            results.update(status="failed", error=err, final={"val/ovss/ade20k/miou_bb": math.nan})
        _job(sweep, n, {"encoder": name, "dataset": "ade20k"}, results)
    files = report(sweep)
    summary = files["md"].read_text()
    rows = [line for line in summary.splitlines() if line.startswith("|")]
    assert len(rows) == 2 + 3  # header, rule, one line per job
    flat = ("resireg.errors.ConfigError: invalid config: full.alpha=0: expected a number "
            "> 0; lite.tau=2: expected a number in [0, 1] \\| or null")  # fmt: skip
    cells = [c.strip() for c in re.split(r"(?<!\\)\|", rows[-1])[1:-1]]  # unescaped pipes
    assert cells[:3] == ["2", "radio", "failed"] and cells[-1] == flat, cells
    assert cells[3:-1] == [""] * (len(cells) - 4)  # its NaN score: an empty cell
    assert f"- job 2 (2_encoder=radio,dataset=ade20k): **failed**: {flat.replace(chr(92), '')}" in (
        summary
    )
    table1 = files["table1_md"].read_text()
    for text in (summary, table1):
        assert "nan" not in text.lower(), text
    lines = {
        line.split("|")[1].strip(): line for line in table1.splitlines() if line.count("|") > 3
    }
    radio = [c.strip() for c in lines["radio"].split("|")[1:-1]]
    assert radio[3:-1] == [""] * (len(radio) - 4) and radio[-1] == "failed"  # cells empty
    assert lines["mean Δ, all encoders"].rstrip(" |").endswith("over 2 of 3 (not radio: failed)")
    assert (
        lines["mean Δ, third-party encoders"]
        .rstrip(" |")
        .endswith("over 1 of 2 (not radio: failed)")
    )
    assert "Over the 2 of 3 encoder x dataset jobs that completed." in table1
    csv_means = {r["encoder"]: r for r in _rows(files["table1_csv"])}
    assert float(csv_means["mean Δ, all encoders"]["ade20k Full Δ"]) == pytest.approx(10.0)


def test_the_job_counts_the_readme_and_the_sweep_files_state_are_the_sweeps_own():
    """Issue 22, case 13: the README said Table 1 runs 8 encoders; it runs 10. The comment
    after every `sweep=table1` / `sweep=table2 model_path=...` command of the README and the
    sweep files (`# 10 encoders x 2 datasets`, `# 10 x 2 = 20 jobs`, `# Table 2: 10 jobs`)
    matches the sweep's own axes."""
    from resireg_train.checks import eval as _eval_checks  # noqa: F401  registers ${resireg_encoders:}

    readme = (CONFIG_DIR.parent / "README.md").read_text().splitlines()
    for name, datasets in (("table1", None), ("table2", 1)):  # table2: ScanNet alone
        sweep = CONFIG_DIR / "sweep" / f"{name}.yaml"
        params = OmegaConf.load(sweep).hydra.sweeper.params
        axes = [len(str(params.encoder).split(",")),
                datasets or len(str(params.dataset).split(","))]  # fmt: skip
        lines = [x for x in readme + sweep.read_text().splitlines()
                 if f"sweep={name} model_path=" in x]  # fmt: skip
        assert len(lines) == 2, lines
        for line in lines:
            comment = line.rsplit("#", 1)[1].replace("Table 2:", "")
            numbers = [int(n) for n in re.findall(r"\d+", comment)]
            if "encoders x" in comment:
                assert numbers == axes, line
            else:
                assert numbers[-1] == math.prod(axes), line


def _saved_config(job_folder, report_sections):
    """What Hydra saves of a job's config (`.hydra/config.yaml`), reduced to the `report` key."""
    (job_folder / ".hydra" / "config.yaml").write_text(yaml.safe_dump({"report": report_sections}))


def test_the_sweep_config_names_its_report_instead_of_the_report_guessing(tmp_path):
    """Issue 23 item 4: the sections beyond the summary are those the sweep config names
    (`report: [...]`, saved in every job's config), whatever the overrides look like; only a
    sweep that names none (an ad hoc `-m`) gets those its jobs show."""
    encoder = {"name": "clip_vit_b16", "kind": "clip", "third_party": True, "parameters": 150e6}
    final = {f"val/ovss/ade20k/miou_{v}": 0.2 + 0.1 * i
             for i, v in enumerate(("bb", "calib", "lite", "full"))}  # fmt: skip
    results = {"status": "completed", "final": final, "encoder": encoder,
               "params": {"dataset": {"name": "ade20k"}, "encoder": encoder}}  # fmt: skip
    # One encoder, no sweep=table1 override, no run name: only the config says Table 1.
    named = tmp_path / "named"
    _saved_config(_job(named, 0, {"dataset": "ade20k"}, results), ["table1"])
    files = report(named)
    assert report_sections(collect(named)) == ["table1"] and files["table1_md"].is_file()
    # Two encoders would be read as Table 1; a config that names no section gets none.
    plain = tmp_path / "plain"
    for n, name in enumerate(("clip_vit_b16", "radseg")):
        _saved_config(_job(plain, n, {"encoder": name}, results), [])
    assert report_sections(collect(plain)) == [] and "table1_md" not in report(plain)
    # The same jobs without a saved config: the encoder axis shows Table 1.
    guessed = tmp_path / "guessed"
    for n, name in enumerate(("clip_vit_b16", "radseg")):
        _job(guessed, n, {"encoder": name}, results)
    assert report_sections(collect(guessed)) == ["table1"] and "table1_md" in report(guessed)


def test_every_evaluation_sweep_names_its_report_and_the_config_check_knows_the_names():
    """Each `conf/sweep/` file of resireg-eval names its sections (composed as a user composes
    it), every name is one the report writes, and a wrong one is refused naming the key."""
    from resireg.errors import ConfigError
    from resireg_train.checks.eval import validate_eval
    from resireg_train.report.specs import section_names

    eval_sweeps = [p.stem for p in (CONFIG_DIR / "sweep").glob("*.yaml")
                   if p.stem != "train_hparams"]  # fmt: skip
    with initialize_config_dir(str(CONFIG_DIR), version_base="1.3"):
        for name in eval_sweeps:
            cfg = compose("eval", overrides=[f"sweep={name}"])
            assert cfg.report is not None, name
            assert set(cfg.report) <= set(section_names()), name
        cfg = compose("eval", overrides=["report=[tabel1]"])
    with pytest.raises(ConfigError, match=r"report=\['tabel1'\]: expected null or a list of"):
        validate_eval(cfg)


def test_every_report_section_loads_and_takes_what_the_report_gives():
    """Each entry of the section table: its writer and detector load and take only the report's
    inputs by name; the names a sweep may list are the entries not written always; the encoder
    sweeps are the encoder table sections."""
    import inspect

    from resireg_train.report.specs import (
        ENCODER_SWEEPS,
        SECTION_INPUTS,
        SECTION_SPECS,
        section_names,
    )

    for name, spec in SECTION_SPECS.items():
        for function in (spec.load(), spec.detector()):
            if function is not None:
                assert set(inspect.signature(function).parameters) <= set(SECTION_INPUTS), name
        assert spec.summary and (spec.detect or not spec.always), name
    assert section_names() == ("table1", "table2", "table3d", "prototype_grid", "layer_sweep",
                               "ovss8")
    assert ENCODER_SWEEPS == ("table1", "table2")


def test_a_report_section_added_through_the_table_is_written(tmp_path, monkeypatch):
    """The recipe of resireg_train.report.specs: one writer and one entry; a sweep config
    naming it (report: [...]) gets its file and its summary.md lines, in table order, and
    the config check accepts the name."""
    import resireg_train.report.specs as sections
    from resireg_train.checks.eval import EVAL_RULES

    def count_section(jobs, out):
        path = out / "count.txt"
        path.write_text(str(len(jobs)))
        return {"count": path}, ["", f"Jobs counted: `{path.name}`."]

    module = type(sys)("count_section_module")
    module.count_section = count_section
    monkeypatch.setitem(sys.modules, "count_section_module", module)
    entry = sections.SectionSpec("count", "count_section_module:count_section", "the job count")
    monkeypatch.setitem(sections.SECTION_SPECS, "count", entry)
    sweep = tmp_path / "sweep"
    for n in range(3):
        _saved_config(_job(sweep, n, {"seed": n}, {"status": "completed", "final": {}}),
                      ["count"])  # fmt: skip
    files = report(sweep)
    assert files["count"].read_text() == "3"
    assert "Jobs counted: `count.txt`." in files["md"].read_text()
    check, _ = EVAL_RULES["report"]
    assert check(["count"]) and not check(["cuont"])
