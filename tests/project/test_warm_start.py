"""The tests' warm start (helpers/warm_start.py) gives a command what a fresh interpreter gives
it: the same output, record, exit code, environment and finish. Each test runs the same command
warm and cold (``RESIREG_TEST_COLD_START=1``) and compares."""

import json
import os
import re
import subprocess
import sys
import textwrap

import pytest

from helpers import warm_start
from helpers.run import run, started

_SCRIPT = textwrap.dedent("""\
    import atexit, os, sys, threading, time
    mode = sys.argv[1]
    here = os.path.dirname(os.path.abspath(globals().get("__file__", "-")))  # -c has none
    print("argv", sys.argv[1:], "cwd", os.getcwd(), "path0", sys.path[0] == here,
          "extra", os.environ["PYTHONPATH"] in sys.path,
          "var", os.environ.get("RESIREG_PROBE"), "main", __name__, "umask", oct(os.umask(0)),
          flush=True)
    with open(os.environ["RESIREG_PROBE_PARENT"], "a") as parent:
        parent.write(f"{os.getppid()}\\n")
    atexit.register(lambda: print("atexit ran", flush=True))
    if mode == "thread":  # a non-daemon thread outliving main is joined before the exit
        threading.Thread(target=lambda: (time.sleep(0.3), print("thread done"))).start()
    elif mode == "code":
        sys.exit(3)
    elif mode == "message":
        sys.exit("a message")
    elif mode == "raise":
        raise ValueError("boom")
    elif mode == "ctrl-c":
        raise KeyboardInterrupt
""")


def _both(cmd, monkeypatch, **kwargs):
    """``cmd`` run warm then cold (started as :func:`helpers.run.run` starts it); the two
    CompletedProcess-like (returncode, stdout, stderr) triples."""
    said = []
    for cold in ("", "1"):
        monkeypatch.setenv("RESIREG_TEST_COLD_START", cold)
        with started(cmd, stderr=subprocess.PIPE, warm=True, **kwargs) as child:
            child.wait(120)
            said.append((child.returncode, child.stdout, child.stderr))
    monkeypatch.delenv("RESIREG_TEST_COLD_START")
    return said


@pytest.mark.parametrize("mode", ["ok", "thread", "code", "message", "raise", "ctrl-c"])
def test_a_script_ends_warm_as_it_ends_cold(tmp_path, monkeypatch, mode):
    """Exit code (sys.exit's int and message, an exception, Ctrl-C's death by SIGINT), stdout,
    stderr, argv, working folder, umask, sys.path and environment of a console script of this
    interpreter: the same warm and cold."""
    script = tmp_path / "bin" / "probe"
    script.parent.mkdir()
    script.write_text(f"#!{sys.executable}\n{_SCRIPT}")
    script.chmod(0o755)
    (tmp_path / "work").mkdir()
    parents = tmp_path / "parents"
    env = {**os.environ, "RESIREG_PROBE": "seen", "PYTHONPATH": str(tmp_path / "lib"),
           "RESIREG_PROBE_PARENT": str(parents)}  # fmt: skip
    (tmp_path / "lib").mkdir()
    before = os.umask(0o027)  # the tests' process's umask reaches the command
    try:
        warm, cold = _both([script, mode, "x y"], monkeypatch, env=env, cwd=tmp_path / "work")
    finally:
        os.umask(before)
    assert warm == cold
    # the first started warm (the server's child), the second cold (this process's)
    server = warm_start.server(warm_start.BASE_ENV)
    assert parents.read_text().split() == [str(server._process.pid), str(os.getpid())]
    code = {"ok": 0, "thread": 0, "code": 3, "message": 1, "raise": 1, "ctrl-c": -2}[mode]
    assert warm[0] == code, warm
    assert warm[1].startswith(f"argv ['{mode}', 'x y'] cwd {tmp_path / 'work'} path0 True extra "
                              "True var seen main __main__ umask 0o27\n")  # fmt: skip
    assert "atexit ran" in warm[1] and ("thread done" in warm[1]) == (mode == "thread")


