"""Test-session settings: never touch the network, keep runs deterministic."""

import os
import sys
from pathlib import Path

# Hub look-ups fail at once instead of retrying name resolution for ~47 s.
os.environ.setdefault("HF_HUB_OFFLINE", "1")
os.environ.setdefault("HF_DATASETS_OFFLINE", "1")
os.environ.setdefault("TRANSFORMERS_OFFLINE", "1")
# pyproject's addopts run the suite in pytest-xdist workers, one per core (at most two). Each
# worker, and every process its tests start, computes on one thread unless told otherwise:
# two workers of two threads on two cores would oversubscribe them, and a parallel region of
# torch waits for its slowest thread. Set before torch loads.
if os.environ.get("PYTEST_XDIST_WORKER"):
    for _var in ("OMP_NUM_THREADS", "MKL_NUM_THREADS"):
        os.environ.setdefault(_var, "1")
# Tests that load a benchmark script by path: its `from _common import ...` (the scripts' shared
# helpers, found next to the script when run as `python benchmarks/x.py`).
sys.path.insert(0, str(Path(__file__).resolve().parents[1] / "benchmarks"))

import pytest  # noqa: E402
import torch  # noqa: E402


@pytest.fixture(autouse=True)
def _seed():
    torch.manual_seed(0)
    yield


@pytest.fixture(scope="session")
def tiny_export(tmp_path_factory):
    """An exported tiny ResiregVLM (random init: same architectures, no training)."""
    from _tiny import TINY_BACKBONE, TINY_HEAD, TINY_TEXT
    from resireg.models import ResiregVLM

    torch.manual_seed(0)
    path = tmp_path_factory.mktemp("export") / "export"
    ResiregVLM.build(TINY_BACKBONE, TINY_HEAD, TINY_TEXT).save_pretrained(path)
    return path


@pytest.fixture(scope="session")
def prototype_sweep(tmp_path_factory, tiny_export):
    """A real `resireg-eval sweep=prototype_batch_jobs` multirun (one job per setting) on a
    reduced grid (2 batch sizes x 3 prototype counts on the synthetic set); 1000 prototypes
    exceed the points of a batch, so those two jobs fail. Returns (sweep folder, process)."""
    from _run import run

    logs = tmp_path_factory.mktemp("sweeps")
    proc = run("resireg-eval", f"model_path={tiny_export}", "dataset=synthetic",
               "dataset.size=12", "num_workers=0", "sweep=prototype_batch_jobs", "batch_size=2,4",
               "full.n_prototypes=4,8,1000", f"paths.log_dir={logs}", check=False)  # fmt: skip
    (sweep,) = (logs / "prototype_batch" / "multirun").iterdir()
    return sweep, proc
