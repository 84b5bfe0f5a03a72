"""Run the console scripts in a fresh process, as a user would (shared by several tests)."""

import json
import os
import shutil
import subprocess
import sys

_MODULES = {
    "resireg-train": "resireg_train.cli.train",
    "resireg-eval": "resireg_train.cli.eval",
    "resireg-report": "resireg_train.cli.report",
}


def run(script, *args, timeout=600, check=True, env=None):
    """``script args...`` offline (in ``env``, default this process's environment); returns the
    CompletedProcess (asserts success if ``check``)."""
    exe = shutil.which(script)
    cmd = [exe] if exe else [sys.executable, "-m", _MODULES[script]]
    proc = subprocess.run(
        [*cmd, *map(str, args)], capture_output=True, text=True, timeout=timeout,
        env={**(os.environ if env is None else env), "HF_HUB_OFFLINE": "1"},
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
