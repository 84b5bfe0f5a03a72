"""`resireg-runs rerun` and `resireg-runs reproduce` (issue 47 items 1 and 2): a smoke training,
an evaluation and a map rerun bitwise identical on this CPU; a code change refused by name,
then run with --allow-drift and recorded; a changed setting reported as "differs" with the
metric that moved; a masked secret and a hostile override refused; a fixture paper row
reproduced on synthetic data, and a missing dataset or model refused before any job starts.

The runs happen in a git copy of the project's packages (as tests/resireg_train/runs/test_runs.py makes one), so
the code the record names is the copy's, which this test alone changes."""

from __future__ import annotations

import hashlib
import json
import math
import os
import shutil
import struct
import subprocess
import sys
from pathlib import Path

import pytest
import yaml

from helpers.paths import ROOT
from helpers.run import run

SRC = ROOT / "src"
CONF = SRC.parent / "conf"
pytestmark = pytest.mark.skipif(shutil.which("git") is None, reason="needs git")

SMOKE = ["experiment=smoke", "trainer.max_epochs=1", "data.steps_per_epoch=2"]


def _git(repo, *args):
    return subprocess.run(["git", "-C", str(repo), *args], check=True, capture_output=True,
                          text=True).stdout.strip()  # fmt: skip


@pytest.fixture(scope="module")
def project(tmp_path_factory):
    """A git checkout holding a copy of the project's packages; its environment runs them
    (conf/ stays the project's: RESIREG_CONFIG_DIR)."""
    repo = tmp_path_factory.mktemp("project")
    shutil.copytree(SRC, repo / "src", ignore=shutil.ignore_patterns("__pycache__", "*.egg-info"))
    _git(repo, "init", "-q", "-b", "main")
    _git(repo, "-c", "user.name=t", "-c", "user.email=t@t", "add", "-A")
    _git(repo, "-c", "user.name=t", "-c", "user.email=t@t", "commit", "-qm", "copy")
    env = {**os.environ, "PYTHONPATH": str(repo / "src"), "RESIREG_CONFIG_DIR": str(CONF),
           "HF_HUB_OFFLINE": "1", "OMP_NUM_THREADS": "1", "MKL_NUM_THREADS": "1"}  # fmt: skip
    return repo, env


def _run(env, module, *args, check=True, threads=None):
    """``python -m module args`` from the copy (``threads``: OMP_NUM_THREADS)."""
    return run(sys.executable, "-m", module, *args, env=env, threads=threads, check=check,
               timeout=900)  # fmt: skip


def _rerun(env, *args, check=None):
    """``resireg-runs rerun args`` (its exit status checked against ``check`` when given)."""
    proc = _run(env, "resireg_train.cli.runs", "rerun", *args, check=False, threads=2)
    if check is not None:
        assert proc.returncode == check, proc.stdout[-3000:] + proc.stderr[-3000:]
    return proc


def _record(folder):
    return json.loads((Path(folder) / "results.json").read_text())


def _sha(path):
    return hashlib.sha256(Path(path).read_bytes()).hexdigest()


def _verdict(proc):
    return next(line for line in proc.stdout.splitlines() if line.startswith("verdict: "))


@pytest.mark.slow
def test_a_smoke_training_rerun_is_bitwise_identical_then_drift_and_a_moved_metric(
    project, tmp_path
):
    repo, env = project
    run = tmp_path / "run"
    # the run: one torch thread (recorded; the rerun's job gets it whatever its environment)
    _run(env, "resireg_train.cli.train", *SMOKE, f"hydra.run.dir={run}", threads=1)
    original = _record(run)
    assert original["provenance"]["machine"]["torch_threads"] == 1
    assert original["provenance"]["code"]["git"]["root"] == str(repo.resolve())

    same = tmp_path / "same"
    proc = _rerun(env, run, "--out", same, check=0)
    assert _verdict(proc).startswith("verdict: identical")
    again = _record(same)
    # every score and the exported weights, bit for bit (independently of the verdict)
    assert json.dumps(again["final"]) == json.dumps(original["final"]) and original["final"]
    assert json.dumps(again["best"]) == json.dumps(original["best"])
    assert _sha(same / "export" / "model.safetensors") == _sha(run / "export" / "model.safetensors")
    assert again["provenance"]["machine"]["torch_threads"] == 1
    assert again["rerun"]["of"] == {"run_id": original["provenance"]["run_id"], "path": str(run)}
    assert again["rerun"]["verdict"] == "identical" and again["rerun"]["drift"] == []
    # the job ran from the rebuilt overrides, in its new folder, as one run
    overrides = yaml.safe_load((same / ".hydra" / "overrides.yaml").read_text())
    assert overrides == yaml.safe_load((run / ".hydra" / "overrides.yaml").read_text())

    # A tracked file changes: refused, naming it, nothing written.
    changed = repo / "src" / "resireg_train" / "record" / "cards.py"
    text = changed.read_text()
    changed.write_text(text + "\n# a local experiment\n")
    try:
        _refused_then_drift_and_moved(env, run, original, tmp_path)
    finally:  # the copy's code as committed again, for the module's other tests
        changed.write_text(text)


