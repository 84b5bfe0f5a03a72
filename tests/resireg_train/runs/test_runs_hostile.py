"""`resireg-runs` under hostile input (issue 51, items 5, 6, 7, 9 and 10): each bad input is
handed to the real command (``resireg_train.cli.runs.main``, or the command in a process where
the error must reach the console) and refused in one line, without a traceback, and every
file of the inputs and of the other runs keeps its SHA-256.

One idea: ``resireg-runs`` under hostile input, each case refused in one line with every
input file's digest unchanged (one check shared by all cases)."""

from __future__ import annotations

import hashlib
import json
import os
import re
import socket
from pathlib import Path

import pytest
import yaml

from helpers.paths import ROOT
from resireg_train.cli.runs import main

SRC = ROOT / "src"


def _digests(*roots: Path) -> dict[str, str]:
    """SHA-256 of every file under ``roots`` (what must not change)."""
    found = {}
    for root in roots:
        paths = [root] if root.is_file() else sorted(p for p in root.rglob("*") if p.is_file())
        for path in paths:
            found[str(path)] = hashlib.sha256(path.read_bytes()).hexdigest()
    return found


def _refused(argv: list[str], capsys) -> str:
    """``resireg-runs argv``: exit status 2 and one line on stderr (returned)."""
    with pytest.raises(SystemExit) as exit_:
        main(argv)
    assert exit_.value.code == 2
    err = capsys.readouterr().err
    assert "Traceback" not in err and len(err.strip().splitlines()) == 1, err
    return err


def _eval_run(folder: Path, overrides: list[str], **provenance) -> Path:
    """A finished resireg-eval run folder with these recorded overrides."""
    (folder / ".hydra").mkdir(parents=True)
    (folder / ".hydra" / "overrides.yaml").write_text(yaml.safe_dump(overrides))
    record = {"name": "eval", "status": "completed", "final": {"loss": 1.0},
              "provenance": {"run_id": "f" * 12, "cli": "resireg-eval", **provenance}}  # fmt: skip
    (folder / "results.json").write_text(json.dumps(record))
    return folder


# ------------------------------------------------------------------------------ item 5
def test_a_rerun_refuses_a_bad_out_a_gone_export_and_the_run_folder_override(
    tmp_path, tiny_export, capsys
):
    other = _eval_run(tmp_path / "other", ["dataset=synthetic"])  # another run: never touched
    run = _eval_run(tmp_path / "run", ["dataset=synthetic", f"model_path={tiny_export}"])
    a_file = tmp_path / "afile"
    a_file.write_text("not a folder\n")
    before = _digests(tmp_path, tiny_export)

    err = _refused(["rerun", str(run), "--out", str(a_file)], capsys)
    assert f"--out {a_file}: not a folder" in err
    err = _refused(["rerun", str(run), "--out", str(a_file / "x")], capsys)
    assert f"--out {a_file / 'x'}: {a_file} is not a folder" in err
    err = _refused(["rerun", str(run), "--out", str(other)], capsys)
    assert "not empty" in err

    # the export it evaluated is gone: one line naming model_path and the folder, no drift list
    gone = tmp_path / "gone-export"
    files = {"model.safetensors": "a" * 64, "config.json": "b" * 64}
    files.update({f"extra{i}.json": "c" * 64 for i in range(90)})
    evaluation = _eval_run(tmp_path / "eval", ["dataset=synthetic", f"model_path={gone}"],
                           models={"export": {"path": str(gone), "files": files}})  # fmt: skip
    before.update(_digests(evaluation))
    err = _refused(["rerun", str(evaluation), "--out", str(tmp_path / "new")], capsys)
    assert f"model_path={gone}: no such export folder" in err and "<absent>" not in err
    err = _refused(["rerun", str(evaluation), "--out", str(tmp_path / "new"), "--allow-drift"],
                   capsys)  # fmt: skip
    assert f"model_path={gone}: no such export folder" in err  # a job could not start either

    # paths.output_dir recorded: refused for what it is, not as an unknown key
    moved = _eval_run(tmp_path / "moved", ["dataset=synthetic", "paths.output_dir=/tmp/x"])
    before.update(_digests(moved))
    err = _refused(["rerun", str(moved), "--out", str(tmp_path / "new")], capsys)
    assert "overrides[1]='paths.output_dir=/tmp/x' is refused" in err
    assert "${hydra:runtime.output_dir}" in err and "no such key" not in err
    assert not (tmp_path / "new").exists()
    assert _digests(tmp_path, tiny_export) == before


