"""The run record and its trackers (resireg_train.runs): one owner of results.json
(RunRecord), one table of trackers, and what a record keeps and refuses.

- a dirty checkout with planted secrets (an untracked .env and token file, a git-ignored file,
  a tracking URI with a password, an environment variable), a dangling symbolic link, bulk and
  binary untracked files: resireg-train, resireg-eval and resireg-map under umask 077 with
  tracker=mlflow on a real `mlflow server`; no secret in any file of the run folders, the MLflow
  store or the console; every file and folder private; code.diff capped and 0600;
- code.diff under umask 022 is 0600, binary and secret-looking changes never inlined;
- an unreachable tracker refuses the run in one line (or, on request, the run completes with
  local records); results.json never stays `running`;
- resireg-runs over hostile records and options; two `card --add` at once both land.
"""

from __future__ import annotations

import ast
import hashlib
import json
import os
import shutil
import socket
import stat
import subprocess
import sys
import textwrap
import time
from pathlib import Path

import pytest
import yaml

from helpers.paths import ROOT
from helpers.run import run

SECRETS = {
    "key": "wJalrPLANTEDKEY0001",  # an untracked .env's AWS_SECRET_ACCESS_KEY
    "token": "ghp_PLANTEDTOKEN0002",  # notes/token.txt
    "password": "s3cr3tPW0003",  # the tracking URI's password
    "ignored": "IGNOREDSECRET0004",  # a git-ignored file's content
    "environment": "ENVSECRET0005",  # an environment variable of the run
}


def _free_port() -> int:
    with socket.socket() as s:
        s.bind(("127.0.0.1", 0))
        return s.getsockname()[1]


def _git(repo, *args):
    return subprocess.run(["git", "-C", str(repo), "-c", "user.name=t", "-c", "user.email=t@t",
                           *args], check=True, capture_output=True, text=True).stdout  # fmt: skip


def _checkout(dest: Path) -> Path:
    """A git checkout of the project's packages and configs in ``dest`` (one commit), with
    a .gitignore that ignores ``ignored.txt``."""
    ignore = shutil.ignore_patterns("__pycache__", "*.egg-info")
    shutil.copytree(ROOT / "src", dest / "src", ignore=ignore)
    shutil.copytree(ROOT / "conf", dest / "conf", ignore=ignore)
    (dest / ".gitignore").write_text("ignored.txt\n")
    _git(dest, "init", "-q", "-b", "main")
    _git(dest, "add", "-A")
    _git(dest, "commit", "-qm", "copy")
    return dest


def _env(repo: Path, **extra) -> dict[str, str]:
    """The environment of a command run from ``repo``'s code (its conf/ found beside it)."""
    env = {k: v for k, v in os.environ.items() if k != "RESIREG_CONFIG_DIR"}
    return {**env, "PYTHONPATH": str(repo / "src"), **extra}


def _sha(data: bytes) -> str:
    return hashlib.sha256(data).hexdigest()


def _room_bag(tmp_path):
    from resireg_train.data.room_bag import TOPICS, room_frames, write_bag

    bag = write_bag(tmp_path / "room", room_frames(4))
    return [f"source.path={bag}", "source=rosbag", f"source.colour_topic={TOPICS['colour']}",
            f"source.depth_topic={TOPICS['depth']}",
            f"source.camera_info_topic={TOPICS['info']}"]  # fmt: skip


def _files(*roots: Path):
    for root in roots:
        if root.is_file():
            yield root
        else:
            yield from (p for p in root.rglob("*") if p.is_file() and not p.is_symlink())