def _refused_then_drift_and_moved(env, run, original, tmp_path):
    refused = tmp_path / "refused"
    proc = _rerun(env, run, "--out", refused, check=2)
    assert "refused" in proc.stderr and "src/resireg_train/record/cards.py" in proc.stderr
    assert "--allow-drift" in proc.stderr and not refused.exists()
    # ... accepted with --allow-drift and a setting changed: the drift recorded, the verdict
    # "differs" with the moved metrics
    moved = tmp_path / "moved"
    proc = _rerun(env, run, "--out", moved, "--allow-drift", "model.optimizer.lr=0.02", check=1)
    assert _verdict(proc).startswith("verdict: differs")
    record = _record(moved)
    drift = record["rerun"]["drift"]
    assert any("src/resireg_train/record/cards.py" in line for line in drift), drift
    assert record["rerun"]["allowed_drift"] is True
    assert record["provenance"]["code"]["git"]["changes"][0]["path"] == (
        "src/resireg_train/record/cards.py")  # fmt: skip
    loss = record["rerun"]["moved"]["final/train/loss"]
    assert loss == {"run": original["final"]["train/loss"], "rerun": record["final"]["train/loss"],
                    "change": loss["change"]}  # fmt: skip
    assert loss["run"] != loss["rerun"]
    assert float(loss["change"].split(",")[0]) == pytest.approx(
        loss["rerun"] - loss["run"], rel=1e-5
    )
    assert f"final/train/loss: {loss['run']:.8g} -> {loss['rerun']:.8g}" in proc.stdout
    assert "model.optimizer.lr: 0.003 -> 0.02" in proc.stdout  # the config that differs


@pytest.fixture(scope="module")
def room_bag(tmp_path_factory):
    from resireg_train.data.room_bag import TOPICS, room_frames, write_bag

    bag = write_bag(tmp_path_factory.mktemp("bag") / "room", room_frames(4))
    topics = [f"source.colour_topic={TOPICS['colour']}", f"source.depth_topic={TOPICS['depth']}",
              f"source.camera_info_topic={TOPICS['info']}"]  # fmt: skip
    return bag, topics


@pytest.mark.slow
def test_an_evaluation_and_a_map_rerun_identical(project, tmp_path, tiny_export, room_bag):
    _, env = project
    evaluation = tmp_path / "eval"
    _run(env, "resireg_train.cli.eval", f"model_path={tiny_export}", "dataset=synthetic",
         "dataset.size=4", "num_workers=0", "full.n_prototypes=4",
         f"hydra.run.dir={evaluation}", threads=1)  # fmt: skip
    proc = _rerun(env, evaluation, "--out", tmp_path / "eval2", check=0)
    assert _verdict(proc).startswith("verdict: identical")
    a, b = _record(evaluation), _record(tmp_path / "eval2")
    assert json.dumps(a["final"]) == json.dumps(b["final"]) and len(a["final"]) == 6
    assert json.dumps(a["per_class_iou"]) == json.dumps(b["per_class_iou"])

    bag, topics = room_bag
    mapped = tmp_path / "map"
    _run(env, "resireg_train.cli.map", f"model_path={tiny_export}", "device=cpu",
         "source=rosbag", f"source.path={bag}", *topics, "variant=full", "window=2",
         f"hydra.run.dir={mapped}", threads=1)  # fmt: skip
    proc = _rerun(env, mapped, "--out", tmp_path / "map2", check=0)
    assert _verdict(proc).startswith("verdict: identical")
    a, b = _record(mapped), _record(tmp_path / "map2")
    assert {k: a["map"][k] for k in ("voxels", "bytes", "frames")} == {
        k: b["map"][k] for k in ("voxels", "bytes", "frames")}  # fmt: skip
    assert _sha(mapped / "map.ply") == _sha(tmp_path / "map2" / "map.ply")
    (ta,), (tb,) = (mapped / "map").glob("*.safetensors"), (tmp_path / "map2" / "map").glob(
        "*.safetensors")  # fmt: skip
    assert _sha(ta) == _sha(tb)  # the map's tensors, bit for bit (their file names are drawn)