def test_a_rerun_into_a_folder_inside_another_run_or_map_is_refused(tmp_path, tiny_export, capsys):
    """rerun --out <a new folder inside another run's folder> (its .hydra/) or inside a map
    folder: refused in one line naming the folder it lies in, nothing written; a folder under
    another tool's results.json (no run record) is not another run's."""
    from resireg_train.record.run_record import target_problem

    other = _eval_run(tmp_path / "other", ["dataset=synthetic"])
    run = _eval_run(tmp_path / "run", ["dataset=synthetic", f"model_path={tiny_export}"])
    a_map = tmp_path / "a-map"
    a_map.mkdir()
    (a_map / "map.json").write_text("{}\n")
    before = _digests(tmp_path, tiny_export)
    for out, above in ((other / ".hydra" / "x", other), (a_map / "x", a_map)):
        err = _refused(["rerun", str(run), "--out", str(out), "--allow-drift"], capsys)
        assert f"--out {out}: inside the folder of another run or map ({above})" in err, err
        assert not out.exists()
    notes = tmp_path / "notes"
    notes.mkdir()
    (notes / "results.json").write_text("[1, 2]\n")
    assert target_problem(notes / "x", folder=True) is None
    assert _digests(tmp_path, tiny_export) == {**before, **_digests(notes)}


# ----------------------------------------------------------------------------- item 10
def _remote(root: Path, name: str, ahead_s: float, stale_after) -> Path:
    """A ``running`` record of another host, its heartbeat ``ahead_s`` seconds in the future
    (negative: in the past), its ``stale_after`` as given (JSON's NaN allowed)."""
    import datetime as dt

    folder = root / name
    (folder / "checkpoints").mkdir(parents=True)
    (folder / "checkpoints" / "last.ckpt").write_bytes(b"weights")
    beat = dt.datetime.now(dt.timezone.utc) + dt.timedelta(seconds=ahead_s)
    record = {"name": name, "status": "running", "final": {"loss": 1.0},
              "provenance": {"run_id": name, "cli": "resireg-train",
                             "machine": {"host": "node-17.cluster", "pid": 1}},
              "heartbeat": {"time": beat.isoformat(), "host": "node-17.cluster",
                            "interval": 30.0, "stale_after": stale_after}}  # fmt: skip
    (folder / "results.json").write_text(json.dumps(record))
    return folder


def test_ls_reports_a_heartbeat_from_the_future_or_never_stale_as_unknown(tmp_path, capsys):
    from resireg_train.record.settings import provenance_settings

    skew = float(provenance_settings()["heartbeat_skew"])
    assert 0 < skew <= 300  # conf/provenance/default.yaml: five minutes at most
    root = tmp_path / "outputs"
    _remote(root, "future", 30 * 86400, 300.0)  # another host's clock 30 days ahead
    _remote(root, "nan", -10, float("nan"))  # never stale: NaN compares False
    _remote(root, "negative", -10, -5.0)
    _remote(root, "zero", -10, 0)
    _remote(root, "a_bit_ahead", skew - 60, 300.0)  # within the skew: a running job's beat
    _remote(root, "fresh", -10, 300.0)
    before = _digests(root)
    main(["ls", str(root), "--format", "json", "--columns", "run_id,status"])
    captured = capsys.readouterr()
    statuses = {r["run_id"]: r["status"] for r in json.loads(captured.out)}
    assert statuses == {"future": "unknown", "nan": "unknown", "negative": "unknown",
                        "zero": "unknown", "a_bit_ahead": "running", "fresh": "running"}  # fmt: skip
    err = captured.err.splitlines()
    (future,) = [line for line in err if "/future/" in line]
    assert "days ahead of this machine's clock" in future and "heartbeat_skew=300" in future
    (nan,) = [line for line in err if "/nan/" in line]
    assert "heartbeat.stale_after=nan is not a number of seconds > 0" in nan
    assert len(err) == 4 and "Traceback" not in captured.err
    # gc never removes the checkpoints of a run that may still be running
    main(["gc", str(root), "--keep", "0", "--by", "loss"])
    capsys.readouterr()
    kept = {p.parent.parent.name for p in root.glob("*/checkpoints/last.ckpt")}
    assert kept == set(statuses)
    assert _digests(root) == before


