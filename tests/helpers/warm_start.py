"""Commands started warm: a console script run in a process forked from an interpreter that has
already imported the heavy libraries every command imports (torch, Lightning, Hydra, timm, ...),
instead of a fresh interpreter that imports them again (7-8 s of each command's start on these
machines, most of what a short command costs).

The forked process is a real process as :func:`helpers.run.started` makes one: its own PID and
session (process group), SIGINT and SIGTERM at a fresh interpreter's defaults, stdin from
/dev/null, stdout and stderr pipes, the command's argv, environment, working folder, the tests'
process's umask and resource limits, and ``sys.path`` (its script's folder, then
``PYTHONPATH``), its exit code as Python gives it (an uncaught exception: 1; ``sys.exit(x)``: as
the interpreter reads ``x``; Ctrl-C: killed by SIGINT), its non-daemon threads joined and its
``atexit`` functions run before it exits. What the imports printed on stderr (warnings) is
printed again at its start, as a fresh interpreter would print it.

What a warm start cannot give, and then a command starts fresh (:func:`helpers.run.started`
decides; ``RESIREG_TEST_COLD_START=1`` starts every command fresh): an environment that differs
from the server's in a variable some pre-imported library reads when it is imported (one of
:data:`_READ_AT_IMPORT`), a ``PYTHONPATH`` folder shadowing a
pre-imported package, a terminal, a ``preexec`` function, input on stdin. Tests about the
process start itself (start-up time, imports) start their interpreters with ``subprocess``.

By hand: this is what multiprocessing's "forkserver" does for functions, here for console
scripts; no library offers it for a command line (pytest-xdist's workers and
multiprocessing's start methods run Python functions, not a script's ``__main__`` with its own
argv, environment and file descriptors)."""

import contextlib
import json
import os
import resource
import select
import signal
import socket
import subprocess
import sys
import threading

#: What the console scripts of the project import before they do their work, less Lightning:
#: Lightning gives its loggers a handler of their own when the root logger has none at its
#: import, so whether it is imported before or after Hydra configures logging changes what a
#: command prints (with its dependencies loaded it imports in a quarter of a second). None of
#: these configures logging by the root logger's state (tests/project/test_warm_start.py).
PRELOADED = ("torch", "numpy", "PIL.Image", "torchvision", "torchmetrics", "hydra", "omegaconf",
             "timm", "open_clip")  # fmt: skip

#: Environment variables (prefixes) the interpreter or a pre-imported library reads when it
#: starts or is imported: a command whose environment differs from the server's in one of them
#: starts cold. Any other variable (what a test sets, what a library sets in the tests' process
#: as it runs) is read when used, in the command's own process.
_READ_AT_IMPORT = ("PYTHON", "HF_", "HUGGINGFACE_", "TRANSFORMERS_", "USE_TORCH", "USE_TF",
                   "USE_JAX", "TORCH", "PYTORCH_", "CUDA_", "NVIDIA_", "TRITON_", "OMP_", "MKL_",
                   "OPENBLAS_", "GOTO", "TIMM_", "MPL", "XDG_", "HOME", "LANG", "LC_", "TZ",
                   "NUMPY_", "SCIPY_", "LD_", "TF_", "JAX_", "XLA_", "SAFETENSORS_",
                   "TOKENIZERS_")  # fmt: skip
#: ... except these: applied in the forked process (the thread counts through
#: ``torch.set_num_threads``, PYTHONPATH through ``sys.path``), or read when used (the rest: set
#: by libraries in the tests' process as tests run).
_APPLIED_OR_READ_WHEN_USED = ("PYTHONPATH", "OMP_NUM_THREADS", "MKL_NUM_THREADS",
                              "TORCHINDUCTOR_CACHE_DIR", "PYTORCH_NVML_BASED_CUDA_CHECK",
                              "TOKENIZERS_PARALLELISM")  # fmt: skip


