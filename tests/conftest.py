"""Test-session settings: never touch the network, keep runs deterministic."""

import contextlib
import glob
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

import psutil  # noqa: E402
import pytest  # noqa: E402
import torch  # noqa: E402

from helpers import warm_start  # noqa: E402, F401  (its BASE_ENV: the environment before any test)


@pytest.fixture(autouse=True)
def _seed():
    torch.manual_seed(0)
    yield


#: Python's shared helper processes, started once and kept for the life of this process: not
#: a test's to stop (matched in their command lines).
_SHARED_HELPERS = ("multiprocessing.resource_tracker", "multiprocessing.forkserver",
                   "_inductor/compile_worker", "_inductor.compile_worker",
                   "helpers/warm_start.py")  # fmt: skip


def _descendants() -> set[int]:
    """The PIDs of this process's descendants. Linux lists each thread's children in
    /proc/<pid>/task/<tid>/children (microseconds; psutil's scan of every process takes
    milliseconds, twice per test); psutil where that file is missing."""
    me = os.getpid()
    if not os.path.exists(f"/proc/{me}/task/{me}/children"):
        return {p.pid for p in psutil.Process().children(recursive=True)}
    found, todo = set(), [me]
    while todo:
        for path in glob.glob(f"/proc/{todo.pop()}/task/*/children"):
            try:
                pids = {int(x) for x in Path(path).read_text().split()}
            except OSError:  # the process has gone
                continue
            todo += pids - found
            found |= pids
    return found


def _kill_left_behind(pids, what: str) -> None:
    """Fail ``what`` naming the processes of ``pids`` still running (not zombies, not shared
    helpers) after a grace period, once killed."""
    from helpers.run import GRACE

    left = []
    for pid in pids:
        try:
            proc = psutil.Process(pid)
            cmdline = " ".join(proc.cmdline())
            if proc.status() != psutil.STATUS_ZOMBIE and not any(
                h in cmdline for h in _SHARED_HELPERS
            ):
                left.append((proc, cmdline))
        except psutil.Error:
            continue
    if not left:
        return
    _, alive = psutil.wait_procs([p for p, _ in left], timeout=GRACE)
    named = [f"PID {p.pid} {c[:200]!r}" for p, c in left if p in alive]
    for proc in alive:
        with contextlib.suppress(psutil.Error):
            proc.kill()
    if named:
        pytest.fail(f"{what} left running (now killed): {'; '.join(named)}", pytrace=False)


@pytest.fixture(autouse=True, scope="session")
def _no_process_left_by_the_session():
    """At the end of the session (of each xdist worker): no process started by a session
    fixture or a test is still running."""
    before = _descendants()
    yield
    _kill_left_behind(_descendants() - before, "the test session")


@pytest.fixture(autouse=True)
def _no_process_left_behind(request):
    """A test (with its function-scoped fixtures, torn down before this one) leaves no process
    running: one still running GRACE seconds after the test fails it, named, and is killed."""
    before = _descendants()
    yield
    _kill_left_behind(_descendants() - before, request.node.nodeid)


@pytest.fixture(autouse=True)
def _run_in_the_tests_own_folder(tmp_path, monkeypatch):
    """Each test runs in its own temporary folder, so that what a command writes relative to
    its working folder (Hydra's default ``outputs/``, MLflow's default artifact root
    ``./mlruns`` next to a database store) never lands in the checkout. A test that needs the
    checkout names it (``cwd=ROOT``)."""
    monkeypatch.chdir(tmp_path)


@pytest.fixture(autouse=True)
def _mlflow_tracking_uri_kept():
    """A training run in the test's own process sets MLflow's process-wide tracking URI
    (Lightning's ``MLFlowLogger`` calls ``mlflow.set_tracking_uri``), which then wins over
    ``MLFLOW_TRACKING_URI`` for every later test of the worker: it is put back after each test.
    (MLflow offers no public getter of the set value: its module attribute is read, as
    MLflow's own ``_use_tracking_uri`` does.)"""
    name = "mlflow.tracking._tracking_service.utils"
    before = getattr(sys.modules.get(name), "_tracking_uri", None)
    yield
    utils = sys.modules.get(name)
    if utils is not None and utils._tracking_uri != before:
        utils.set_tracking_uri(before)


@pytest.fixture(scope="session")
def mlflow_server(tmp_path_factory):
    """``mlflow server`` on 127.0.0.1 (a SQLite store and the artifacts in a ``store`` folder),
    started through ``helpers.run.started`` as every long-lived process of a test; its
    ``uri``, ``port`` and ``store`` (``server.db``, ``artifacts/``, ``server.log``). One server
    per test process (its start takes ~13 s): the tests using it name their runs, folders and
    models apart. The end of the session kills the server's process group (its uvicorn and job
    workers): a graceful stop is not what the tests using it are about, and took over 30 s on a
    loaded machine."""
    import shutil
    import socket
    import time
    import urllib.request
    from types import SimpleNamespace

    from helpers.run import started

    with socket.socket() as s:
        s.bind(("127.0.0.1", 0))
        port = s.getsockname()[1]
    store = tmp_path_factory.mktemp("mlflow") / "store"
    store.mkdir()
    exe = shutil.which("mlflow") or str(Path(sys.executable).with_name("mlflow"))
    with started([exe, "server", "--backend-store-uri", f"sqlite:///{store}/server.db",
                  "--artifacts-destination", store / "artifacts", "--host", "127.0.0.1",
                  "--port", port, "--workers", "1"], stdout=store / "server.log", cwd=store) as proc:  # fmt: skip
        uri = f"http://127.0.0.1:{port}"
        deadline = time.monotonic() + 180
        while True:
            try:
                with urllib.request.urlopen(f"{uri}/health", timeout=5) as response:
                    if response.status == 200:
                        break
            except OSError:
                pass
            if proc.poll() is not None or time.monotonic() > deadline:
                pytest.fail(f"mlflow server did not start: {(store / 'server.log').read_text()}")
            time.sleep(0.5)
        yield SimpleNamespace(uri=uri, port=port, store=store)


@pytest.fixture(scope="session")
def tiny_export(tmp_path_factory):
    """An exported tiny ResiregVLM (random init: same architectures, no training)."""
    from helpers.tiny import TINY_BACKBONE, TINY_HEAD, TINY_TEXT
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
    from helpers.run import run

    logs = tmp_path_factory.mktemp("sweeps")
    proc = run("resireg-eval", f"model_path={tiny_export}", "dataset=synthetic",
               "dataset.size=12", "num_workers=0", "sweep=prototype_batch_jobs", "batch_size=2,4",
               "full.n_prototypes=4,8,1000", f"paths.log_dir={logs}", check=False)  # fmt: skip
    (sweep,) = (logs / "prototype_batch" / "multirun").iterdir()
    return sweep, proc