def test_ls_reports_a_heartbeat_time_that_is_no_time_as_unknown(tmp_path, capsys):
    """A running record of another host whose heartbeat.time is NaN, a number or absent never
    ages (nothing to compare with the clock): listed 'unknown', naming the field, not running;
    gc keeps its checkpoints."""
    root = tmp_path / "outputs"
    for name, time in (("nan", float("nan")), ("text", "nan"), ("number", 12345)):
        folder = _remote(root, name, -10, 300.0)
        record = json.loads((folder / "results.json").read_text())
        record["heartbeat"]["time"] = time
        (folder / "results.json").write_text(json.dumps(record))
    folder = _remote(root, "absent", -10, 300.0)
    record = json.loads((folder / "results.json").read_text())
    del record["heartbeat"]["time"]
    (folder / "results.json").write_text(json.dumps(record))
    _remote(root, "fresh", -10, 300.0)
    before = _digests(root)
    main(["ls", str(root), "--format", "json", "--columns", "run_id,status"])
    captured = capsys.readouterr()
    statuses = {r["run_id"]: r["status"] for r in json.loads(captured.out)}
    assert statuses == {"nan": "unknown", "text": "unknown", "number": "unknown",
                        "absent": "unknown", "fresh": "running"}  # fmt: skip
    err = captured.err.splitlines()
    assert len(err) == 4 and "Traceback" not in captured.err, captured.err
    for name, shown in (("nan", "nan"), ("text", "'nan'"), ("number", "12345"),
                        ("absent", "None")):  # fmt: skip
        (line,) = [x for x in err if f"/{name}/" in x]
        assert f"heartbeat.time={shown} is not a time (ISO 8601)" in line, line
        assert "listed as 'unknown', not running" in line
    main(["gc", str(root), "--keep", "0", "--by", "loss"])
    capsys.readouterr()
    assert {p.parent.parent.name for p in root.glob("*/checkpoints/last.ckpt")} == set(statuses)
    assert _digests(root) == before


# ------------------------------------------------------------------------------ item 9
def _train_run(folder: Path, csv_text: str) -> Path:
    folder.mkdir(parents=True)
    record = {"name": "t", "status": "completed", "final": {"train/loss": 0.25},
              "provenance": {"run_id": folder.name, "cli": "resireg-train"}}  # fmt: skip
    (folder / "results.json").write_text(json.dumps(record))
    (folder / "metrics.csv").write_text(csv_text)
    return folder