#: The resource limits a child inherits from the tests' process (with its umask), applied in the
#: forked process.
_LIMITS = ("RLIMIT_FSIZE", "RLIMIT_NOFILE", "RLIMIT_AS", "RLIMIT_DATA", "RLIMIT_CORE",
           "RLIMIT_CPU", "RLIMIT_STACK")  # fmt: skip


def _safe(name: str) -> bool:
    """Whether a command may start warm with ``name`` set otherwise than in the server."""
    return name in _APPLIED_OR_READ_WHEN_USED or not name.startswith(_READ_AT_IMPORT)


#: The environment of the tests' process when it started (before any test changed it): the
#: warm-start server runs in it.
BASE_ENV = {**os.environ, "HF_HUB_OFFLINE": "1"}


# ------------------------------------------------------------------------------------ the server
_THIS_FILE = __file__  # a command's traceback leaves out this file's frames


def _exit_code(exit: SystemExit) -> int:
    """The exit status Python gives ``sys.exit(code)`` (Python/pythonrun.c's handling)."""
    code = exit.code
    if code is None:
        return 0
    if isinstance(code, int):
        return code & 0xFF
    with contextlib.suppress(Exception):
        print(code, file=sys.stderr)
    return 1


def _run_child(request, fds, import_stderr: bytes, base_path: list[str]) -> None:
    """In the forked process: become the command, run its script as ``__main__``, exit."""
    import runpy
    import tempfile
    import types

    import numpy
    import torch

    signal.set_wakeup_fd(-1)
    signal.signal(signal.SIGCHLD, signal.SIG_DFL)
    signal.signal(signal.SIGINT, signal.default_int_handler)  # a fresh interpreter's
    signal.signal(signal.SIGTERM, signal.SIG_DFL)
    os.setsid()
    for target, fd in enumerate(fds):
        os.dup2(fd, target)
        os.close(fd)
    os.chdir(request["cwd"])
    os.umask(request["umask"])  # what a child inherits from the tests' process
    for name, limits in request["limits"].items():
        with contextlib.suppress(ValueError, OSError):
            resource.setrlimit(getattr(resource, name), tuple(limits))
    os.environ.clear()
    os.environ.update(request["env"])
    if "OMP_NUM_THREADS" in os.environ:
        torch.set_num_threads(int(os.environ["OMP_NUM_THREADS"]))
    tempfile.tempdir = None  # found again from this environment's TMPDIR
    numpy.random.seed()  # a fresh interpreter seeds its own (Python's random reseeds at fork)
    argv = list(request["argv"])
    extra = [p for p in os.environ.get("PYTHONPATH", "").split(os.pathsep) if p]
    if argv[0] == sys.executable:  # `python -m module`, `python -c code`, `python file.py`
        form = argv[1] if argv[1] in ("-m", "-c") else "script"
        argv = argv if form != "script" else argv[1:]
    else:  # a console script (its shebang names this interpreter)
        form = "script"
    # sys.path[0] and sys.argv as the interpreter sets them for `python -m`, `-c` and a script
    # (its folder, links resolved)
    first = {"-m": os.getcwd(), "-c": "", "script": os.path.dirname(os.path.realpath(argv[0]))}[
        form
    ]
    sys.path[:] = [first, *extra, *base_path]
    sys.argv = {"-m": argv[2:], "-c": ["-c", *argv[3:]], "script": argv}[form]
    os.write(2, import_stderr)
    code, interrupted = 0, False
    try:
        if form == "-m":  # what `python -m` calls (its two frames show in a traceback), in a
            # __main__ of its own (it runs the module in the __main__ it finds: this one's)
            sys.modules["__main__"] = types.ModuleType("__main__")
            runpy._run_module_as_main(argv[2])
        elif form == "-c":
            main = sys.modules["__main__"] = types.ModuleType("__main__")
            exec(compile(argv[2], "<string>", "exec"), main.__dict__)
        else:
            runpy.run_path(argv[0], run_name="__main__")
    except SystemExit as exit:
        code = _exit_code(exit)
    except BaseException as error:
        tb = error.__traceback__  # from the command's own frames on, as a fresh one shows it
        ours = (_THIS_FILE,) if form == "-m" else (_THIS_FILE, "<frozen runpy>")
        while tb is not None and tb.tb_frame.f_code.co_filename in ours:
            tb = tb.tb_next
        error = error.with_traceback(tb)  # None: it failed before its code ran (a syntax error)
        sys.excepthook(type(error), error, error.__traceback__)
        code, interrupted = 1, isinstance(error, KeyboardInterrupt)
    # what Py_FinalizeEx does before the process ends: join non-daemon threads, atexit, flush
    with contextlib.suppress(BaseException):
        threading._shutdown()
    with contextlib.suppress(BaseException):
        import atexit

        atexit._run_exitfuncs()
    for stream in (sys.stdout, sys.stderr):
        with contextlib.suppress(BaseException):
            stream.flush()
    if interrupted:  # Python ends an uncaught KeyboardInterrupt killed by SIGINT
        signal.signal(signal.SIGINT, signal.SIG_DFL)
        os.kill(os.getpid(), signal.SIGINT)
    os._exit(code)


