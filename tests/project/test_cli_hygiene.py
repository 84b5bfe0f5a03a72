"""What the commands do around the work itself: a run folder locked while a job writes it,
what they print (each line once, no colour codes in a redirected log), how they fail fast
with the option's own name, and the files they leave (git-ignored folders, the umask)."""

import contextlib
import fcntl
import json
import os
import signal
import subprocess
import sys
import textwrap
from pathlib import Path

import pytest

from helpers.paths import ROOT, TESTS
from helpers.run import _command, run, run_side_by_side, started


@contextlib.contextmanager
def _hold(folder):
    """A separate process that locks ``folder`` as a job does and waits, for the ``with``
    block; given once the lock is held."""
    code = textwrap.dedent(f"""
        import sys
        from pathlib import Path
        from resireg_train.jobs.run_folder import hold_run_folder
        hold_run_folder(Path({str(folder)!r}))
        print("held", flush=True)
        sys.stdin.read()
    """)
    with started([sys.executable, "-c", code], stdin=subprocess.PIPE) as proc:
        proc.expect("held", timeout=120, what="the lock held")
        yield proc


def _files(folder):
    return {p.relative_to(folder): p.read_bytes() for p in sorted(folder.rglob("*")) if p.is_file()}


def test_second_job_on_a_locked_folder_is_refused_and_a_killed_holder_frees_it(
    tmp_path, tiny_export
):
    """A folder a job holds: resireg-eval given it is refused with one line naming the
    holder's PID, before writing anything (the holder's files stay byte for byte); once the
    holder is killed with SIGKILL the lock is free again (the OS released it)."""
    out = tmp_path / "run"
    out.mkdir()
    (out / "results.json").write_text('{"name": "map", "status": "running"}\n')
    (out / "map.log").write_text("the first job's log\n")
    (out / ".hydra").mkdir()
    (out / ".hydra" / "overrides.yaml").write_text("- window=4\n")
    with _hold(out) as holder:
        before = _files(out)
        proc = run("resireg-eval", f"model_path={tiny_export}", "dataset=synthetic",
                   f"hydra.run.dir={out}", check=False, timeout=300)  # fmt: skip
        _assert_refused(proc, out, holder.pid)
        assert _files(out) == before  # nothing written: no log, no .hydra, no record
        holder.kill()  # SIGKILL: no clean-up code runs in the holder
    assert holder.returncode == -signal.SIGKILL
    _assert_free(out)


def _assert_refused(proc, out, pid):
    assert proc.returncode == 1, proc.stdout[-2000:] + proc.stderr[-2000:]
    lines = [x for x in proc.stderr.splitlines() if x.strip()]
    assert len(lines) == 1 and f"(PID {pid}," in lines[0], proc.stderr
    assert str(out) in lines[0] and "refused" in lines[0]


def _assert_free(out):
    with open(out / ".run.lock") as f:  # this process takes the lock at once
        fcntl.flock(f.fileno(), fcntl.LOCK_EX | fcntl.LOCK_NB)


@pytest.mark.slow
def test_a_running_training_job_keeps_its_folder_until_killed(tmp_path, tiny_export):
    """A real resireg-train job, paused once training started: resireg-map and resireg-eval
    (resume=true, the same hydra.run.dir) are refused naming its PID and change none of its
    files; after kill -9 the lock is free."""
    out = tmp_path / "run"
    tests = str(TESTS)
    env = {**os.environ,
           "PYTHONPATH": os.pathsep.join([tests, os.environ.get("PYTHONPATH", "")])}  # fmt: skip
    with started(_command("resireg-train", [
        "experiment=smoke", "trainer.max_epochs=1", "data.steps_per_epoch=2",
        "+callbacks.hold._target_=helpers.hold.WaitFor", f"+callbacks.hold.path={tmp_path / 'go'}",
        # the job's own writers that keep running while it is held (the system-metrics rows
        # every 10 s, the heartbeat every 30 s) are off: the files compared are the refused
        # commands' doing only
        "system_metrics.enabled=false", "provenance.heartbeat_interval=3600",
        f"hydra.run.dir={out}"]), env=env) as job:  # fmt: skip
        # until training has started (the folder written, locked)
        job.expect("holding", timeout=300, what="training")
        before = _files(out)
        assert (out / ".hydra" / "overrides.yaml").is_file() and (out / "train.log").is_file()
        refused = run_side_by_side(
            ("resireg-map", f"model_path={tiny_export}", "source=tum", "resume=true",
             f"source.path={tmp_path}", f"hydra.run.dir={out}"),
            ("resireg-eval", f"model_path={tiny_export}", "dataset=synthetic",
             f"hydra.run.dir={out}"),
            check=False, threads=None,
        )  # fmt: skip
        for proc in refused:
            _assert_refused(proc, out, job.pid)
        assert _files(out) == before
        job.kill()
    assert job.returncode == -signal.SIGKILL
    _assert_free(out)


