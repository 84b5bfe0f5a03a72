"""Run the console scripts in a fresh process, as a user would (shared by several tests), and
start every long-lived subprocess of a test (:func:`started`): SIGINT at its default, its own
process group, output read with timeouts, the whole group killed whatever happens."""

import contextlib
import io
import json
import os
import shlex
import shutil
import signal
import subprocess
import sys
import threading
import time
from pathlib import Path

import psutil

_MODULES = {
    "resireg-train": "resireg_train.cli.train",
    "resireg-eval": "resireg_train.cli.eval",
    "resireg-report": "resireg_train.cli.report",
    "resireg-map": "resireg_train.cli.map",
    # one module, two commands: its __main__ takes the command's name first
    "resireg-export": "resireg.deploy.cli export",
    "resireg-segment": "resireg.deploy.cli segment",
    "resireg-map-merge": "resireg_train.cli.map_merge",
}

#: Seconds a command that exited may take for the rest of its process group (data loader
#: workers, a tracker's service) to exit before they count as left behind.
GRACE = 10


def _ctrl_c_as_in_a_terminal() -> None:
    """The child takes SIGINT (and SIGTERM) as a terminal's Ctrl-C (or kill) would reach it. A
    shell without job control that starts the suite in the background (`cmd &`, `nohup cmd &`,
    some CI runners) makes it ignore SIGINT, an ignored disposition survives fork and exec, and
    Python then installs no KeyboardInterrupt handler: a test's SIGINT would vanish and its
    child outlive it."""
    signal.signal(signal.SIGINT, signal.SIG_DFL)
    signal.signal(signal.SIGTERM, signal.SIG_DFL)


def _command(script, args):
    # a path as given; else this interpreter's own console script first (a version manager's
    # shim on PATH would start another process to find it)
    own = Path(script) if os.path.isabs(script) else Path(sys.executable).with_name(script)
    exe = str(own) if own.is_file() else shutil.which(script)
    return [*([exe] if exe else [sys.executable, "-m", *_MODULES[script].split()]), *map(str, args)]


def _env(env, threads=None):
    env = {**(os.environ if env is None else env), "HF_HUB_OFFLINE": "1"}
    if threads is not None:  # torch's intra-op threads (side by side: 1 each, no contention)
        env["OMP_NUM_THREADS"] = env["MKL_NUM_THREADS"] = str(threads)
    return env


def _checked(proc, check):
    if check:
        assert proc.returncode == 0, proc.stdout[-2000:] + proc.stderr[-3000:]
    return proc


class _Lines:
    """The lines of one output of a child, read by a thread as they come (a child never
    stalls on a full pipe; a test waits for a line with a timeout, never on a blocking read).
    By hand: subprocess reads a pipe only to its end (communicate) or without a timeout
    (readline); a reader thread per pipe is its documented way round (pexpect's spawn would
    need a terminal, which changes what a command prints)."""

    def __init__(self, file):
        self._lines: list[str] = []
        self._ended = False
        self._changed = threading.Condition()
        self._thread = threading.Thread(target=self._read, args=(file,), daemon=True)
        self._thread.start()

    def _read(self, file):
        try:
            for line in file:
                with self._changed:
                    self._lines.append(line)
                    self._changed.notify_all()
        except OSError:  # a terminal's master side reads EIO once the child's side is closed
            pass
        finally:
            file.close()
            with self._changed:
                self._ended = True
                self._changed.notify_all()

    def text(self) -> str:
        with self._changed:
            return "".join(self._lines)

    def line(self, index: int, deadline: float) -> str | None:
        """Line ``index`` ('' once the output ended before it), ``None`` at the deadline."""
        with self._changed:
            while len(self._lines) <= index and not self._ended:
                left = deadline - time.monotonic()
                if left <= 0:
                    return None
                self._changed.wait(left)
            return self._lines[index] if index < len(self._lines) else ""

    def join(self, deadline: float) -> bool:
        """Whether the output ended (every writer closed it) by ``deadline``."""
        self._thread.join(max(0.0, deadline - time.monotonic()))
        return not self._thread.is_alive()


