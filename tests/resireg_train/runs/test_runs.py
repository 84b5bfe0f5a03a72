"""Provenance (resireg_train.record.provenance) and the run index (resireg-runs): the code's commit and
uncommitted change from a real git checkout of the project, package versions, data
fingerprints, a stage 1 -> stage 2 -> export -> eval / map lineage, and ls / show / diff on
generated run folders (one of them killed)."""

from __future__ import annotations

import contextlib
import csv
import hashlib
import importlib.metadata as md
import io
import json
import os
import shutil
import subprocess
import sys
import textwrap
from pathlib import Path

import pytest
import yaml

from helpers.paths import ROOT
from helpers.run import run
from resireg_train.record.provenance.inputs import data_identity
from resireg_train.record.provenance.machine import package_versions
from resireg_train.runs.diff import diff_runs
from resireg_train.runs.index import find_run, scan

SRC = ROOT / "src"
_PROBE = textwrap.dedent(
    """
    import json, sys
    from pathlib import Path
    import resireg_train.record.provenance.code as p
    from resireg_train.record.settings import provenance_settings
    settings = {**provenance_settings(), **json.loads(sys.argv[2])}
    print(json.dumps({"file": p.__file__,
                      "code": p.code_provenance(Path(sys.argv[1]), settings=settings)}))
    """
)


def _git(repo, *args):
    return subprocess.run(["git", "-C", str(repo), *args], check=True, capture_output=True,
                          text=True).stdout.strip()  # fmt: skip


def _project_copy(dest: Path, git: bool) -> Path:
    """A copy of the project's packages in ``dest/src`` (a git repository when ``git``)."""
    shutil.copytree(SRC, dest / "src", ignore=shutil.ignore_patterns("__pycache__", "*.egg-info"))
    if git:
        _git(dest, "init", "-q", "-b", "main")
        _git(dest, "-c", "user.name=t", "-c", "user.email=t@t", "add", "-A")
        _git(dest, "-c", "user.name=t", "-c", "user.email=t@t", "commit", "-qm", "copy")
    return dest


def _probe(repo: Path, out: Path, **settings) -> dict:
    """``code_provenance`` run from the copy ``repo`` into ``out``; ``settings``: keys of the
    ``provenance`` block (conf/provenance/default.yaml) to override."""
    out.mkdir(parents=True, exist_ok=True)
    env = {
        **os.environ,
        "PYTHONPATH": str(repo / "src"),
        "RESIREG_CONFIG_DIR": str(SRC.parent / "conf"),
    }
    proc = run(sys.executable, "-c", _PROBE, out, json.dumps(settings), env=env)
    result = json.loads(proc.stdout.strip().splitlines()[-1])
    assert Path(result["file"]).resolve().is_relative_to(repo.resolve())  # the copy ran
    return result["code"]


@pytest.mark.skipif(shutil.which("git") is None, reason="needs git")
def test_code_provenance_from_a_checkout_clean_dirty_and_outside_one(tmp_path):
    repo = _project_copy(tmp_path / "repo", git=True)
    clean = _probe(repo, tmp_path / "run_clean")
    assert clean["version"] == md.version("resireg")
    git = clean["git"]
    assert git["commit"] == _git(repo, "rev-parse", "HEAD") and git["branch"] == "main"
    assert git["dirty"] is False and git["diff"] is None
    assert not (tmp_path / "run_clean" / "code.diff").exists()

    # Dirty: a tracked file changed and an untracked one added.
    changed = repo / "src" / "resireg_train" / "runs" / "index.py"
    changed.write_text(changed.read_text() + "\n# a local experiment\nX = 1\n")
    added = repo / "src" / "resireg_train" / "my_callback.py"
    added.write_text("VALUE = 42\n")
    # untracked files' content only on the explicit opt-in (provenance.untracked_content)
    dirty = _probe(repo, tmp_path / "run_dirty", untracked_content=["src/*.py"])
    assert dirty["git"]["dirty"] is True and dirty["git"]["diff"] == "code.diff"
    assert dirty["git"]["commit"] == git["commit"]
    assert dirty["git"]["untracked"] == [{
        "path": "src/resireg_train/my_callback.py", "size": 11,
        "sha256": hashlib.sha256(b"VALUE = 42\n").hexdigest()}]  # fmt: skip
    # The diff reproduces the change: a clean clone at the commit + git apply == the tree.
    clone = tmp_path / "clone"
    subprocess.run(["git", "clone", "-q", str(repo), str(clone)], check=True)
    _git(clone, "checkout", "-q", dirty["git"]["commit"])
    _git(clone, "apply", str(tmp_path / "run_dirty" / "code.diff"))
    for path in (changed, added):
        assert (clone / path.relative_to(repo)).read_text() == path.read_text()
    assert _git(clone, "status", "--porcelain") == _git(repo, "status", "--porcelain")

    # Outside any checkout: the version alone, nothing fails, no diff written.
    plain = _project_copy(tmp_path / "plain", git=False)
    outside = _probe(plain, tmp_path / "run_plain")
    assert outside == {"version": md.version("resireg"), "git": None}
    assert not (tmp_path / "run_plain" / "code.diff").exists()