@pytest.mark.parametrize("form", ["file", "-m", "-c"])
def test_python_file_m_and_c_end_warm_as_they_end_cold(tmp_path, monkeypatch, form):
    """``python file.py``, ``python -m module`` and ``python -c code``: the same sys.path[0],
    argv, output and traceback warm and cold, the warm one the server's child."""
    lib = tmp_path / "lib"
    lib.mkdir()
    (lib / "probe.py").write_text(_SCRIPT)
    (tmp_path / "work").mkdir()
    parents = tmp_path / "parents"
    env = {**os.environ, "RESIREG_PROBE": "seen", "PYTHONPATH": str(lib),
           "RESIREG_PROBE_PARENT": str(parents)}  # fmt: skip
    given = {"file": [lib / "probe.py"], "-m": ["-m", "probe"], "-c": ["-c", _SCRIPT]}[form]
    warm, cold = _both([sys.executable, *given, "raise", "x y"], monkeypatch, env=env,
                       cwd=tmp_path / "work")  # fmt: skip
    assert warm == cold and warm[0] == 1 and "ValueError: boom" in warm[2], (warm, cold)
    server = warm_start.server(warm_start.BASE_ENV)
    assert parents.read_text().split() == [str(server._process.pid), str(os.getpid())]


def test_the_warm_start_is_used_and_refused_where_it_must_be(tmp_path):
    """The server takes a command whose environment differs in a variable no pre-imported
    library reads at import; it refuses, naming it, one that changes such a variable
    (HF_HOME: huggingface_hub reads it when imported), unsets the thread count it runs
    with, or puts a folder shadowing a pre-imported package on PYTHONPATH."""
    server = warm_start.server(warm_start.BASE_ENV)
    base = dict(server.env)
    assert server.refusal({**base, "RESIREG_X": "1", "MLFLOW_TRACKING_URI": "http://h"}) is None
    assert server.refusal({**base, "HF_HOME": str(tmp_path)}) == "environment variable HF_HOME"
    (tmp_path / "torch").mkdir()
    why = server.refusal({**base, "PYTHONPATH": str(tmp_path)})
    assert why == f"PYTHONPATH folder {tmp_path} shadows ['torch']"
    if "OMP_NUM_THREADS" in base:
        unset = {k: v for k, v in base.items() if k != "OMP_NUM_THREADS"}
        assert server.refusal(unset) == "environment variable OMP_NUM_THREADS unset"


@pytest.mark.slow
def test_no_preloaded_library_configures_logging_by_the_root_logger():
    """Every library the server imports sets up its loggers alike whether or not the root
    logger has a handler at its import (Hydra configures logging before a command imports
    what it needs; the server imports first): the loggers' handlers, propagation and levels
    compared across the two orders."""
    probe = textwrap.dedent(f"""\
        import importlib, json, logging, sys
        if sys.argv[1] == "root":
            logging.root.addHandler(logging.NullHandler())
        for name in {warm_start.PRELOADED!r}:
            importlib.import_module(name)
        print(json.dumps({{n: [[type(h).__name__ for h in x.handlers], x.propagate, x.level]
                          for n, x in logging.root.manager.loggerDict.items()
                          if isinstance(x, logging.Logger)}}))
    """)
    # the root logger with a handler first, in a fresh interpreter; without one: the server's
    # own state (it imported them so), read by a command forked from it
    root = subprocess.run([sys.executable, "-c", probe, "root"], check=True, capture_output=True,
                          text=True).stdout  # fmt: skip
    states = [json.loads(root), json.loads(run(sys.executable, "-c", probe, "none").stdout)]
    differ = sorted(
        n for n in set(states[0]) | set(states[1]) if states[0].get(n) != states[1].get(n)
    )
    assert not differ, differ
    assert "torch" in states[0]  # the probe imported them


@pytest.mark.slow
def test_a_warm_training_prints_and_records_what_a_cold_one_does(tmp_path, monkeypatch):
    """One smoke epoch through `resireg-train`, warm then cold: the same lines on stdout and
    stderr (their times and folder aside) and the same final scores in results.json."""
    outputs, finals = [], []
    for cold in ("", "1"):
        monkeypatch.setenv("RESIREG_TEST_COLD_START", cold)
        out = tmp_path / ("cold" if cold else "warm")
        proc = run("resireg-train", "experiment=smoke", "trainer.max_epochs=1",
                   f"hydra.run.dir={out}", threads=1)  # fmt: skip

        def plain(text, out=out):
            text = text.replace(str(out), "<run>")
            text = re.sub(r"^\[[\d\- :,]+\]", "", text, flags=re.M)
            return re.sub(r"\| [\d.]+ s$", "", text, flags=re.M)

        outputs.append((plain(proc.stdout), plain(proc.stderr)))
        finals.append(json.loads((out / "results.json").read_text())["final"])
    assert outputs[0] == outputs[1]
    assert finals[0] == finals[1] and finals[0]