def test_plot_leaves_out_points_it_cannot_draw_and_refuses_a_bad_out(tmp_path, capsys):
    from resireg_train.runs.index import read_run
    from resireg_train.runs.plots import plot_runs

    steps = _train_run(tmp_path / "steps", "step,train/loss\n0,1.0\n1e308,0.5\n-1e308,0.4\n"
                       "2,0.3\n")  # fmt: skip
    values = _train_run(tmp_path / "values", "step,train/loss\n0,1.7e308\n1,-1.7e308\n2,0.2\n"
                        "3,nan\n4,\n")  # fmt: skip
    a_file = tmp_path / "afile"
    a_file.write_text("not a folder\n")
    before = _digests(tmp_path)
    out = tmp_path / "curves.png"
    main(["plot", str(steps), str(values), "--metric", "train/loss", "--out", str(out)])
    captured = capsys.readouterr()
    assert captured.out.strip() == str(out) and out.stat().st_size > 0
    warned = captured.err.strip().splitlines()
    assert len(warned) == 2 and "Traceback" not in captured.err, captured.err
    assert "run steps (" in warned[0] and "train/loss: 2 point(s)" in warned[0]
    assert "step=1e308 value=0.5" in warned[0] and "step=-1e308 value=0.4" in warned[0]
    assert "run values (" in warned[1] and "train/loss: 3 point(s)" in warned[1]  # +-1.7e308, nan
    # what is drawn: the finite points within float32's range, read back from the figure
    drawn = plot_runs([read_run(steps), read_run(values)], ["train/loss"], tmp_path / "b.png")
    curves = list(drawn.curves["train/loss"].values())
    assert curves == [([0.0, 2.0], [1.0, 0.3]), ([2.0], [0.2])]
    (tmp_path / "b.png").unlink()

    for option, target, expected in (("--out", a_file / "x.png", f"{a_file} is not a folder"),
                                     ("--out", tmp_path, "a folder, not a file"),
                                     ("--html", a_file / "x.html", f"{a_file} is not a folder")):  # fmt: skip
        argv = ["plot", str(steps), "--metric", "train/loss", option, str(target)]
        if option == "--html":
            argv += ["--out", str(tmp_path / "c.png")]
        err = _refused(argv, capsys)
        assert f"{option} {target}: {expected}" in err
        assert not (tmp_path / "c.png").exists()  # refused before drawing
    out.unlink()
    assert _digests(tmp_path) == before


def test_plot_names_points_whose_step_or_value_is_text(tmp_path, capsys):
    """metrics.csv with a word or nothing in the step column of a row holding a value, and a
    word as a value: those points cannot be drawn and are named (not lost in silence); a row
    whose value cell is empty is no point (the metric was not logged at that step)."""
    from resireg_train.runs.index import read_run
    from resireg_train.runs.plots import plot_runs

    run = _train_run(tmp_path / "text", "step,train/loss,other\n0,1.0,\nabc,0.5,\n,0.4,\n"
                     "3,high,\n4,,7\nxyz,,8\n5,0.2,\n")  # fmt: skip
    before = _digests(tmp_path)
    out = tmp_path / "curves.png"
    main(["plot", str(run), "--metric", "train/loss", "--out", str(out)])
    captured = capsys.readouterr()
    assert captured.out.strip() == str(out) and "Traceback" not in captured.err
    (warned,) = captured.err.strip().splitlines()
    assert "run text (" in warned and "train/loss: 3 point(s) of metrics.csv:train/loss" in warned
    assert "step=abc value=0.5, step= value=0.4, step=3 value=high" in warned, warned
    drawn = plot_runs([read_run(run)], ["train/loss"], tmp_path / "b.png")
    assert list(drawn.curves["train/loss"].values()) == [([0.0, 5.0], [1.0, 0.2])]
    out.unlink()
    (tmp_path / "b.png").unlink()
    assert _digests(tmp_path) == before


# ------------------------------------------------------------------------------ item 7
_ROW = "resireg_vlm: {params_m: 25, ade20k: {bb: 12.5}}"