def _fake_eval_run(folder, overrides, **provenance):
    """A finished resireg-eval run folder with these recorded overrides."""
    (folder / ".hydra").mkdir(parents=True)
    (folder / ".hydra" / "overrides.yaml").write_text(yaml.safe_dump(overrides))
    record = {"name": "eval", "status": "completed", "final": {},
              "provenance": {"run_id": "f" * 12, "cli": "resireg-eval", **provenance}}  # fmt: skip
    (folder / "results.json").write_text(json.dumps(record))
    return folder


def test_a_recorded_override_is_checked_as_a_search_worker_checks_it(tmp_path, capsys):
    from resireg_train.cli.runs import main

    # an override given on the command line that Hydra does not read, or that the job's config
    # refuses: one line naming it, nothing started
    folder = _fake_eval_run(tmp_path / "ok", ["dataset=synthetic"])
    for given, message in (("dataset=[", "override 'dataset=[': not a key=value Hydra reads"),
                           ("nonkey=3", "Could not override 'nonkey'")):  # fmt: skip
        with pytest.raises(SystemExit) as exit_:
            main(["rerun", str(folder), "--out", str(tmp_path / "given"), given])
        assert exit_.value.code == 2
        err = capsys.readouterr().err
        assert message in err and "Traceback" not in err and len(err.splitlines()) == 1, err
        assert not (tmp_path / "given").exists()

    hostile = [
        ("+callbacks.x._target_=os.system", "names a class to instantiate"),
        ("hydra.run.dir=/etc", "sets Hydra's own config"),
        ("model_path=${oc.env:HOME}", "interpolation"),
        ("batch_sise=4", "resireg-eval's config has no such key"),
    ]
    for i, (override, reason) in enumerate(hostile):
        folder = _fake_eval_run(tmp_path / f"run{i}", ["dataset=synthetic", override])
        with pytest.raises(SystemExit) as exit_:
            main(["rerun", str(folder), "--out", str(tmp_path / f"out{i}")])
        assert exit_.value.code == 2
        err = capsys.readouterr().err
        assert reason in err and repr(override) in err, err  # the entry and why, named
        assert not (tmp_path / f"out{i}").exists()  # refused before anything ran
    # the message names the file and the entry (captured through stderr)
    proc = run(sys.executable, "-m", "resireg_train.cli.runs", "rerun", tmp_path / "run0",
               "--out", tmp_path / "x", check=False, env={**os.environ, "PYTHONPATH": str(SRC)})  # fmt: skip
    assert proc.returncode == 2
    assert (
        "overrides.yaml: overrides[1]='+callbacks.x._target_=os.system' is refused" in proc.stderr
    )


def test_a_masked_secret_is_never_rebuilt_from_the_record(tmp_path):
    """The record masks a URL's password; the rerun drops the mask (the tracker takes the
    password from the environment) and refuses any other masked value."""
    from resireg_train.runs.index import read_run
    from resireg_train.runs.rerun.plan import RerunRefused, _recorded_overrides

    uri = "tracker.mlflow.tracking_uri=http://ana:***@mlflow.lab:5000"
    run = read_run(_fake_eval_run(tmp_path / "a", ["dataset=synthetic", "tracker=mlflow", uri]))
    kept = _recorded_overrides(run, "eval", [])
    assert kept == ["dataset=synthetic", "tracker=mlflow",
                    "tracker.mlflow.tracking_uri=http://ana@mlflow.lab:5000"]  # fmt: skip
    # given again on the command line, the user's value replaces the record's
    assert _recorded_overrides(run, "eval", ["tracker.mlflow.tracking_uri=sqlite:///x.db"]) == [
        "dataset=synthetic", "tracker=mlflow"]  # fmt: skip
    query = 'tracker.mlflow.tracking_uri="http://mlflow.lab:5000/?token=***"'
    run = read_run(_fake_eval_run(tmp_path / "b", ["tracker=mlflow", query]))
    with pytest.raises(RerunRefused, match="masked secret.*tracker.mlflow.tracking_uri=..."):
        _recorded_overrides(run, "eval", [])