@pytest.mark.slow
def test_two_resireg_map_runs_into_one_folder_one_is_refused(tmp_path, tiny_export):
    """Two real resireg-map jobs started together on one hydra.run.dir: one maps, the other
    is refused naming the first one's PID; the folder's log and overrides are the first's."""
    pytest.importorskip("rosbags")
    from resireg_train.data.room_bag import TOPICS, room_frames, write_bag

    bag = write_bag(tmp_path / "room", room_frames(6))
    out = tmp_path / "run"
    common = [f"model_path={tiny_export}", "device=cpu", "source=rosbag",
              f"source.path={bag}", f"source.colour_topic={TOPICS['colour']}",
              f"source.depth_topic={TOPICS['depth']}", f"source.camera_info_topic={TOPICS['info']}",
              "variant=full@n_prototypes:4", "window=2", "voxel_size=0.2",
              f"hydra.run.dir={out}"]  # fmt: skip
    procs = run_side_by_side(("resireg-map", *common, "seed=1"), ("resireg-map", *common, "seed=2"),
                             check=False)  # fmt: skip
    codes = sorted(p.returncode for p in procs)
    assert codes[0] == 0 and codes[1] != 0, [p.stderr[-2000:] for p in procs]
    winner, loser = sorted(procs, key=lambda p: p.returncode)
    pid = int((out / ".run.lock").read_text())
    assert f"(PID {pid}," in loser.stderr, loser.stderr
    assert json.loads((out / "results.json").read_text())["status"] == "completed"
    seed = "seed=1" if "seed=1" in winner.args else "seed=2"
    assert seed in (out / ".hydra" / "overrides.yaml").read_text()
    assert (out / "map.log").read_text().count("output dir:") == 1


def test_results_and_log_files_follow_the_umask(tmp_path):
    """atomic_write (results.json, metrics, reports) creates files as open() does: mode
    0666 minus the umask, so a group that may read the folder reads the record."""
    from resireg.integrity import atomic_write

    old = os.umask(0o027)
    try:
        path = atomic_write(tmp_path / "a.json", "{}")
    finally:
        os.umask(old)
    assert path.stat().st_mode & 0o777 == 0o640
    old = os.umask(0o002)
    try:
        path = atomic_write(tmp_path / "a.json", "{}")  # replaced: the new file's mode
    finally:
        os.umask(old)
    assert path.stat().st_mode & 0o777 == 0o664


def test_gitignore_covers_the_folders_runs_write():
    """The folders the guide's commands write by default are ignored by git."""
    ignored = subprocess.run(
        ["git", "check-ignore", "--no-index", "data/x.bag", "outputs/train/run/results.json",
         "multirun/x", "outputs/map/run/.run.lock"],
        cwd=ROOT, capture_output=True, text=True,
    )  # fmt: skip
    assert ignored.stdout.split() == ["data/x.bag", "outputs/train/run/results.json",
                                      "multirun/x", "outputs/map/run/.run.lock"]  # fmt: skip


@pytest.mark.parametrize("script", ["resireg-train", "resireg-eval", "resireg-map",
                                    "resireg-report", "resireg-playground"])  # fmt: skip
