"""Run the console scripts in a fresh process, as a user would (shared by several tests)."""

import contextlib
import io
import json
import os
import shutil
import signal
import subprocess
import sys
from concurrent.futures import ThreadPoolExecutor

_MODULES = {
    "resireg-train": "resireg_train.cli.train",
    "resireg-eval": "resireg_train.cli.eval",
    "resireg-report": "resireg_train.cli.report",
    "resireg-map": "resireg_train.cli.map",
    "resireg-map-merge": "resireg_train.cli.map_merge",
}


def _ctrl_c_as_in_a_terminal() -> None:
    """The child takes SIGINT as a terminal's Ctrl-C would reach it. A shell that starts the
    suite in the background (`cmd &`, no job control) makes its children ignore SIGINT, an
    ignored disposition survives exec, and Python then installs no KeyboardInterrupt handler:
    the Ctrl-C test would see its signal vanish."""
    signal.signal(signal.SIGINT, signal.SIG_DFL)


def _command(script, args):
    exe = shutil.which(script)
    return [*([exe] if exe else [sys.executable, "-m", _MODULES[script]]), *map(str, args)]


def _env(env, threads=None):
    env = {**(os.environ if env is None else env), "HF_HUB_OFFLINE": "1"}
    if threads is not None:  # torch's intra-op threads (side by side: 1 each, no contention)
        env["OMP_NUM_THREADS"] = env["MKL_NUM_THREADS"] = str(threads)
    return env


def _checked(proc, check):
    if check:
        assert proc.returncode == 0, proc.stdout[-2000:] + proc.stderr[-3000:]
    return proc


def run(script, *args, timeout=600, check=True, env=None, threads=None):
    """``script args...`` offline (in ``env``, default this process's environment; ``threads``:
    its OMP_NUM_THREADS); returns the CompletedProcess (asserts success if ``check``)."""
    proc = subprocess.run(
        _command(script, args), capture_output=True, text=True, timeout=timeout,
        env=_env(env, threads), preexec_fn=_ctrl_c_as_in_a_terminal,
    )  # fmt: skip
    return _checked(proc, check)


def run_side_by_side(*commands, timeout=600, check=True, env=None, threads=1):
    """Independent ``(script, *args)`` commands as :func:`run` runs them, but started together
    (their start-up, mostly single-threaded imports, overlaps on the cores), each with
    ``threads`` torch threads; returns their CompletedProcesses in order, each checked as
    :func:`run` checks it (``check``: one flag for all, or one per command). A test whose
    point is the order of runs keeps :func:`run`."""
    procs = [
        subprocess.Popen(
            _command(script, args),
            stdout=subprocess.PIPE,
            stderr=subprocess.PIPE,
            text=True,
            env=_env(env, threads),
            preexec_fn=_ctrl_c_as_in_a_terminal,
        )
        for script, *args in commands
    ]

    def finish(proc):  # read every pipe at once: no child waits on a full one
        out, err = proc.communicate(timeout=timeout)
        return subprocess.CompletedProcess(proc.args, proc.returncode, out, err)

    try:
        with ThreadPoolExecutor(len(procs)) as pool:
            done = list(pool.map(finish, procs))
    finally:
        for proc in procs:
            if proc.poll() is None:
                proc.kill()
                proc.wait()
    checks = [check] * len(done) if isinstance(check, bool) else list(check)
    assert len(checks) == len(done), (checks, commands)
    return [_checked(proc, c) for proc, c in zip(done, checks, strict=True)]


def report(sweep, *args):
    """``resireg-report sweep args...`` in this process (its ``main``, as the console script
    calls it: the test is about the report, not the process start, and this process has
    already imported what the report needs); returns its stdout. A usage error is the
    SystemExit the console script would exit with."""
    from resireg_train.cli.report import main

    out = io.StringIO()
    with contextlib.redirect_stdout(out):
        main([str(sweep), *map(str, args)])
    return out.getvalue()


def evaluate(*overrides):
    """``resireg-eval overrides...`` in this process: ``eval.yaml`` composed with the overrides
    and :func:`resireg_train.cli.eval.evaluate` (the Hydra main's task), for a test that
    checks scores, not the process (torch is loaded here already); ``paths.output_dir=`` in
    place of ``hydra.run.dir=``. Returns results.json's content. Settings the export
    recorded fill the values left at their default, as on the command line (an override
    equal to its default is taken for one left at it: give other values)."""
    from hydra import compose, initialize_config_dir

    from resireg_train.cli.eval import evaluate
    from resireg_train.cli.job import CONFIG_DIR

    with initialize_config_dir(str(CONFIG_DIR), version_base="1.3"):
        cfg = compose("eval", overrides=[str(o) for o in overrides])
    return evaluate(cfg)


def evaluate_export(export, out, *overrides):
    """resireg-eval's task on an export and the smoke experiment's eval set, in this process
    (:func:`evaluate`; it was a ``resireg-eval`` process, whose start-up cost more than the
    evaluation); returns the scores its results.json holds."""
    evaluate(f"model_path={export}", "dataset=synthetic", "num_workers=0",
             "full.n_prototypes=12", f"paths.output_dir={out}", *overrides)  # fmt: skip
    results = json.loads((out / "results.json").read_text())  # the record as written
    assert results["status"] == "completed"
    return results["final"]