def _describe(procs) -> str:
    said = []
    for p in procs:
        try:
            said.append(f"PID {p.pid} {shlex.join(p.cmdline())[:200]!r}")
        except psutil.Error:
            said.append(f"PID {p.pid}")
    return "; ".join(said)


def _group(pgid: int) -> list[psutil.Process]:
    """The live (not zombie) processes of process group ``pgid``."""
    members = []
    for proc in psutil.process_iter():
        try:
            if os.getpgid(proc.pid) == pgid and proc.status() != psutil.STATUS_ZOMBIE:
                members.append(proc)
        except (OSError, psutil.Error):
            continue
    return members


def _wait_gone(procs, timeout: float) -> list[psutil.Process]:
    """Those of ``procs`` still running (zombies count as gone: where no init reaps them, they
    would stay) after waiting up to ``timeout`` seconds."""
    deadline = time.monotonic() + timeout
    while True:
        alive = []
        for proc in procs:
            with contextlib.suppress(psutil.Error):
                if proc.is_running() and proc.status() != psutil.STATUS_ZOMBIE:
                    alive.append(proc)
        if not alive or time.monotonic() >= deadline:
            return alive
        time.sleep(0.1)


class Child:
    """A process :func:`started` runs: its outputs as they come, waits that time out, and
    signals to it or to its process group (the group a command's own children join)."""

    def __init__(self, popen: subprocess.Popen, out: _Lines | None, err: _Lines | None):
        self.popen, self._out, self._err = popen, out, err
        self.args, self.pid = popen.args, popen.pid
        self._next = 0  # the next stdout line readline() gives

    def __str__(self) -> str:
        return f"{shlex.join(map(str, self.args))[:300]!r} (PID {self.pid})"

    @property
    def returncode(self) -> int | None:
        return self.popen.returncode

    def poll(self) -> int | None:
        return self.popen.poll()

    @property
    def stdout(self) -> str:
        """What it printed so far on stdout (with ``stderr=STDOUT``: on both; a terminal's
        screen with ``terminal=True``); '' when stdout is not a pipe."""
        return self._out.text() if self._out else ""

    @property
    def stderr(self) -> str:
        return self._err.text() if self._err else ""

    def _tail(self) -> str:
        return (self.stdout[-3000:] + self.stderr[-3000:]) or "(nothing printed)"

    def readline(self, timeout: float) -> str:
        """Its next stdout line ('' once stdout ended); an AssertionError naming it and what it
        printed if none comes within ``timeout`` seconds."""
        line = self._out.line(self._next, time.monotonic() + timeout)
        if line is None:
            raise AssertionError(f"{self}: no line in {timeout} s; it printed:\n{self._tail()}")
        self._next += bool(line)
        return line

    def expect(self, match, timeout: float, what: str) -> str:
        """Its stdout lines until one for which ``match(line)`` holds (a str: the line's text
        without its newline); an AssertionError if the output ends or ``timeout`` passes."""
        if isinstance(match, str):
            text, match = match, lambda line: line.rstrip("\r\n") == text
        deadline = time.monotonic() + timeout
        while True:
            line = self.readline(max(0.0, deadline - time.monotonic()))
            if not line:
                raise AssertionError(f"{self} ended (exit {self.popen.wait()}) before {what}:"
                                     f"\n{self._tail()}")  # fmt: skip
            if match(line):
                return line

    def send(self, sig: int, group: bool = False) -> None:
        """``sig`` to the process (``group``: to its whole process group)."""
        with contextlib.suppress(ProcessLookupError):
            os.killpg(self.pid, sig) if group else self.popen.send_signal(sig)

    def wait(self, timeout: float) -> int:
        """Its exit code once it exited and its outputs ended; ``subprocess.TimeoutExpired``
        after ``timeout`` seconds (the ``with`` block then kills its group)."""
        self.popen.wait(timeout)
        deadline = time.monotonic() + GRACE
        for lines in (self._out, self._err):
            if lines and not lines.join(deadline):  # a process it started holds the pipe open
                left = _group(self.pid)
                raise AssertionError(f"{self} exited ({self.returncode}) but left running, "
                                     f"holding its output: {_describe(left) or '?'}")  # fmt: skip
        return self.popen.returncode

    def stop(self, sig: int = signal.SIGTERM, timeout: float = 60, group: bool = False) -> int:
        """Send ``sig`` (to the group with ``group``) and wait for the exit; an AssertionError
        if it does not stop within ``timeout`` seconds (and the group is killed)."""
        self.send(sig, group)
        try:
            return self.wait(timeout)
        except subprocess.TimeoutExpired:
            self.kill()
            name = signal.Signals(sig).name
            raise AssertionError(f"{self} did not stop within {timeout} s of {name}; it "
                                 f"printed:\n{self._tail()}") from None  # fmt: skip

    def kill(self) -> None:
        """SIGKILL to its process group and to every process it started that left the group;
        reaped."""
        try:
            stray = psutil.Process(self.pid).children(recursive=True)
        except psutil.Error:
            stray = []
        self.send(signal.SIGKILL, group=True)
        for proc in stray:
            with contextlib.suppress(psutil.Error):
                proc.kill()
        self.popen.wait()