def test_console_scripts_without_the_train_extra_say_so_in_one_line(script):
    """A core-only install (lightning and hydra cannot be imported): the installed console
    script itself, run as the shell runs it, prints one line naming the extra, no traceback."""
    import shutil

    path = shutil.which(script)
    if path is None or not Path(path).read_text(errors="replace").startswith("#!"):
        pytest.skip(f"{script} is not installed as a console script here")
    code = ("import runpy, sys\n"
            "for name in ('lightning', 'hydra'):\n"
            "    sys.modules[name] = None  # 'import lightning' raises ImportError, as uninstalled\n"
            f"runpy.run_path({path!r}, run_name='__main__')\n")  # fmt: skip
    proc = subprocess.run([sys.executable, "-c", code], capture_output=True, text=True,
                          timeout=120)  # fmt: skip
    assert proc.returncode == 1 and proc.stdout == ""
    assert proc.stderr.splitlines() == [
        f"{script}: error: needs the 'train' extra (hydra-core, lightning not installed): "
        'pip install "resireg[train]" (in a clone: pip install -e ".[train]" -c constraints.txt)'
    ], proc.stderr


def test_playground_names_model_path_before_loading_torch(tmp_path):
    """A --model-path that is neither a folder nor a cached repo id (offline) is refused naming
    --model-path, before torch, the models or Gradio are imported."""
    code = textwrap.dedent(f"""
        import sys
        from resireg_train.cli import playground
        try:
            playground.main(["--model-path", {str(tmp_path / "nope")!r}])
        except SystemExit as exit:
            print("exit", exit.code)
        print("loaded:", sorted(m for m in ("torch", "gradio", "lightning") if m in sys.modules))
    """)
    for path in (str(tmp_path / "nope"), "outputs/nope"):
        proc = subprocess.run([sys.executable, "-c", code.replace(str(tmp_path / "nope"), path)],
                              capture_output=True, text=True, timeout=120, cwd=tmp_path,
                              env={**os.environ, "HF_HUB_OFFLINE": "1"})  # fmt: skip
        assert proc.stdout.splitlines() == ["exit 2", "loaded: []"], proc.stdout + proc.stderr
        assert proc.stderr.startswith(f"resireg-playground: error: --model-path: {path!r}")
        assert "encoder.path" not in proc.stderr and "model_path=" not in proc.stderr


@pytest.mark.slow
def test_training_prints_each_line_once_and_the_bar_shows_the_epoch_values(tmp_path):
    """resireg-train experiment=smoke, redirected: each Lightning line once (Hydra's format),
    no colour codes, a model summary without an unmeasured FLOPs count. The same run on a
    terminal: the progress bar shows every value of the logged epoch line (losses, learning
    rate, evaluation mIoU, skip counts) and the running step loss."""
    import re

    args = ["experiment=smoke", "trainer.max_epochs=2", "data.steps_per_epoch=2", "export=false"]
    env = {**os.environ, "COLUMNS": "2000", "TERM": "xterm"}
    with started(_command("resireg-train", [*args, f"hydra.run.dir={tmp_path / 'tty'}"]),
                 env=env, terminal=True) as tty:  # fmt: skip
        piped = run("resireg-train", *args, f"hydra.run.dir={tmp_path / 'piped'}", timeout=600)
        tty.wait(timeout=600)
    printed = piped.stdout + piped.stderr
    assert "\x1b[" not in printed
    for message in ("Seed set to 0", "GPU available: False", "`Trainer.fit` stopped"):
        assert printed.count(message) == 1, (message, printed[-3000:])
    assert not [x for x in printed.splitlines() if x.startswith("INFO: ")]
    assert printed.count("Trainable params") == 1 and "Flops" not in printed
    assert "FLOPs" not in printed and "model summary" not in printed
    log = (tmp_path / "piped" / "train.log").read_text()
    assert log.count("Trainable params") == 1 and log.count("Seed set to 0") == 1

    screen = tty.stdout
    assert tty.returncode == 0, screen[-3000:]
    screen = re.sub(r"\x1b\[[0-9;?]*[A-Za-z]", "", screen)  # the terminal's control codes
    (last,) = [x for x in (tmp_path / "tty" / "train.log").read_text().splitlines()
               if "epoch 1/1 |" in x]  # fmt: skip
    values = last.split(" | ")[1].split()
    assert {v.split("=")[0] for v in values} >= {
        "train/loss",
        "train/lr",
        "val/ovss/synthetic/miou_full",
        "data/skipped_invalid",
    }
    bar = [x for x in screen.splitlines() if x.startswith("Epoch 1/1") and "2/2" in x][-1]
    for value in values:  # the epoch line's key=value as the bar's "key: value"
        assert value.replace("=", ": ", 1) in bar, (value, bar)
    assert "train/loss_step: " in bar