def test_package_versions_are_importlib_metadatas():
    versions = package_versions()
    assert versions["torch"] == md.version("torch") and versions["numpy"] == md.version("numpy")
    for name, version in versions.items():
        assert md.version(name) == version
    assert "not-a-package-xyz" not in package_versions(("torch", "not-a-package-xyz"))


def test_data_fingerprint_changes_with_one_file_and_only_then(tmp_path):
    data = tmp_path / "ADEChallengeData2016"
    for i in range(5):
        (data / "images").mkdir(parents=True, exist_ok=True)
        (data / "images" / f"{i}.jpg").write_bytes(bytes([i]) * (100 + i))
    entry = {"name": "ade20k", "kind": "ade20k", "path": str(data), "split": "validation"}
    first = data_identity(entry)
    assert first["kind"] == "local" and first["files"] == 5
    assert first["bytes"] == sum(100 + i for i in range(5))
    assert data_identity(entry) == first  # nothing changed: same fingerprint
    target = data / "images" / "3.jpg"
    stat = target.stat()
    target.write_bytes(b"\x07" * (100 + 3))  # same size, new content and time
    os.utime(target, ns=(stat.st_atime_ns, stat.st_mtime_ns + 1_000_000))
    assert data_identity(entry)["fingerprint"] != first["fingerprint"]
    # ScanNet: only the listed scenes count (another scene changing changes nothing)
    for scene in ("scene0011_00", "scene0050_00"):
        (tmp_path / "scannet" / scene).mkdir(parents=True)
        (tmp_path / "scannet" / scene / "0.jpg").write_bytes(b"x")
    scannet = {"kind": "scannet", "path": str(tmp_path / "scannet"), "scenes": ["scene0011_00"]}
    before = data_identity(scannet)
    (tmp_path / "scannet" / "scene0050_00" / "0.jpg").write_bytes(b"changed")
    assert data_identity(scannet) == before and before["files"] == 1
    hub = data_identity({"path": "zhoubolei/scene_parse_150", "config": "scene_parsing",
                         "split": "validation", "revision": "refs/convert/parquet"})  # fmt: skip
    assert hub == {"kind": "hub", "repo": "zhoubolei/scene_parse_150", "config": "scene_parsing",
                   "split": "validation", "revision": "refs/convert/parquet"}  # fmt: skip
    generated = data_identity({"path": "synthetic", "size": 256, "seed": 0})
    assert generated == {"kind": "generated", "settings": {"path": "synthetic", "size": 256,
                                                           "seed": 0}}  # fmt: skip


@pytest.fixture
def room_bag_path(tmp_path):
    """The demo room as a ROS 2 bag and the overrides naming its topics."""
    from resireg_train.data.room_bag import TOPICS, room_frames, write_bag

    bag = write_bag(tmp_path / "room", room_frames(4))
    topics = [f"source.colour_topic={TOPICS['colour']}", f"source.depth_topic={TOPICS['depth']}",
              f"source.camera_info_topic={TOPICS['info']}"]  # fmt: skip
    return bag, topics


def _runs_cli(*args) -> str:
    from resireg_train.cli.runs import main

    out = io.StringIO()
    with contextlib.redirect_stdout(out):
        main([str(a) for a in args])
    return out.getvalue()