@pytest.mark.parametrize(
    ("text", "key", "held"),
    [
        (f"j: &j {{a: 1}}\ntable1:\n  datasets: *j\n  rows: {{{_ROW}}}\n",
         "table1.datasets: expected a list of dataset names", "a mapping"),
        ("j: &j [ade20k]\ntable1:\n  datasets: *j\n  rows: {resireg_vlm: *j}\n",
         "table1.rows.resireg_vlm: expected a mapping", "a list"),
        ("j: &j [1, 2]\ntable1:\n  datasets: [ade20k]\n  rows:\n"
         "    resireg_vlm: {ade20k: {bb: *j}}\n",
         "table1.rows.resireg_vlm.ade20k.bb: expected a number or null", "a list"),
        ("j: &j {x: 1}\ntable1:\n  datasets: [ade20k]\n  rows: *j\n",
         "table1.rows.x: expected a mapping", "int"),
        ("j: &j [ade20k]\ntable1: *j\n", "table1: expected a mapping", "a list"),
        (f"j: &j {{a: 1}}\ntable1:\n  datasets: [ade20k]\n  rows: {{{_ROW}}}\n"
         "protocol: {table1: {short_side: *j}}\n",
         "protocol.table1.short_side: expected a value or a list of values", "a mapping"),
    ],
)  # fmt: skip
def test_reproduce_refuses_a_paper_file_off_its_schema_naming_the_key(
    tmp_path, capsys, text, key, held
):
    paper = tmp_path / "paper.yaml"
    paper.write_text(text)
    before = _digests(tmp_path)
    out = tmp_path / "sweep"
    err = _refused(["reproduce", "table1/resireg_vlm", "--paper", str(paper), "--out", str(out)],
                   capsys)  # fmt: skip
    assert f"--paper {paper}: {key}, got {held}" in err, err
    assert not out.exists() and _digests(tmp_path) == before


@pytest.mark.parametrize(
    ("text", "says"),
    [
        ("table1: !!python/object/apply:os.system [echo]\n",
         "could not determine a constructor for the tag"),
        ("table1: [unclosed\n", "while parsing a flow sequence"),
    ],
)  # fmt: skip
def test_reproduce_refuses_a_paper_file_that_is_not_yaml_in_one_line(tmp_path, capsys, text, says):
    """A figures file YAML cannot read (a Python tag, a broken flow list): PyYAML's message
    spans lines (the place on its own line); the refusal is one line naming the file."""
    paper = tmp_path / "paper.yaml"
    paper.write_text(text)
    before = _digests(tmp_path)
    out = tmp_path / "sweep"
    err = _refused(["reproduce", "table1/resireg_vlm", "--paper", str(paper), "--out", str(out)],
                   capsys)  # fmt: skip
    assert f"--paper {paper}: not a paper file (" in err and says in err, err
    assert f'in "{paper}", line 1' in err, err
    assert not out.exists() and _digests(tmp_path) == before


def test_the_papers_own_figures_file_fits_the_schema():
    from resireg_train.report.paper import paper_results
    from resireg_train.runs.reproduce import paper_problems

    assert paper_problems(paper_results()) == []


# ------------------------------------------------------------------------------ item 6
def _closed_port() -> int:
    """A port of 127.0.0.1 nothing listens on (bound, then released)."""
    with socket.socket() as s:
        s.bind(("127.0.0.1", 0))
        return s.getsockname()[1]


def test_register_checks_the_name_and_the_registry_before_writing(tmp_path, tiny_export, capsys):
    pytest.importorskip("mlflow")
    store = tmp_path / "registry.db"
    before = _digests(tiny_export)
    for argv, expected in (
        (["--name", "../x"], "--name '../x': Invalid model name '../x'"),
        (["--name", ".."], "--name '..': not a registered model's name"),
        (["--name", "a@b"], "--name 'a@b': not a registered model's name"),
        (["--name", "ok", "--alias", "../a"], "--alias '../a': Invalid alias name"),
        (["--name", "ok", "--alias", "latest"], "--alias 'latest'"),  # MLflow's reserved alias
    ):  # fmt: skip
        err = _refused(["register", str(tiny_export), *argv, "--tracking-uri",
                        f"sqlite:///{store}"], capsys)  # fmt: skip
        assert expected in err, err
        assert not store.exists()  # nothing written, not even an empty store
    # a registry that does not answer: one line (the trackers' check), not minutes of retries
    port = _closed_port()
    err = _refused(["register", str(tiny_export), "--name", "ok", "--tracking-uri",
                    f"http://127.0.0.1:{port}"], capsys)  # fmt: skip
    assert f"cannot reach the model registry http://127.0.0.1:{port}" in err
    assert "tracker.mlflow.check_timeout" in err
    assert _digests(tiny_export) == before