def _serve(control: socket.socket) -> None:
    import importlib
    import tempfile

    with tempfile.TemporaryFile() as said:  # what the imports print on stderr
        saved = os.dup(2)
        os.dup2(said.fileno(), 2)
        try:
            for name in PRELOADED:
                importlib.import_module(name)
        finally:
            sys.stderr.flush()
            os.dup2(saved, 2)
            os.close(saved)
        said.seek(0)
        import_stderr = said.read()
    base_path = sys.path[1:]  # a fresh interpreter's path after its script's folder
    modules = sorted({m.split(".")[0] for m in sys.modules})
    wake_r, wake_w = os.pipe()
    for fd in (wake_r, wake_w):
        os.set_blocking(fd, False)
    signal.set_wakeup_fd(wake_w)
    signal.signal(signal.SIGCHLD, lambda *_: None)
    hello = {"ready": True, "modules": modules, "path": base_path}
    control.sendall(json.dumps(hello).encode())
    replies: dict[int, socket.socket] = {}
    while True:
        ready, _, _ = select.select([control, wake_r], [], [])
        if wake_r in ready:
            with contextlib.suppress(BlockingIOError):
                os.read(wake_r, 4096)
        while replies:
            try:
                pid, status = os.waitpid(-1, os.WNOHANG)
            except ChildProcessError:
                break
            if pid == 0:
                break
            reply = replies.pop(pid, None)
            if reply is not None:
                with contextlib.suppress(OSError):
                    reply.sendall(json.dumps({"status": status}).encode())
                reply.close()
        if control in ready:
            message, fds, _, _ = socket.recv_fds(control, 1 << 20, 4)
            if not message:  # the tests' process has gone
                return
            request = json.loads(message)
            *std, reply_fd = fds
            reply = socket.socket(fileno=reply_fd)
            pid = os.fork()
            if pid == 0:
                control.close()
                reply.close()
                for other in replies.values():
                    other.close()
                os.close(wake_r)
                os.close(wake_w)
                try:
                    _run_child(request, std, import_stderr, base_path)
                finally:
                    os._exit(1)
            for fd in std:
                os.close(fd)
            replies[pid] = reply
            reply.sendall(json.dumps({"pid": pid}).encode())


