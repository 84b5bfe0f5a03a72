"""Run the console scripts in a fresh process, as a user would (shared by several tests)."""

import json
import os
import shutil
import signal
import subprocess
import sys

_MODULES = {
    "resireg-train": "resireg_train.cli.train",
    "resireg-eval": "resireg_train.cli.eval",
    "resireg-report": "resireg_train.cli.report",
    "resireg-map": "resireg_train.cli.map",
}


def _ctrl_c_as_in_a_terminal() -> None:
    """The child takes SIGINT as a terminal's Ctrl-C would reach it. A shell that starts the
    suite in the background (`cmd &`, no job control) makes its children ignore SIGINT, an
    ignored disposition survives exec, and Python then installs no KeyboardInterrupt handler:
    the Ctrl-C test would see its signal vanish."""
    signal.signal(signal.SIGINT, signal.SIG_DFL)


def run(script, *args, timeout=600, check=True, env=None):
    """``script args...`` offline (in ``env``, default this process's environment); returns the
    CompletedProcess (asserts success if ``check``)."""
    exe = shutil.which(script)
    cmd = [exe] if exe else [sys.executable, "-m", _MODULES[script]]
    proc = subprocess.run(
        [*cmd, *map(str, args)], capture_output=True, text=True, timeout=timeout,
        env={**(os.environ if env is None else env), "HF_HUB_OFFLINE": "1"},
        preexec_fn=_ctrl_c_as_in_a_terminal,
    )  # fmt: skip
    if check:
        assert proc.returncode == 0, proc.stdout[-2000:] + proc.stderr[-3000:]
    return proc


def evaluate_export(export, out, *overrides):
    """``resireg-eval`` of an export on the smoke experiment's eval set; returns its scores."""
    run("resireg-eval", f"model_path={export}", "dataset=synthetic", "num_workers=0",
        "full.n_prototypes=12", f"hydra.run.dir={out}", *overrides)  # fmt: skip
    results = json.loads((out / "results.json").read_text())
    assert results["status"] == "completed"
    return results["final"]
