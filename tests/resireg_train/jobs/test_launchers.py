"""A multirun's failed-job summary when the jobs run outside the launching process.

``hydra/launcher=submitit_slurm`` runs each job on a cluster node, so the process that launched
the sweep never runs a job: its summary must come from the jobs' ``results.json``. submitit's
local executor (``hydra/launcher=submitit_local``, the same Hydra launcher plugin) runs each job
in its own process, which is that situation on one machine.
"""

from __future__ import annotations

import json

import pytest

from helpers.run import run

pytest.importorskip("hydra_plugins.hydra_submitit_launcher", reason="the slurm extra")


@pytest.mark.slow
def test_jobs_run_elsewhere_are_listed_from_their_records(tmp_path, tiny_export):
    """Two jobs in two submitit processes, one with a bad config value: the launching process
    ends with the one failed job's line, and a failed record left in the sweep folder by an
    earlier launch (a resumed search's folder) is neither counted nor listed."""
    sweep = tmp_path / "sweep"
    earlier = sweep / "7_batch_size=3"
    earlier.mkdir(parents=True)
    (earlier / "results.json").write_text(json.dumps({"status": "failed", "error": "old"}))
    proc = run("resireg-eval", "-m", "hydra/launcher=submitit_local", f"model_path={tiny_export}",
               "dataset=synthetic", "dataset.size=4", "num_workers=0", "variants=[bb]",
               "batch_size=2,0", f"hydra.sweep.dir={sweep}", check=False)  # fmt: skip
    assert proc.returncode == 1, proc.stderr[-3000:]
    good, bad = (next(sweep.glob(f"{n}_batch_size={b},*")) for n, b in ((0, 2), (1, 0)))
    assert json.loads((good / "results.json").read_text())["status"] == "completed"
    assert json.loads((bad / "results.json").read_text())["status"] == "failed"
    tail = proc.stderr.strip().splitlines()[-2:]
    assert tail == [
        f"resireg-eval: 1 of 2 jobs failed (sweep {sweep}; resireg-report {sweep} lists every "
        "job):",
        f"  job 1 ({bad.name}): resireg.errors.ConfigError: invalid config: "
        "batch_size=0: expected an integer >= 1",
    ], proc.stderr[-3000:]