# ------------------------------------------------------------------------------------ the client
class WarmPopen:
    """The part of ``subprocess.Popen`` :class:`helpers.run.Child` uses, for a warm start."""

    def __init__(self, args, reply: socket.socket, stdout, stderr):
        self.args, self._reply = args, reply
        self.stdin, self.stdout, self.stderr = None, stdout, stderr
        self.returncode = None
        self.pid = json.loads(self._receive(None))["pid"]

    def _receive(self, timeout):
        self._reply.settimeout(timeout)
        message = self._reply.recv(4096)
        if not message:
            raise RuntimeError(f"the warm-start server ended before {self.args[0]!r} did")
        return message

    def _done(self, message) -> int:
        self.returncode = os.waitstatus_to_exitcode(json.loads(message)["status"])
        self._reply.close()
        return self.returncode

    def poll(self):
        if self.returncode is None:
            try:
                self._done(self._receive(0))
            except (BlockingIOError, TimeoutError):
                pass
        return self.returncode

    def wait(self, timeout=None):
        if self.returncode is None:
            try:
                self._done(self._receive(timeout))
            except (TimeoutError, BlockingIOError):  # a timeout of 0 reads without blocking
                raise subprocess.TimeoutExpired(self.args, timeout) from None
        return self.returncode

    def send_signal(self, sig):
        if self.returncode is None:
            os.kill(self.pid, sig)


class Server:
    """One warm interpreter per test process, started at its first warm start."""

    def __init__(self, env: dict):
        self.env = dict(env)
        ours, theirs = socket.socketpair(socket.AF_UNIX, socket.SOCK_SEQPACKET)
        self._process = subprocess.Popen(
            [sys.executable, __file__, str(theirs.fileno())], pass_fds=[theirs.fileno()],
            env=self.env, stdin=subprocess.DEVNULL, stdout=subprocess.DEVNULL,
            stderr=subprocess.DEVNULL, start_new_session=True, cwd="/",
        )  # fmt: skip
        theirs.close()
        self._control, self._lock = ours, threading.Lock()
        self._control.settimeout(600)
        hello = self._control.recv(1 << 20)
        if not hello:
            raise RuntimeError(f"the warm-start server exited ({self._process.wait()})")
        hello = json.loads(hello)
        self.modules = set(hello["modules"])
        self.path = {os.path.realpath(p) for p in hello["path"] if p}

    def refusal(self, env: dict) -> str | None:
        """Why a command in ``env`` cannot start warm (None: it can)."""
        for name in sorted(set(env) | set(self.env)):
            if env.get(name) != self.env.get(name) and not _safe(name):
                return f"environment variable {name}"
        for name in ("OMP_NUM_THREADS", "MKL_NUM_THREADS"):
            if name in self.env and name not in env:
                return f"environment variable {name} unset"
        for folder in env.get("PYTHONPATH", "").split(os.pathsep):
            # a folder of the server's own path holds the files it imported from
            if folder and os.path.isdir(folder) and os.path.realpath(folder) not in self.path:
                names = {n.removesuffix(".py") for n in os.listdir(folder)}
                if names & self.modules:
                    return f"PYTHONPATH folder {folder} shadows {sorted(names & self.modules)}"
        return None

    def start(self, argv, env, cwd) -> WarmPopen:
        out_r, out_w = os.pipe()
        err_r, err_w = os.pipe()
        ours, theirs = socket.socketpair(socket.AF_UNIX, socket.SOCK_SEQPACKET)
        with open(os.devnull, "rb") as stdin:
            umask = os.umask(0)
            os.umask(umask)
            request = {"argv": list(argv), "env": dict(env), "cwd": str(cwd or os.getcwd()),
                       "umask": umask, "limits": {name: resource.getrlimit(getattr(resource, name))
                                                  for name in _LIMITS}}  # fmt: skip
            with self._lock:
                socket.send_fds(self._control, [json.dumps(request).encode()],
                                [stdin.fileno(), out_w, err_w, theirs.fileno()])  # fmt: skip
        for fd in (out_w, err_w):
            os.close(fd)
        theirs.close()
        return WarmPopen(argv, ours, os.fdopen(out_r, "rb"), os.fdopen(err_r, "rb"))


_server: Server | None = None


def server(env: dict) -> Server:
    """This process's warm-start server (started with ``env`` at the first call)."""
    global _server
    if _server is None or _server._process.poll() is not None:
        _server = Server(env)
    return _server


if __name__ == "__main__":
    _serve(socket.socket(fileno=int(sys.argv[1])))