@pytest.mark.slow
def test_resireg_map_prints_its_summary_once(tmp_path, tiny_export):
    """resireg-map on the demo bag: the summary line once on the console, once in map.log."""
    pytest.importorskip("rosbags")
    bag = tmp_path / "room"
    run(sys.executable, "-m", "resireg_train.data.room_bag", bag, timeout=300)
    from resireg_train.data.room_bag import TOPICS

    out = tmp_path / "run"
    proc = run("resireg-map", f"model_path={tiny_export}", "device=cpu", "source=rosbag",
               f"source.path={bag}", f"source.colour_topic={TOPICS['colour']}",
               f"source.depth_topic={TOPICS['depth']}", f"source.camera_info_topic={TOPICS['info']}",
               "variant=full@n_prototypes:4", "window=4", f"hydra.run.dir={out}")  # fmt: skip
    printed = proc.stdout + proc.stderr
    assert printed.count("unpaired colour messages:") == 1, printed
    assert (out / "map.log").read_text().count("unpaired colour messages:") == 1
    assert "\x1b[" not in printed


@pytest.mark.slow
def test_wandb_logger_does_not_warn_about_the_anonymous_setting(tmp_path):
    """An offline W&B run made by conf/tracker/wandb.yaml's factory: no warning about a setting
    the user never gave."""
    pytest.importorskip("wandb")
    code = textwrap.dedent(f"""
        from resireg_train.record.trackers.wandb import wandb_logger
        logger = wandb_logger("t", save_dir={str(tmp_path)!r})
        logger.experiment.finish()
    """)
    env = {**os.environ, "WANDB_MODE": "offline", "WANDB_CONFIG_DIR": str(tmp_path / "config"),
           "WANDB_CACHE_DIR": str(tmp_path / "cache")}  # fmt: skip
    proc = subprocess.run([sys.executable, "-c", code], capture_output=True, text=True,
                          timeout=300, env=env, cwd=tmp_path)  # fmt: skip
    assert proc.returncode == 0, proc.stderr[-2000:]
    assert list(tmp_path.glob("wandb/offline-run-*"))  # the run was made
    assert "anonymous" not in proc.stdout + proc.stderr, proc.stderr


@pytest.mark.slow
def test_playground_launch_prints_its_address_and_no_share_hint(tmp_path):
    """The playground's launch(): the local address once, not Gradio's share=True advice."""
    pytest.importorskip("gradio")
    import socket

    with socket.socket() as s:
        s.bind(("127.0.0.1", 0))
        port = s.getsockname()[1]
    code = textwrap.dedent(f"""
        import gradio as gr
        from resireg_train.playground.app import launch
        with gr.Blocks() as demo:
            gr.Markdown("hello")
        launch(demo, "127.0.0.1", {port})
    """)
    env = {**os.environ, "GRADIO_ANALYTICS_ENABLED": "False"}
    with started([sys.executable, "-c", code], env=env) as proc:
        first = proc.readline(timeout=180)
        assert first == f"* Running on local URL:  http://127.0.0.1:{port}/\n", first
        assert proc.stop(signal.SIGINT, timeout=60) == 0, proc.stdout  # Ctrl-C: a clean exit
    assert "share=True" not in proc.stdout, proc.stdout
