"""The run-folder lock (resireg_train/jobs/run_folder.py) against a holder in another process
that takes the lock and writes its PID a moment later, as a job started at the same time does."""

import subprocess
import sys
import textwrap

import pytest

from helpers.run import started
from resireg_train.jobs.run_folder import LOCK_FILE, RunFolderBusy, hold_run_folder


def _holder(folder, write_after):
    """A process that locks ``folder``'s lock file, says so, and writes its PID
    ``write_after`` seconds later (never when None); it waits on stdin."""
    code = textwrap.dedent(f"""
        import fcntl, os, sys, time
        handle = open({str(folder / LOCK_FILE)!r}, "a+")
        fcntl.flock(handle.fileno(), fcntl.LOCK_EX | fcntl.LOCK_NB)
        print("locked", flush=True)
        if {write_after!r} is not None:
            time.sleep({write_after!r})
            handle.write(f"{{os.getpid()}}\\n")
            handle.flush()
        sys.stdin.read()
    """)
    return started([sys.executable, "-c", code], stdin=subprocess.PIPE)


@pytest.mark.parametrize(("write_after", "named"), [(0.3, "pid"), (None, "starting")])
def test_a_job_refused_while_the_holder_starts_names_its_pid_once_written(
    tmp_path, write_after, named
):
    """The lock taken and the PID not yet written: the refusal waits for it (up to 2 s) and
    names it; a holder that never writes it is said to be starting."""
    with _holder(tmp_path, write_after) as holder:
        holder.expect("locked", timeout=60, what="the lock taken")
        with pytest.raises(RunFolderBusy) as refused:
            hold_run_folder(tmp_path)
        said = str(refused.value)
        if named == "pid":
            assert f"in use by another job (PID {holder.pid}, lock file" in said, said
        else:
            assert "(PID unknown (it is starting), lock file" in said, said
        holder.kill()