def _warm(cmd, env, cwd):
    """``cmd`` started warm (:mod:`helpers.warm_start`), or None where it cannot be: not a
    console script, ``python -m``, ``python -c`` or ``python file.py`` of this environment's
    interpreter, an environment the warm interpreter cannot take on, or
    ``RESIREG_TEST_COLD_START`` set."""
    from helpers import warm_start

    def ours(python: str) -> bool:  # its folder too: another venv's shares the real file
        return os.path.dirname(python) == os.path.dirname(sys.executable) and \
            os.path.realpath(python) == os.path.realpath(sys.executable)  # fmt: skip

    if os.environ.get("RESIREG_TEST_COLD_START") or not os.path.isabs(cmd[0]):
        return None
    if ours(cmd[0]):
        if len(cmd) < 2 or (cmd[1] in ("-m", "-c") and len(cmd) < 3) or \
                (cmd[1] not in ("-m", "-c") and not cmd[1].endswith(".py")):  # fmt: skip
            return None
        cmd = [sys.executable, *cmd[1:]]
    else:
        try:
            with open(cmd[0], "rb") as script:
                first = script.readline().strip()
        except OSError:
            return None
        if not first.startswith(b"#!") or not ours(first[2:].decode()):
            return None
    server = warm_start.server(warm_start.BASE_ENV)
    why = server.refusal(env)
    return None if why else server.start(cmd, env, cwd)