# ------------------------------------------------------------- secrets, cap, links, umask
@pytest.mark.slow
@pytest.mark.skipif(shutil.which("git") is None, reason="needs git")
def test_a_dirty_checkout_with_secrets_leaves_none_in_any_record(
    tmp_path, tiny_export, mlflow_server
):
    """Issue 44 cases 1-4: train, eval and map from a dirty checkout holding secrets, under
    umask 077, tracked by an MLflow server given a password in its URI."""
    port, store = mlflow_server.port, mlflow_server.store
    repo = _checkout(tmp_path / "repo")
    (repo / ".env").write_text(f"AWS_SECRET_ACCESS_KEY={SECRETS['key']}\n")
    (repo / "notes").mkdir()
    (repo / "notes" / "token.txt").write_text(SECRETS["token"] + "\n")
    (repo / "ignored.txt").write_text(SECRETS["ignored"] + "\n")
    (repo / "datasets").symlink_to("/mnt/missing-resireg-test")  # dangling
    line = "0123456789abcdef" * 4 + "\n"
    (repo / "bulk").mkdir()
    for i in range(64):  # 64 x 512 KiB of text: 32 MiB, far over the cap
        (repo / "bulk" / f"f{i:02d}.txt").write_text(line * (512 * 1024 // len(line)))
    blob = bytes(range(256)) * 64  # binary (NUL bytes)
    (repo / "blob.bin").write_bytes(blob)
    edited = repo / "src" / "resireg_train" / "cli" / "report.py"
    edited.write_text(edited.read_text() + "\n# a local edit\n")
    env = _env(repo, RESIREG_TEST_TOKEN=SECRETS["environment"])
    uri = f"http://user:{SECRETS['password']}@127.0.0.1:{port}"
    common = ["tracker=mlflow", f"tracker.mlflow.tracking_uri={uri}",
              "provenance.untracked_content=[*]", "provenance.diff_max_bytes=1048576"]  # fmt: skip
    runs = tmp_path / "runs"
    old = os.umask(0o077)
    try:
        procs = [
            run("resireg-train", "experiment=smoke", "trainer.max_epochs=1",
                "data.steps_per_epoch=2", f"hydra.run.dir={runs / 'train'}", *common, env=env,
                threads=1),
            run("resireg-eval", f"model_path={tiny_export}", "dataset=synthetic",
                "dataset.size=4", "num_workers=0", "variants=[bb]",
                f"hydra.run.dir={runs / 'eval'}", *common, env=env, threads=1),
            run("resireg-map", f"model_path={tiny_export}", "device=cpu", *_room_bag(tmp_path),
                "variant=bb", "window=2", f"hydra.run.dir={runs / 'map'}", *common,
                env=env, threads=1),
        ]  # fmt: skip
    finally:
        os.umask(old)
    shown = run("resireg-runs", "show", runs / "eval", env=env)
    console = "".join(p.stdout + p.stderr for p in [*procs, shown])

    # 1. no secret anywhere: run folders, the MLflow store, the console
    for path in _files(runs, store / "artifacts", *store.glob("server.db*")):
        data = path.read_bytes()
        for name, secret in SECRETS.items():
            assert secret.encode() not in data, (name, path)
    for name, secret in SECRETS.items():
        assert secret not in console, (name, console[-3000:])
    record = json.loads((runs / "eval" / "results.json").read_text())
    assert f"user:***@127.0.0.1:{port}" in record["provenance"]["environment"]["command"]
    assert "user:***@127.0.0.1" in shown.stdout
    from mlflow import MlflowClient

    client = MlflowClient(tracking_uri=f"http://127.0.0.1:{port}")
    tracked = client.get_run(record["tracking"]["mlflow_run_id"])
    assert tracked.data.params["tracker.mlflow.tracking_uri"] == f"http://user:***@127.0.0.1:{port}"
    assert tracked.info.status == "FINISHED"

    # untracked files by name, size and SHA-256; the link as a link; never their content
    git = record["provenance"]["code"]["git"]
    untracked = {e["path"]: e for e in git["untracked"]}
    env_bytes = (repo / ".env").read_bytes()
    assert untracked[".env"] == {"path": ".env", "size": len(env_bytes), "sha256": _sha(env_bytes)}
    assert untracked["datasets"] == {"path": "datasets", "link": "/mnt/missing-resireg-test"}
    assert "ignored.txt" not in untracked  # git-ignored: not even named
    left = {e["path"]: e["reason"] for e in git["left_out"]}
    assert left[".env"] == left["notes/token.txt"] == "a secret-looking name: never inlined"
    assert left["blob.bin"] == "binary"

    # 2. code.diff: the tracked edit first, opted-in text up to the cap, the rest named
    for name in ("train", "eval", "map"):
        diff = runs / name / "code.diff"
        assert diff.stat().st_size <= 1048576
        assert "+# a local edit" in diff.read_text()
    over = [e for e in git["left_out"] if e["reason"] == "over provenance.diff_max_bytes=1048576"]
    bulk = {f"bulk/f{i:02d}.txt" for i in range(64)}
    assert len(over) >= 62 and {e["path"] for e in over} <= bulk
    for entry in over:
        data = (repo / entry["path"]).read_bytes()
        assert (entry["size"], entry["sha256"]) == (len(data), _sha(data))
    assert git["diff_bytes"] == (runs / "eval" / "code.diff").stat().st_size

    # 3. umask 077: every file and folder the three runs wrote is private
    for name in ("train", "eval", "map"):
        folder = runs / name
        for path in [folder, *folder.rglob("*")]:
            mode = path.lstat().st_mode
            assert stat.S_ISLNK(mode) or mode & 0o077 == 0, (oct(mode), path)
    # 4. the dangling link failed nothing: three completed runs
    for name in ("train", "eval", "map"):
        assert json.loads((runs / name / "results.json").read_text())["status"] == "completed"


_PROBE = textwrap.dedent(
    """
    import json, sys
    from pathlib import Path
    import resireg_train.record.provenance.code as p
    from resireg_train.record.settings import provenance_settings
    settings = {**provenance_settings(), **json.loads(sys.argv[2])}
    print(json.dumps(p.code_provenance(Path(sys.argv[1]), settings=settings)))
    """
)


@pytest.mark.skipif(shutil.which("git") is None, reason="needs git")
def test_code_diff_is_private_and_holds_only_text_that_is_not_secret(tmp_path):
    """Under umask 022, code.diff is 0600. A tracked binary change and a tracked
    secret-looking file are left out by path, size and digest; untracked content only when
    opted in; the diff applies on the commit."""
    repo = _checkout(tmp_path / "repo")
    (repo / "data.bin").write_bytes(b"\0\1\2" * 10)
    (repo / "deploy.env").write_text("TOKEN=old\n")
    _git(repo, "add", "-A")
    _git(repo, "commit", "-qm", "binary and env")
    (repo / "data.bin").write_bytes(b"\0\3\4" * 12)
    (repo / "deploy.env").write_text(f"TOKEN={SECRETS['token']}\n")
    edited = repo / "src" / "resireg" / "errors.py"
    edited.write_text(edited.read_text() + "# edit\n")
    (repo / "extra.py").write_text("X = 1\n")

    def probe(out, **settings):
        out.mkdir()
        old = os.umask(0o022)
        try:
            command = [sys.executable, "-c", _PROBE, str(out), json.dumps(settings)]
            proc = subprocess.run(command, env=_env(repo), check=True, capture_output=True,
                                  text=True)  # fmt: skip
        finally:
            os.umask(old)
        return json.loads(proc.stdout.strip().splitlines()[-1])["git"]

    plain = probe(tmp_path / "a")  # no opt-in: untracked files are named, not inlined
    diff = tmp_path / "a" / "code.diff"
    assert diff.stat().st_mode & 0o777 == 0o600
    text = diff.read_text()
    assert "+# edit" in text and "X = 1" not in text and SECRETS["token"] not in text
    assert plain["untracked"] == [{"path": "extra.py", "size": 6, "sha256": _sha(b"X = 1\n")}]
    left = {e["path"]: e for e in plain["left_out"]}
    assert left["data.bin"]["reason"] == "binary"
    assert left["data.bin"]["sha256"] == _sha((repo / "data.bin").read_bytes())
    assert left["deploy.env"]["reason"] == "a secret-looking name: never inlined"
    opted = probe(tmp_path / "b", untracked_content=["*.py"])
    assert "X = 1" in (tmp_path / "b" / "code.diff").read_text()
    clone = tmp_path / "clone"
    subprocess.run(["git", "clone", "-q", str(repo), str(clone)], check=True)
    _git(clone, "apply", str(tmp_path / "b" / "code.diff"))
    assert (clone / "extra.py").read_text() == "X = 1\n"
    assert (clone / edited.relative_to(repo)).read_text() == edited.read_text()
    assert opted["diff_bytes"] == (tmp_path / "b" / "code.diff").stat().st_size


# ------------------------------------------------------------------ unreachable trackers
@pytest.mark.slow
def test_an_unreachable_tracker_refuses_the_run_in_one_line_or_is_left_out(tmp_path, tiny_export):
    """A tracking URI on a closed port: refused before any work, in one line naming the
    tracker, the record `failed`; with unreachable=warn the run completes with its local
    records. (Without the check: more than 120 s of MLflow's retries, the record `running`.)"""
    port = _free_port()  # closed: nothing listens
    uri = f"http://user:{SECRETS['password']}@127.0.0.1:{port}"
    evaluation = [f"model_path={tiny_export}", "dataset=synthetic", "dataset.size=4",
                  "num_workers=0", "variants=[bb]"]  # fmt: skip
    cases = {
        "eval": ("resireg-eval", *evaluation, "tracker=mlflow"),
        "train": ("resireg-train", "experiment=smoke", "trainer.max_epochs=1",
                  "data.steps_per_epoch=2", "tracker=mlflow"),
    }  # fmt: skip
    for name, (script, *args) in cases.items():
        out = tmp_path / name
        proc = run(script, *args, f"tracker.mlflow.tracking_uri={uri}",
                   "tracker.mlflow.check_timeout=2",
                   f"hydra.run.dir={out}", check=False, timeout=120, threads=1)  # fmt: skip
        assert proc.returncode == 1, proc.stderr[-2000:]
        said = [line for line in proc.stderr.splitlines() if "cannot reach" in line]
        assert len(said) == 1 and (f"resireg_train.record.trackers.base.TrackerUnreachable: "
                                   f"tracker.mlflow: cannot reach http://user:***@127.0.0.1:"
                                   f"{port} (") in said[0], proc.stderr[-2000:]  # fmt: skip
        assert "Traceback" not in proc.stderr and SECRETS["password"] not in proc.stderr
        record = json.loads((out / "results.json").read_text())
        assert (
            record["status"] == "failed" and "TrackerUnreachable: tracker.mlflow" in record["error"]
        )
        assert not (out / "checkpoints").exists()  # refused before any work
    # unreachable=warn, in a two-job multirun (its job folders are named after the overrides,
    # escaped by Hydra's sweeper): both complete, and no password in a file, a folder name or
    # the console
    sweep = tmp_path / "warn"
    # the export by a short relative name (the test runs in tmp_path), so that the job folder's
    # name, cut at 200 characters, still reaches the tracking URI whatever tmp_path's length
    (tmp_path / "m").symlink_to(tiny_export)
    proc = run("resireg-eval", "-m", "model_path=m", *evaluation[1:], "full.alpha=5,10",
               "tracker=mlflow",
               f"tracker.mlflow.tracking_uri={uri}", "tracker.mlflow.unreachable=warn",
               "tracker.mlflow.check_timeout=2", f"hydra.sweep.dir={sweep}", timeout=300,
               threads=1)  # fmt: skip
    jobs = sorted(p.parent for p in sweep.glob("*/results.json"))
    assert len(jobs) == 2
    for job in jobs:
        record = json.loads((job / "results.json").read_text())
        assert record["status"] == "completed" and record["final"]
        assert list(record["tracking"]["unreachable"]) == ["mlflow"]
        assert r"user\:masked@127.0.0.1" in job.name  # (Hydra escapes the ':')
    assert (proc.stdout + proc.stderr).count("tracker.mlflow: cannot reach") == 2
    assert SECRETS["password"] not in proc.stdout + proc.stderr
    for path in [*sweep.rglob("*"), *_files(sweep)]:
        assert SECRETS["password"] not in str(path)
        assert not path.is_file() or SECRETS["password"].encode() not in path.read_bytes(), path
    # W&B online, its server on the closed port: the same refusal
    env = {**os.environ, "WANDB_BASE_URL": f"http://127.0.0.1:{port}", "WANDB_MODE": "online",
           "WANDB_CONFIG_DIR": str(tmp_path / "wandb"), "WANDB_API_KEY": "x" * 40}  # fmt: skip
    pytest.importorskip("wandb")
    proc = run("resireg-eval", *evaluation, "tracker=wandb", "tracker.wandb.check_timeout=2",
               f"hydra.run.dir={tmp_path / 'wandb_run'}", check=False, timeout=120, env=env,
               threads=1)  # fmt: skip
    assert proc.returncode == 1
    said = [line for line in proc.stderr.splitlines() if "cannot reach" in line]
    assert len(said) == 1 and f"TrackerUnreachable: tracker.wandb: cannot reach http://127.0.0.1:"\
        f"{port} (" in said[0], proc.stderr[-2000:]  # fmt: skip
    assert json.loads((tmp_path / "wandb_run" / "results.json").read_text())["status"] == "failed"
    # W&B offline beside the unreachable MLflow (left out): W&B's config, its record of the
    # command line and its console capture keep no password either
    env = {**env, "WANDB_MODE": "offline", "WANDB_SILENT": "true"}
    out = tmp_path / "offline"
    run("resireg-eval", *evaluation, "tracker=[wandb,mlflow]", f"tracker.mlflow.tracking_uri={uri}",
        "tracker.mlflow.unreachable=warn", "tracker.mlflow.check_timeout=2", f"hydra.run.dir={out}",
        timeout=300, env=env, threads=1)  # fmt: skip
    assert list(out.glob("wandb/offline-run-*/run-*.wandb"))
    for path in _files(out):
        assert SECRETS["password"].encode() not in path.read_bytes(), path


# ---------------------------------------------------------------------- the run's record
def test_the_final_status_is_written_whenever_the_job_body_returns(tmp_path):
    """A body that returns without a status of its own (a resumed training run with nothing
    left to train: Lightning calls no on_train_end) ends `completed`, its provenance closed;
    every URL's password in any field is masked."""
    from omegaconf import OmegaConf

    from resireg_train.cli.job import run_task
    from resireg_train.record.run_record import RunRecord

    def body(cfg, record):
        record.update(note={"uri": f"postgresql+psycopg://u:{SECRETS['password']}@db/x"})
        return {}

    cfg = OmegaConf.create({"name": "n", "paths": {"output_dir": str(tmp_path)}})
    final = run_task(cfg, body)
    written = json.loads((tmp_path / "results.json").read_text())
    assert final["status"] == written["status"] == "completed" and written["error"] is None
    assert written["provenance"]["time"]["wall_seconds"] is not None
    assert written["note"]["uri"] == "postgresql+psycopg://u:***@db/x"
    assert SECRETS["password"] not in (tmp_path / "results.json").read_text()
    assert RunRecord.read(tmp_path)["note"] == written["note"]


@pytest.mark.slow
def test_resuming_a_finished_training_run_records_it_completed(tmp_path):
    """ckpt_path=last on a run whose training is complete: nothing is trained, the record
    says `completed` (it said `running`: Lightning's on_train_end is not called)."""
    out = tmp_path / "run"
    args = ["experiment=smoke", "trainer.max_epochs=1", "data.steps_per_epoch=2",
            f"hydra.run.dir={out}"]  # fmt: skip
    run("resireg-train", *args, threads=2)
    first = json.loads((out / "results.json").read_text())
    run("resireg-train", *args, "ckpt_path=last", threads=2)
    again = json.loads((out / "results.json").read_text())
    assert again["status"] == "completed" and again["error"] is None
    assert again["history"] == first["history"]  # nothing was trained again
    assert again["provenance"]["run_id"] == first["provenance"]["run_id"]


class _Toy:
    """A tracker added at run time: one TRACKER_SPECS entry (the recipe)."""


def test_every_tracker_is_one_table_entry_and_one_conf_file(tmp_path):
    """TRACKER_SPECS names exactly the conf/tracker/ files, each a block of its own name whose
    own keys pass the entry's rules; an unknown name is refused with the closest; a tracker
    added as a table entry is driven by the record (begin, end with the final record)."""
    from omegaconf import OmegaConf

    from resireg.errors import ConfigError
    from resireg_train.record.run_record import RunRecord
    from resireg_train.record.settings import RecordSettings
    from resireg_train.record.trackers.base import Tracker
    from resireg_train.record.trackers.specs import TRACKER_SPECS, TrackerSpec

    files = sorted(p.stem for p in (ROOT / "conf" / "tracker").glob("*.yaml"))
    assert sorted(TRACKER_SPECS.names()) == files == ["csv", "mlflow", "tensorboard", "wandb"]
    for name, spec in TRACKER_SPECS.items():
        block = yaml.safe_load((ROOT / spec.config).read_text())
        assert list(block) == [name]
        assert issubclass(spec.load(), Tracker)
        for key, (check, expected) in spec.params.items():
            assert check(block[name][key]), (name, key, expected)

    seen = []

    class Toy(Tracker):
        def begin(self):
            seen.append(("begin", self.record.get("status")))

        def end(self, record, failed):
            seen.append(("end", record["status"], failed, self.settings["colour"]))
            return {"toy": "done"}

    sys.modules[__name__]._Toy = Toy
    rules = {"colour": (lambda v: v in ("red", "blue"), "red|blue")}
    TRACKER_SPECS["toy"] = TrackerSpec("toy", f"{__name__}:_Toy", "a test's own", rules)
    try:
        cfg = OmegaConf.create({"name": "n", "tracker": {"toy": {"colour": "red"}}})
        record = RunRecord(tmp_path)
        record.start(RecordSettings.from_config(cfg))
        record.finish()
        assert seen == [("begin", "running"), ("end", "completed", False, "red")]
        assert RunRecord.read(tmp_path)["tracking"] == {"toy": "done"}
        bad = OmegaConf.create({"name": "n", "tracker": {"toy": {"colour": "green"}}})
        with pytest.raises(ConfigError, match=r"tracker.toy.colour='green': expected red\|blue"):
            RunRecord(tmp_path / "b").start(RecordSettings.from_config(bad))
    finally:
        del TRACKER_SPECS["toy"]
    with pytest.raises(ConfigError, match="did you mean 'mlflow'"):
        cfg = OmegaConf.create({"name": "n", "tracker": {"mlflo": {"tracking_uri": "x"}}})
        RunRecord(tmp_path / "c").start(RecordSettings.from_config(cfg))


def test_no_module_outside_the_record_and_the_run_tools_reads_or_writes_results_json():
    """RunRecord is results.json's one owner: outside resireg_train/record/ (its writer) and
    resireg_train/runs/ (the tools that read finished runs) no module imports the record's file
    name or its old free functions, nor names the file in code (docstrings and messages
    aside)."""
    private = {"RESULTS_FILE", "read_results", "update_results", "strict_json", "NON_FINITE"}
    offenders = []
    for path in sorted((ROOT / "src").rglob("*.py")):
        if any(f"resireg_train/{package}/" in path.as_posix() for package in ("record", "runs")):
            continue
        tree = ast.parse(path.read_text())
        docstrings = {id(n.body[0].value) for n in ast.walk(tree)
                      if isinstance(n, (ast.Module, ast.ClassDef, ast.FunctionDef))
                      and n.body and isinstance(n.body[0], ast.Expr)}  # fmt: skip
        for node in ast.walk(tree):
            if isinstance(node, ast.ImportFrom) and any(a.name in private for a in node.names):
                offenders.append(f"{path}:{node.lineno} imports {[a.name for a in node.names]}")
            elif (isinstance(node, ast.Constant) and node.value == "results.json"
                  and id(node) not in docstrings):  # fmt: skip
                offenders.append(f"{path}:{node.lineno} names results.json")
    assert not offenders, offenders


# --------------------------------------------------------------------------- resireg-runs
def test_runs_ls_lists_the_good_runs_and_names_each_bad_record_once(tmp_path):
    """A results.json holding a JSON list, another tool's JSON object, a provenance of the
    wrong type and a bad .hydra/overrides.yaml beside good runs: `ls` lists the good ones
    (the bad overrides' run too) and names each bad file once on stderr, no traceback;
    --where with a YAML tag or an unclosed list and an unknown option exit 2 in one line;
    --sort over mixed types sorts."""
    root = tmp_path / "outputs"

    def record(name, content, overrides=None):
        folder = root / name
        (folder / ".hydra").mkdir(parents=True)
        (folder / "results.json").write_text(json.dumps(content))
        if overrides is not None:
            (folder / ".hydra" / "overrides.yaml").write_text(overrides)
        return folder

    record("good1", {"name": "smoke", "status": "completed", "final": {"m": 0.5},
                     "provenance": {"run_id": "aaaa00000001"}}, "- seed=1\n")  # fmt: skip
    record("good2", {"name": 7.5, "status": "completed"})  # not a name: sorts as text
    record("good3", {"name": None, "status": "failed", "provenance": {"run_id": "aaaa00000003"}},
           "- seed: [unclosed\n")  # fmt: skip
    lists = record("list", [1, 2, 3])
    other = record("other", {"version": 2, "metrics": {"loss": 1}})
    wrong = record("wrong", {"status": "completed", "provenance": "not a block"})
    columns = "path,name,status,overrides"
    proc = run("resireg-runs", "ls", root, "--format", "json", "--columns", columns,
               "--sort", "name", check=False)  # fmt: skip
    assert proc.returncode == 0 and "Traceback" not in proc.stderr, proc.stderr
    rows = json.loads(proc.stdout)
    assert sorted(Path(r["path"]).name for r in rows) == ["good1", "good2", "good3"]
    assert [Path(r["path"]).name for r in rows][:2] == ["good2", "good1"]  # 7.5, then 'smoke'
    said = proc.stderr.splitlines()
    assert said.count(f"resireg-runs: skipped {lists}/results.json: not a run record (a JSON "
                      "document holding a list, not an object)") == 1  # fmt: skip
    assert sum(str(other) in line and "no 'status' field" in line for line in said) == 1
    assert sum(f"{wrong}/results.json: not a run record ('provenance' holds a string)" in line
               for line in said) == 1  # fmt: skip
    assert sum("good3/.hydra/overrides.yaml: unreadable" in line for line in said) == 1
    assert len(said) == 4, said
    for where in ("status=!!python/object/apply:os.system ['touch x']", "status=[x"):
        proc = run("resireg-runs", "ls", root, "--where", where, check=False)
        assert proc.returncode == 2 and proc.stdout == ""
        assert proc.stderr.count("\n") == 1 and proc.stderr.startswith(
            f"resireg-runs: error: --where {where!r}: the value is not a plain YAML value ("
        ), proc.stderr
    proc = run("resireg-runs", "ls", root, "--colour", check=False)
    assert proc.returncode == 2 and proc.stderr.count("\n") == 1, proc.stderr
    assert not (tmp_path / "x").exists()


# ------------------------------------------------------------------------ model card lock
_ADD = textwrap.dedent(
    """
    import sys, time
    from pathlib import Path
    import huggingface_hub
    load = huggingface_hub.ModelCard.load

    def slow_load(*args, **kwargs):  # a slow file system: read, then a pause before the write
        card = load(*args, **kwargs)
        time.sleep(1.0)
        return card

    huggingface_hub.ModelCard.load = slow_load
    go = Path(sys.argv[1])
    while not go.exists():
        time.sleep(0.01)
    from resireg_train.cli.runs import main
    main(["card", sys.argv[2], "--add", sys.argv[3]])
    """
)


@pytest.mark.slow
def test_two_card_adds_at_once_both_land(tmp_path, tiny_export):
    """Two `resireg-runs card <export> --add <run>` processes released at once (each reading
    the card slowly): both evaluations are in the card, none lost."""
    from huggingface_hub import ModelCard

    from resireg_train.record.cards import write_export_card
    from resireg_train.record.run_record import RunRecord

    export = tmp_path / "train" / "export"
    shutil.copytree(tiny_export, export)
    training = RunRecord(tmp_path / "train")
    training.update(name="smoke", status="completed", output_dir=str(tmp_path / "train"),
                    final={"val/ovss/synthetic/miou_full": 0.25},
                    provenance={"run_id": "0123456789ab"})  # fmt: skip
    write_export_card(export, training)
    evaluations = []
    for i, dataset in enumerate(("ade20k", "voc20")):
        folder = tmp_path / f"eval{i}"
        RunRecord(folder).update(
            status="completed", provenance={"run_id": f"e{i}" * 6},
            params={"dataset": {"name": dataset, "split": "validation"}},
            final={f"val/ovss/{dataset}/miou_full": 0.1 + i, f"val/ovss/{dataset}/fmiou_full": 0.2},
        )  # fmt: skip
        evaluations.append(folder)
    go = tmp_path / "go"
    procs = [subprocess.Popen([sys.executable, "-c", _ADD, str(go), str(export), str(folder)],
                              stdout=subprocess.PIPE, stderr=subprocess.PIPE, text=True)
             for folder in evaluations]  # fmt: skip
    try:
        time.sleep(3)  # both started and waiting
        go.touch()
        outs = [p.communicate(timeout=120) for p in procs]
    finally:
        for p in procs:
            if p.poll() is None:
                p.kill()
                p.wait()
    assert [p.returncode for p in procs] == [0, 0], [err[-2000:] for _, err in outs]
    card = ModelCard.load(export / "README.md")
    added = {(r.dataset_name, r.metric_name): r.metric_value for r in card.data.eval_results
             if r.source_name.startswith("resireg-eval")}  # fmt: skip
    expected = {("ade20k", "miou (full)"): 0.1, ("ade20k", "fmiou (full)"): 0.2,
                ("voc20", "miou (full)"): 1.1, ("voc20", "fmiou (full)"): 0.2}  # fmt: skip
    assert added == pytest.approx(expected)
    section = card.text.split("## Evaluations")[1]
    assert all(f"`{folder}`" in section for folder in evaluations)


def test_a_password_is_masked_where_urllib_cannot_take_the_url_apart():
    """Hydra's override_dirname joins overrides with ',' (urllib then sees one URL up to the
    next space, '[' in its host part): every password in it is masked all the same."""
    from resireg.secrets import mask_text
    from resireg_train.jobs.resolvers import safe_dirname

    dirname = ("tracker.mlflow.tracking_uri=http://user:pw1@127.0.0.1:5000,provenance."
               "untracked_content=[*],storage=postgresql+psycopg://u:pw2@db/x")  # fmt: skip
    assert mask_text(dirname) == (
        "tracker.mlflow.tracking_uri=http://user:***@127.0.0.1:5000,provenance."
        "untracked_content=[*],storage=postgresql+psycopg://u:***@db/x"
    )
    # a sweep job's folder is named after its overrides: no password in a path either
    assert safe_dirname(dirname) == (
        "tracker.mlflow.tracking_uri=http:__user:masked@127.0.0.1:5000,provenance."
        "untracked_content=[*],storage=postgresql+psycopg:__u:masked@db_x"
    )
    # a multirun job's overrides escape ':' (Hydra's sweeper): masked as well
    escaped = r"tracker.mlflow.tracking_uri=http\://user\:pw3@127.0.0.1\:5000"
    assert mask_text(escaped) == r"tracker.mlflow.tracking_uri=http\://user\:***@127.0.0.1\:5000"
    assert (
        safe_dirname(escaped) == r"tracker.mlflow.tracking_uri=http\:__user\:masked@127.0.0.1\:5000"
    )


# ------------------------------------------------------------------- the record's settings
def test_record_settings_are_read_once_from_the_config():
    """RecordSettings.from_config: the trackers' blocks in their order (unset ones left out)
    as plain resolved values, the flags, the provenance block over conf/provenance's values,
    the system metrics; the config as plain values with its URL passwords, which only
    masked_config (a tracker's copy) and the repr leave out; the digest equals the SHA-256 of
    the resolved YAML computed here."""
    from omegaconf import OmegaConf

    from resireg_train.record.settings import RecordSettings

    defaults = yaml.safe_load((ROOT / "conf" / "provenance" / "default.yaml").read_text())
    url = f"http://user:{SECRETS['password']}@127.0.0.1:5000"
    cfg = OmegaConf.create({
        "name": "n", "seed": 3, "seen": "${seed}", "trainer": {"max_epochs": 1},
        "ckpt_path": "last", "provenance": {"heartbeat_interval": 7},
        "system_metrics": {"enabled": True, "interval": 2.5},
        "tracker": {"wandb": {"project": "p"}, "csv": None, "mlflow": {"tracking_uri": url}},
    })  # fmt: skip
    settings = RecordSettings.from_config(cfg)
    assert list(settings.trackers) == ["wandb", "mlflow"]
    assert settings.trackers["mlflow"] == {"tracking_uri": url}
    assert (settings.name, settings.training, settings.resuming) == ("n", True, True)
    assert settings.provenance == {**defaults, "heartbeat_interval": 7}
    assert settings.system_metrics == (True, 2.5)
    assert (
        settings.config["seen"] == 3 and settings.config["tracker"]["mlflow"]["tracking_uri"] == url
    )
    masked = settings.masked_config["tracker"]["mlflow"]["tracking_uri"]
    assert masked == "http://user:***@127.0.0.1:5000"
    assert SECRETS["password"] not in repr(settings)
    resolved = OmegaConf.to_yaml(cfg, resolve=True, sort_keys=True)
    assert settings.config_sha256 == hashlib.sha256(resolved.encode()).hexdigest()
    bare = RecordSettings.from_config(OmegaConf.create({"name": "m"}))
    assert (bare.trackers, bare.training, bare.resuming, bare.system_metrics) == (
        {}, False, False, (False, 0.0))  # fmt: skip
    assert bare.provenance == defaults


def test_no_part_of_the_record_reads_the_config_but_its_settings():
    """The composed config enters the record in one place: outside the settings' readers
    (record/settings.py, system_settings, config_digest) no function under
    resireg_train/record/ takes a parameter named cfg (the record, its trackers and its
    provenance take RecordSettings)."""
    allowed = {("settings.py", "provenance_settings"), ("settings.py", "from_config"),
               ("system.py", "system_settings"), ("inputs.py", "config_digest")}  # fmt: skip
    found = []
    for path in sorted((ROOT / "src" / "resireg_train" / "record").rglob("*.py")):
        for node in ast.walk(ast.parse(path.read_text())):
            if isinstance(node, (ast.FunctionDef, ast.AsyncFunctionDef)):
                names = [a.arg for a in (*node.args.posonlyargs, *node.args.args,
                                         *node.args.kwonlyargs)]  # fmt: skip
                if "cfg" in names and (path.name, node.name) not in allowed:
                    found.append(f"{path.name}:{node.lineno} {node.name}")
    assert found == []