def _fake_run(root, name, status, lr, miou, pid=None, commit="a" * 40, numpy="2.4.6"):
    folder = root / name
    (folder / ".hydra").mkdir(parents=True)
    (folder / ".hydra" / "overrides.yaml").write_text(yaml.safe_dump([f"model.optimizer.lr={lr}"]))
    (folder / ".hydra" / "config.yaml").write_text(
        yaml.safe_dump({"name": "smoke", "seed": 0, "model": {"optimizer": {"lr": lr}}})
    )
    import socket

    provenance = {
        "run_id": name.rjust(12, "0")[-12:], "cli": "resireg-train",
        "code": {"version": "0.1.0", "git": {"commit": commit, "dirty": False}},
        "environment": {"packages": {"numpy": numpy}},
        "machine": {"host": socket.gethostname(), "pid": pid or os.getpid()},
        "time": {"start": f"2026-12-0{name[-1]}T10:00:00+00:00", "wall_seconds": 12.5},
    }  # fmt: skip
    record = {"name": "smoke", "status": status, "final": {"val/ovss/synthetic/miou_full": miou,
              "train/loss": 1.0 - miou}, "provenance": provenance}  # fmt: skip
    (folder / "results.json").write_text(json.dumps(record))
    return folder


def test_runs_ls_filters_sorts_and_shows_a_killed_run_as_died(tmp_path):
    root = tmp_path / "outputs"
    dead = subprocess.Popen([sys.executable, "-c", "import time; time.sleep(60)"])
    dead.kill()
    dead.wait()  # a PID no process holds any more (reaped)
    _fake_run(root, "run1", "completed", 1e-3, 0.20)
    _fake_run(root, "run2", "completed", 3e-3, 0.30)
    _fake_run(root / "multirun" / "x", "run3", "running", 1e-4, 0.05, pid=dead.pid)
    _fake_run(root, "run4", "running", 2e-3, 0.10)  # this process: alive
    rows = list(csv.DictReader(io.StringIO(_runs_cli("ls", root, "--format", "csv"))))
    assert [r["run_id"][-4:] for r in rows] == ["run1", "run2", "run3", "run4"]  # by start
    statuses = {r["run_id"][-4:]: r["status"] for r in rows}
    assert statuses == {"run1": "completed", "run2": "completed", "run3": "died",
                        "run4": "running"}  # fmt: skip
    got = json.loads(_runs_cli("ls", root, "--where", "val/ovss/synthetic/miou_full>0.15",
                               "--sort=-val/ovss/synthetic/miou_full", "--columns",
                               "run_id,model.optimizer.lr,value", "--format", "json"))  # fmt: skip
    assert [(r["run_id"][-4:], r["model.optimizer.lr"], r["value"]) for r in got] == [
        ("run2", 3e-3, 0.30), ("run1", 1e-3, 0.20)]  # fmt: skip
    assert [r.run_id[-4:] for r in scan([root]) if r.status == "died"] == ["run3"]
    table = _runs_cli("ls", root, "--where", "status=completed", "--where",
                      "model.optimizer.lr<=0.001")  # fmt: skip
    assert "run1" in table and "run2" not in table and table.strip().endswith("1 run(s)")
    with pytest.raises(SystemExit) as bad:
        _runs_cli("ls", root, "--where", "nonsense")
    assert bad.value.code == 2


def test_runs_diff_shows_config_provenance_and_metric_differences(tmp_path):
    root = tmp_path / "outputs"
    a = _fake_run(root, "run1", "completed", 1e-3, 0.20)
    _fake_run(root, "run2", "completed", 3e-3, 0.30, commit="b" * 40, numpy="2.5.0")
    differences = diff_runs(find_run(str(a), [root]), find_run("00000000run2", [root]))
    assert differences["config"] == [("model.optimizer.lr", 1e-3, 3e-3)]
    assert ("provenance.code.git.commit", "a" * 40, "b" * 40) in differences["provenance"]
    assert ("provenance.environment.packages.numpy", "2.4.6", "2.5.0") in differences["provenance"]
    assert not any(k.startswith("provenance.time") for k, _, _ in differences["provenance"])
    assert ("val/ovss/synthetic/miou_full", 0.20, 0.30) in differences["metrics"]
    text = _runs_cli("diff", a, "00000000run2", "--root", root)
    assert "model.optimizer.lr" in text and "2.5.0" in text and "b" * 40 in text


