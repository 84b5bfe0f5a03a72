"""A PostgreSQL server of a test's own (Debian's ``postgresql`` package): the Optuna searches
whose study lives in a database, with and without a password."""

from __future__ import annotations

import contextlib
import os
import shutil
import socket
import subprocess
import tempfile
from collections.abc import Iterator
from pathlib import Path

import pytest


def _postgres_bin() -> Path | None:
    found = sorted(Path("/usr/lib/postgresql").glob("*/bin/initdb"))
    return found[-1].parent if found else None


@contextlib.contextmanager
def postgres_server(password: str | None = None) -> Iterator[dict[str, str]]:
    """A server with an ``optuna`` database, as the package's postgres user (initdb refuses
    root), on a Unix socket in a temporary folder; yields the environment (PGHOST / PGPORT /
    PGUSER) that reaches it. ``password``: the server asks for it (scram-sha-256); it is not in
    the environment yielded. Skips the test where PostgreSQL is not installed."""
    bindir = _postgres_bin()
    if bindir is None:
        pytest.skip("PostgreSQL's initdb is not installed (Debian: apt-get install postgresql)")
    as_postgres: list[str] = []
    if os.geteuid() == 0:
        if shutil.which("runuser") is None:
            pytest.skip("running as root without runuser: cannot start PostgreSQL as postgres")
        as_postgres = ["runuser", "-u", "postgres", "--"]
    folder = Path(tempfile.mkdtemp(prefix="resireg-pg-"))
    pw = folder / "pw"
    auth = ["--auth=trust"]
    if password is not None:
        pw.write_text(password + "\n")
        auth = ["--auth=scram-sha-256", f"--pwfile={pw}"]
    if as_postgres:
        for path in (folder, pw) if password is not None else (folder,):
            shutil.chown(path, "postgres", "postgres")
    with socket.socket() as s:
        s.bind(("127.0.0.1", 0))
        port = s.getsockname()[1]
    data, pg = folder / "data", [*as_postgres]
    subprocess.run([*pg, bindir / "initdb", "-D", data, "-U", "postgres", *auth],
                   check=True, capture_output=True)  # fmt: skip
    pw.unlink(missing_ok=True)
    subprocess.run([*pg, bindir / "pg_ctl", "-D", data, "-w", "-l", folder / "log", "-o",
                    f"-k {folder} -p {port} -c listen_addresses=''", "start"],
                   check=True, capture_output=True)  # fmt: skip
    env = {"PGHOST": str(folder), "PGPORT": str(port), "PGUSER": "postgres"}
    login = {} if password is None else {"PGPASSWORD": password}
    try:
        subprocess.run([*pg, bindir / "createdb", "-h", folder, "-p", str(port), "optuna"],
                       check=True, capture_output=True, env={**os.environ, **env, **login})  # fmt: skip
        yield env
    finally:
        subprocess.run([*pg, bindir / "pg_ctl", "-D", data, "-m", "immediate", "stop"],
                       capture_output=True)  # fmt: skip
        shutil.rmtree(folder, ignore_errors=True)