@contextlib.contextmanager
def started(cmd, *, env=None, threads=None, cwd=None, stdin=subprocess.DEVNULL,
            stdout=subprocess.PIPE, stderr=subprocess.STDOUT, terminal=False,
            preexec=None, warm=False):  # fmt: skip
    """``cmd`` (a list) started for the ``with`` block, as every long-lived subprocess of a test
    is: SIGINT and SIGTERM at their default (whatever this process ignores), its own process
    group (session), offline (``env``, ``threads`` as :func:`run`'s), stdin from /dev/null
    unless given. ``stdout`` / ``stderr``: ``subprocess.PIPE`` (read by a thread: see
    :class:`Child`), ``subprocess.STDOUT`` (stderr into stdout), ``DEVNULL`` or a path (a log
    file). ``terminal``: a pseudo-terminal for stdin, stdout and stderr (what it shows is
    :attr:`Child.stdout`). ``preexec``: run in the child before the command.

    Leaving the block kills whatever of its process group still runs. When the block ends
    without an error and the command had exited, processes of its group still running
    ``GRACE`` seconds later fail the test, named (a command must not leave processes behind).

    ``warm``: a console script of this interpreter starts in a process forked from a warm one
    (:mod:`helpers.warm_start`) where it can (stdin from /dev/null, stdout and stderr pipes, no
    terminal, no ``preexec``, an environment it allows); otherwise, or with
    ``RESIREG_TEST_COLD_START=1``, in a fresh interpreter."""
    opened, out, err = [], None, None

    def target(where):
        if isinstance(where, (str, Path)):
            opened.append(open(where, "w"))
            return opened[-1]
        return where

    def before_exec():
        _ctrl_c_as_in_a_terminal()
        if preexec is not None:
            preexec()

    if terminal:
        import pty

        master, slave = pty.openpty()
        stdin = stdout = stderr = slave
    popen, argv, env = None, [str(c) for c in cmd], _env(env, threads)
    if warm and not terminal and preexec is None and stdin == subprocess.DEVNULL and \
            stdout == subprocess.PIPE and stderr == subprocess.PIPE:  # fmt: skip
        popen = _warm(argv, env, cwd)
    try:
        popen = popen or subprocess.Popen(
            argv, stdin=stdin, stdout=target(stdout), stderr=target(stderr), env=env, cwd=cwd,
            start_new_session=True, preexec_fn=before_exec,
        )  # fmt: skip
    finally:
        for file in opened:  # the child holds its own descriptor
            file.close()
    if terminal:
        os.close(slave)
        out = _Lines(io.TextIOWrapper(os.fdopen(master, "rb"), errors="replace"))
    else:
        if popen.stdout is not None:
            out = _Lines(io.TextIOWrapper(popen.stdout, errors="replace"))
        if popen.stderr is not None:
            err = _Lines(io.TextIOWrapper(popen.stderr, errors="replace"))
    if popen.stdin is not None:
        popen.stdin = io.TextIOWrapper(popen.stdin, write_through=True)
    child = Child(popen, out, err)
    ok = False
    try:
        yield child
        ok = True
    finally:
        exited = child.poll() is not None
        if not exited:
            child.kill()
        if popen.stdin is not None:
            with contextlib.suppress(OSError):
                popen.stdin.close()
        left = _group(child.pid)
        if left and ok and exited:
            left = _wait_gone(left, GRACE)
        said = _describe(left)
        for proc in left:
            with contextlib.suppress(psutil.Error):
                proc.kill()
        _wait_gone(left, 10)  # gone once the block ends
        deadline = time.monotonic() + 10
        for lines in (out, err):
            if lines:
                lines.join(deadline)
        if left and ok and exited:
            raise AssertionError(f"{child} exited ({child.returncode}) but left running (now "
                                 f"killed): {said}")  # fmt: skip


def run(script, *args, timeout=600, check=True, env=None, threads=None, preexec=None):
    """``script args...`` offline (in ``env``, default this process's environment; ``threads``:
    its OMP_NUM_THREADS; ``preexec``: see :func:`started`); returns the CompletedProcess
    (asserts success if ``check``). Past ``timeout`` seconds: ``subprocess.TimeoutExpired``,
    its process group killed."""
    return run_side_by_side((script, *args), timeout=timeout, check=check, env=env,
                            threads=threads, preexec=preexec)[0]  # fmt: skip


def run_side_by_side(*commands, timeout=600, check=True, env=None, threads=1, preexec=None):
    """Independent ``(script, *args)`` commands as :func:`run` runs them, but started together
    (their start-up, mostly single-threaded imports, overlaps on the cores), each with
    ``threads`` torch threads; returns their CompletedProcesses in order, each checked as
    :func:`run` checks it (``check``: one flag for all, or one per command). A test whose
    point is the order of runs keeps :func:`run`."""
    deadline = time.monotonic() + timeout
    with contextlib.ExitStack() as stack:
        children = [
            stack.enter_context(started(_command(script, args), env=env, threads=threads,
                                        stderr=subprocess.PIPE, preexec=preexec, warm=True))
            for script, *args in commands
        ]  # fmt: skip
        for child in children:
            try:
                child.wait(max(0.0, deadline - time.monotonic()))
            except subprocess.TimeoutExpired:
                raise subprocess.TimeoutExpired(child.args, timeout, child.stdout,
                                                child.stderr) from None  # fmt: skip
    done = [subprocess.CompletedProcess(c.args, c.returncode, c.stdout, c.stderr)
            for c in children]  # fmt: skip
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
    from resireg_train.config.paths import CONFIG_DIR

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