def _paper_file(tmp_path, datasets, row, protocol):
    path = tmp_path / "paper.yaml"
    path.write_text(yaml.safe_dump({"table1": {"datasets": datasets, "rows": {"resireg_vlm": row}},
                                    "protocol": {"table1": protocol}}))  # fmt: skip
    return path


@pytest.mark.slow
def test_reproduce_a_fixture_paper_row_on_synthetic_data(tmp_path, tiny_export):
    paper = _paper_file(tmp_path, ["synthetic"], {"params_m": 1, "synthetic": {"bb": 12.5,
                        "full": 30.0}}, {"short_side": 576, "temperature": 100.0})  # fmt: skip
    out = tmp_path / "sweep"
    env = {**os.environ, "PYTHONPATH": str(SRC), "HF_HUB_OFFLINE": "1"}
    proc = _run(env, "resireg_train.cli.runs", "reproduce", "table1/resireg_vlm",
                "--paper", paper, "--out", out, f"model_path={tiny_export}", "num_workers=0",
                "dataset.size=4", "full.n_prototypes=4", threads=2)  # fmt: skip
    (job,) = [p for p in out.iterdir() if (p / "results.json").is_file()]
    record = _record(job)
    assert record["status"] == "completed"
    assert record["params"]["variants"] == ["bb", "full"]  # the variants the row reports
    assert record["name"] == "table1"  # the table's own sweep file ran
    rows = {}
    for line in proc.stdout.splitlines():
        parts = line.split()
        if len(parts) == 5 and parts[0] == "synthetic":
            rows[parts[1]] = tuple(float(x) for x in parts[2:])
    for variant, paper_value in (("bb", 12.5), ("full", 30.0)):
        yours = 100 * record["final"][f"val/ovss/synthetic/miou_{variant}"]
        assert rows[variant] == pytest.approx((yours, paper_value, yours - paper_value), abs=6e-3)
    # the protocol settings that differ from the paper's, as resireg-report lists them
    short_side = record["protocol"]["settings"]["short_side"]
    assert short_side != 576 and f"short_side={short_side} (paper: 576): job 0" in proc.stdout
    assert "temperature" not in proc.stdout  # the same as the paper's


def test_reproduce_refuses_a_missing_dataset_and_model_before_any_job(tmp_path):
    from resireg_train.cli.runs import main

    paper = _paper_file(tmp_path, ["orad3d"], {"orad3d": {"bb": 19.85}}, {"short_side": 576})
    out = tmp_path / "sweep"
    proc = run(sys.executable, "-m", "resireg_train.cli.runs", "reproduce", "table1/resireg_vlm",
               "--paper", paper, "--out", out, f"model_path={tmp_path / 'no_export'}",
               f"paths.data_dir={tmp_path / 'no_data'}", check=False,
               env={**os.environ, "PYTHONPATH": str(SRC)})  # fmt: skip
    assert proc.returncode == 2, proc.stderr
    err = proc.stderr
    assert "no job was started" in err and not out.exists()
    assert f"dataset=orad3d: dataset.path='{tmp_path / 'no_data'}/ORAD-3D'" in err, err
    assert "download ORAD-3D" in err and "set dataset.path" in err
    assert f"model_path='{tmp_path / 'no_export'}'" in err and "set model_path" in err
    with pytest.raises(SystemExit) as exit_:  # a row the paper file does not hold
        main(["reproduce", "table1/radseg", "--paper", str(paper)])
    assert exit_.value.code == 2


def _scored_run(folder, final, status="completed"):
    """A finished evaluation run folder whose record holds the scores ``final``."""
    _fake_eval_run(folder, ["dataset=synthetic"])
    record = json.loads((folder / "results.json").read_text())
    (folder / "results.json").write_text(json.dumps({**record, "final": final, "status": status}))
    return folder