@pytest.mark.slow
def test_lineage_stage1_stage2_export_eval_and_map(tmp_path, room_bag_path):
    """data -> stage 1 -> stage 2 (+model.init_from) -> export -> an evaluation and a map:
    every run's provenance links to the one before, and resireg-runs lineage prints it."""
    from helpers.run import evaluate_export, run

    logs = tmp_path / "outputs"
    short = ["experiment=smoke", "trainer.max_epochs=1", "data.steps_per_epoch=2",
             f"paths.log_dir={logs}"]  # fmt: skip
    stage1, stage2 = logs / "stage1", logs / "stage2"
    run("resireg-train", *short, f"hydra.run.dir={stage1}", threads=2)
    ckpt = stage1 / "checkpoints" / "last.ckpt"
    run("resireg-train", *short, f"hydra.run.dir={stage2}", f"+model.init_from={ckpt}",
        threads=2)  # fmt: skip
    export = stage2 / "export"
    made_by = json.loads((export / "provenance.json").read_text())
    s2 = json.loads((stage2 / "results.json").read_text())["provenance"]
    assert made_by["run_id"] == s2["run_id"] and made_by["run_dir"] == str(stage2.resolve())
    from resireg.integrity import sha256_file

    assert made_by["checkpoint"]["sha256"] == sha256_file(stage2 / "checkpoints" / "last.ckpt")
    assert s2["models"]["init_from"] == {"path": str(ckpt.resolve()), "sha256": sha256_file(ckpt)}
    assert s2["cli"] == "resireg-train" and s2["time"]["wall_seconds"] > 0
    assert s2["data"]["data.sources.synthetic"]["kind"] == "generated"
    evaluation = logs / "eval"
    evaluate_export(export, evaluation)
    used = json.loads((evaluation / "results.json").read_text())["provenance"]["models"]["export"]
    assert used["path"] == str(export.resolve())
    assert used["files"]["model.safetensors"] == sha256_file(export / "model.safetensors")
    assert used["training_run"]["run_id"] == s2["run_id"]
    mapped = logs / "map"
    run("resireg-map", f"model_path={export}", "device=cpu", "source=rosbag",
        f"source.path={room_bag_path[0]}", *room_bag_path[1], "variant=bb", "window=2",
        f"hydra.run.dir={mapped}", threads=2)  # fmt: skip
    lines = _runs_cli("lineage", evaluation, "--root", logs).splitlines()
    s1 = json.loads((stage1 / "results.json").read_text())["provenance"]
    assert lines[0].startswith("data data.sources.synthetic: generated")
    order = [s1["run_id"], f"checkpoint {ckpt.resolve()}", s2["run_id"], f"export {export.resolve()}",
             str(evaluation)]  # fmt: skip
    positions = [next(i for i, line in enumerate(lines) if part in line) for part in order]
    assert positions == sorted(positions), lines
    # The export's model card: parsed by huggingface_hub, its results equal results.json
    from huggingface_hub import ModelCard

    card = ModelCard.load(export / "README.md")
    s2_final = json.loads((stage2 / "results.json").read_text())["final"]
    trained = {r.metric_name: r.metric_value for r in card.data.eval_results}
    assert trained == pytest.approx({f"{k.split('/')[-1].split('_')[0]} "
                                     f"({k.split('/')[-1].split('_', 1)[1]})": v
                                     for k, v in s2_final.items() if k.startswith("val/")
                                     and "miou_" in k})  # fmt: skip
    assert card.data.library_name == "resireg" and s2["run_id"] in card.text
    _runs_cli("card", export, "--add", evaluation)
    card = ModelCard.load(export / "README.md")
    evaluated = json.loads((evaluation / "results.json").read_text())
    added = {(r.source_name.split()[0], r.metric_name): r.metric_value
             for r in card.data.eval_results if r.source_name.startswith("resireg-eval")}  # fmt: skip
    expected = {("resireg-eval", f"{k.split('/')[-1].split('_')[0]} "
                 f"({k.split('/')[-1].split('_', 1)[1]})"): v
                for k, v in evaluated["final"].items() if "iou_" in k}  # fmt: skip
    assert expected and added == pytest.approx(expected)
    kept = {r.metric_name: r.metric_value for r in card.data.eval_results
            if r.source_name == "resireg-train validation"}  # fmt: skip
    assert kept == pytest.approx(trained)  # the training's validation scores stay
    assert str(evaluation) in card.text.split("## Evaluations")[1]
    down = _runs_cli("lineage", export, "--root", logs)
    assert "used by resireg-map" in down and str(mapped) in down and str(evaluation) in down