@pytest.mark.slow
def test_register_keeps_its_files_beside_a_sqlite_store(tmp_path, tiny_export, monkeypatch,
                                                      capsys):  # fmt: skip
    """``resireg-runs register`` into ``sqlite:///<folder>/registry.db`` started from another
    folder: the registration's files go to ``<folder>/mlartifacts`` (the trackers' rule,
    ``resireg_train.record.trackers.mlflow.artifact_location``), nothing into the current folder."""
    pytest.importorskip("mlflow")
    from mlflow import MlflowClient

    store = tmp_path / "store"
    store.mkdir()
    elsewhere = tmp_path / "elsewhere"
    elsewhere.mkdir()
    monkeypatch.chdir(elsewhere)
    uri = f"sqlite:///{store / 'registry.db'}"
    main(["register", str(tiny_export), "--name", "tiny", "--tracking-uri", uri])
    assert "registered" in capsys.readouterr().out
    assert list(elsewhere.iterdir()) == []
    (run,) = MlflowClient(tracking_uri=uri).search_runs(
        [MlflowClient(tracking_uri=uri).get_experiment_by_name("resireg").experiment_id])
    assert run.info.artifact_uri.startswith((store / "mlartifacts").as_uri())
    stored = {p.name for p in (store / "mlartifacts").rglob("*") if p.is_file()}
    assert {"config.json", "model.safetensors"} <= stored


def test_a_registration_that_fails_midway_is_marked_failed(tmp_path, tiny_export, capsys):
    """The artifact store cannot be written (a file where its folder should be): the
    registration's MLflow run is marked FAILED, no model version is left, one line says so."""
    pytest.importorskip("mlflow")
    from mlflow import MlflowClient

    uri = f"sqlite:///{tmp_path / 'registry.db'}"
    blocker = tmp_path / "blocker"
    blocker.write_text("a file\n")
    client = MlflowClient(tracking_uri=uri, registry_uri=uri)
    experiment = client.create_experiment("broken", artifact_location=str(blocker / "artifacts"))
    capsys.readouterr()  # MLflow's own log of the store it created
    before = _digests(tiny_export, blocker)
    err = _refused(["register", str(tiny_export), "--name", "tiny", "--experiment", "broken",
                    "--tracking-uri", uri], capsys)  # fmt: skip
    (run,) = client.search_runs([experiment])
    assert f"--name tiny: the registration failed and its MLflow run {run.info.run_id} is " \
           "marked FAILED" in err  # fmt: skip
    assert run.info.status == "FAILED" and run.data.tags["resireg.registration"] == "failed"
    assert client.search_model_versions("name='tiny'") == []
    assert _digests(tiny_export, blocker) == before


def test_a_library_load_from_an_unreachable_registry_fails_at_once(tmp_path, monkeypatch):
    """``ResiregVLM.from_pretrained("models:/NAME@ALIAS")`` (resireg-segment's and the ROS 2
    node's path, without resireg_train) with MLFLOW_TRACKING_URI on a closed port: refused by
    the trackers' connection check within ``tracker.mlflow.check_timeout`` (2 s here), one
    error naming the URI (password masked) and the settings to change, instead of minutes of
    MLflow's retries. The bound on the time is a bound on a hang, not a speed test."""
    pytest.importorskip("mlflow")
    import time

    from resireg.models.vlm.model import ResiregVLM
    from resireg.models.vlm.registry import RegistryError

    conf = tmp_path / "conf"
    (conf / "tracker").mkdir(parents=True)
    (conf / "tracker" / "mlflow.yaml").write_text("mlflow:\n  check_timeout: 2\n")
    monkeypatch.setenv("RESIREG_CONFIG_DIR", str(conf))
    port = _closed_port()
    monkeypatch.setenv("MLFLOW_TRACKING_URI", f"http://someone:hunter2@127.0.0.1:{port}")
    monkeypatch.delenv("MLFLOW_REGISTRY_URI", raising=False)
    monkeypatch.setenv("RESIREG_REGISTRY_CACHE", str(tmp_path / "cache"))
    started = time.monotonic()
    with pytest.raises(RegistryError) as caught:
        ResiregVLM.from_pretrained("models:/x@a")
    assert time.monotonic() - started < 30
    message = str(caught.value)
    assert len(message.splitlines()) == 1, message
    assert "hunter2" not in message
    assert f"'models:/x@a': cannot reach the model registry http://someone:***@127.0.0.1:{port}" \
        in message  # fmt: skip
    assert "MLFLOW_TRACKING_URI" in message and "(the wait, 2 s: tracker.mlflow.check_timeout)" \
        in message  # fmt: skip
    assert not (tmp_path / "cache").exists()  # nothing downloaded, no folder made