@pytest.mark.parametrize(
    ("then", "now", "rtol"),
    [
        (0.5, 0.5, 1e-6),  # bitwise equal
        (0.5, 0.5 + 3e-8, 1e-6),  # within rtol: a GPU's non-deterministic kernels
        (0.5, 0.5 + 3e-8, 1e-9),  # the same change, beyond a tighter rtol
        (0.5, 0.6, 1e-6),
        (0.5, float("nan"), 1e-6),  # NaN on one side: never within tolerance
    ],
)
def test_the_verdict_of_two_records_follows_the_relative_tolerance(tmp_path, then, now, rtol):
    """compare() on two records that differ in one score by a chosen amount: the verdict is
    the one math.isclose (relative to the larger magnitude, no absolute floor) gives, the
    unchanged score is not listed, and the moved score's printed change is the difference."""
    from resireg_train.runs.index import read_run
    from resireg_train.runs.rerun.verdict import compare

    a = read_run(_scored_run(tmp_path / "a", {"ovss/synthetic/miou_bb": then, "loss": 1.25}))
    b = read_run(_scored_run(tmp_path / "b", {"ovss/synthetic/miou_bb": now, "loss": 1.25}))
    verdict = compare(a, b, rtol)
    equal = struct.pack("<d", then) == struct.pack("<d", now)
    close = not math.isnan(now) and math.isclose(then, now, rel_tol=rtol, abs_tol=0.0)
    expected = "identical" if equal else "within tolerance" if close else "differs"
    assert verdict.kind == expected
    assert verdict.compared == 2
    listed = [row[0] for row in (*verdict.moved, *verdict.nudged)]
    assert listed == ([] if equal else ["final/ovss/synthetic/miou_bb"])
    assert verdict.lines()[0].startswith(f"verdict: {expected}")
    if expected == "differs" and not math.isnan(now):
        ((key, x, y, change),) = verdict.moved
        assert (x, y) == (then, now) and change.startswith(f"{now - then:+.6g}")


def test_a_failed_rerun_differs_whatever_its_scores(tmp_path):
    from resireg_train.runs.index import read_run
    from resireg_train.runs.rerun.verdict import compare

    a = read_run(_scored_run(tmp_path / "a", {"loss": 1.0}))
    b = read_run(_scored_run(tmp_path / "b", {"loss": 1.0}, status="failed"))
    verdict = compare(a, b, 1e-6)
    assert verdict.kind == "differs" and "status completed -> failed" in verdict.lines()[0]


@pytest.mark.slow
def test_a_rerun_after_the_model_changed_is_refused_then_allowed(project, tmp_path, tiny_export):
    """The export an evaluation ran with is replaced by another model at the same path: the
    rerun is refused before any job, naming the input whose digest moved; --allow-drift runs
    it and records the drift in the new run."""
    import torch

    from helpers.tiny import TINY_BACKBONE, TINY_HEAD, TINY_TEXT
    from resireg.models import ResiregVLM

    _, env = project
    export = tmp_path / "export"
    shutil.copytree(tiny_export, export)
    evaluation = tmp_path / "eval"
    _run(env, "resireg_train.cli.eval", f"model_path={export}", "dataset=synthetic",
         "dataset.size=4", "num_workers=0", "variants=[bb]", f"hydra.run.dir={evaluation}",
         threads=1)  # fmt: skip
    shutil.rmtree(export)
    torch.manual_seed(7)
    ResiregVLM.build(TINY_BACKBONE, TINY_HEAD, TINY_TEXT).save_pretrained(export)
    refused = _rerun(env, evaluation, "--out", tmp_path / "again", check=2)
    assert "models." in refused.stderr and "Traceback" not in refused.stderr, refused.stderr
    assert not (tmp_path / "again").exists()
    allowed = _rerun(env, evaluation, "--out", tmp_path / "again", "--allow-drift")
    assert allowed.returncode in (0, 1), allowed.stderr[-3000:]  # ran: identical or differs
    drift = _record(tmp_path / "again")["rerun"]["drift"]
    assert any(line.startswith("models.") for line in drift), drift