@pytest.mark.slow
def test_a_registered_model_path_fails_in_one_line(tmp_path, tiny_export, capsys):
    """resireg-eval model_path=models:/...: a URI of neither form, a registry on a closed port
    and a registered model.safetensors altered in the artifact store each end the command in
    one line naming it; an earlier record in the run folder is not touched."""
    pytest.importorskip("mlflow")
    from mlflow import MlflowClient

    from helpers.run import run_side_by_side

    uri = f"sqlite:///{tmp_path / 'registry.db'}"
    client = MlflowClient(tracking_uri=uri, registry_uri=uri)
    client.create_experiment("resireg", artifact_location=str(tmp_path / "artifacts"))
    main(["register", str(tiny_export), "--name", "tiny", "--alias", "champion",
          "--tracking-uri", uri])  # fmt: skip
    capsys.readouterr()
    (stored,) = (tmp_path / "artifacts").rglob("model.safetensors")
    stored.write_bytes(stored.read_bytes()[:-8] + b"\1" * 8)
    earlier = {"status": "completed", "final": {"loss": 1.0}}
    folders = [tmp_path / f"eval{i}" for i in range(3)]
    for folder in folders:
        folder.mkdir()
        (folder / "results.json").write_text(json.dumps(earlier))
    before = _digests(tiny_export, tmp_path / "registry.db")
    common = ["dataset=synthetic", "dataset.size=2", "num_workers=0"]
    env = {**os.environ, "PYTHONPATH": f"{SRC}{os.pathsep}{os.environ.get('PYTHONPATH', '')}",
           "RESIREG_REGISTRY_CACHE": str(tmp_path / "cache"), "MLFLOW_TRACKING_URI": uri}  # fmt: skip
    closed = {**env, "MLFLOW_TRACKING_URI": f"http://127.0.0.1:{_closed_port()}"}
    procs = [
        run_side_by_side(("resireg-eval", "model_path=models:/../x@a", *common,
                          f"hydra.run.dir={folders[0]}"), check=False, env=env)[0],
        run_side_by_side(("resireg-eval", "model_path=models:/tiny@champion", *common,
                          f"hydra.run.dir={folders[1]}"), check=False, env=closed)[0],
        run_side_by_side(("resireg-eval", "model_path=models:/tiny@champion", *common,
                          f"hydra.run.dir={folders[2]}"), check=False, env=env)[0],
    ]  # fmt: skip
    expected = [
        "ConfigError: model_path: 'models:/../x@a' is not a model registry URI",
        "RegistryError: model_path='models:/tiny@champion': cannot reach the model registry",
        "model.safetensors",
    ]
    for proc, text in zip(procs, expected, strict=True):
        assert proc.returncode != 0 and "Traceback" not in proc.stderr, proc.stderr[-3000:]
        errors = [line for line in proc.stderr.splitlines() if re.match(r"[\w.]+Error: ", line)]
        assert len(errors) == 1 and text in errors[0], proc.stderr[-3000:]
    assert "IntegrityError" in procs[2].stderr
    for folder in folders[:2]:  # refused before the run started: the earlier record as it was
        assert json.loads((folder / "results.json").read_text()) == earlier
    assert _digests(tiny_export, tmp_path / "registry.db") == before
    assert not any((tmp_path / "cache").rglob("model.safetensors"))  # no altered copy kept
