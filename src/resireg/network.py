"""The one short connection check before anything waits on a server (the standard library
only: the ground floor, importable without torch, MLflow or ``resireg_train``).

:func:`reach` says, within a given number of seconds, whether a URL's server accepts a TCP
connection (or whether a local store's folder can be written), instead of a client's own
minutes of retries: the trackers (``resireg_train.record.trackers.base``, ``tracker.<name>.check_timeout``),
the model registry (``resireg-runs register``, ``model_path=models:/...`` of the commands, and
:mod:`resireg.models.vlm.registry` for ``ResiregVLM.from_pretrained``, ``resireg-segment``,
the ROS 2 node) and the weight hubs (:func:`resireg.models.hub.require_online`) all ask it.
"""

from __future__ import annotations

import socket
import tempfile
import threading
import urllib.request
from pathlib import Path
from urllib.parse import unquote, urlsplit

__all__ = ["local_store", "reach", "writable"]

#: The port of a URL that names none, by scheme (``postgresql+psycopg`` reads as ``postgresql``).
_PORTS = {"http": 80, "https": 443, "postgresql": 5432, "mysql": 3306, "mssql": 1433}


def local_store(url: str) -> Path | None:
    """The folder a local store URL writes into: a SQLite database's folder
    (``sqlite:///<file>``; ``sqlite://`` alone is in memory: ``None``), a ``file:`` URL's or a
    plain path's folder; ``None`` for a URL with a host (a server, another database)."""
    parts = urlsplit(url)
    scheme = parts.scheme.lower()
    if parts.hostname:
        return None
    if scheme.split("+")[0] == "sqlite":
        name = url.split(":///", 1)[1] if ":///" in url else ""
        name = name.split("?", 1)[0]
        return Path(name).expanduser().parent if name and name != ":memory:" else None
    if scheme == "file":
        return Path(unquote(parts.path)).expanduser()
    return Path(url).expanduser() if not scheme and url else None


def writable(folder: Path) -> str | None:
    """``None`` if ``folder`` exists or can be made (it is made now, as the store would make
    it) and a file can be written in it, else why not (the folder and the system's reason)."""
    try:
        folder.mkdir(parents=True, exist_ok=True)
        with tempfile.TemporaryFile(dir=folder):
            pass
    except FileExistsError as err:  # the folder's name is taken by a file
        return f"{err.filename or folder} is a file, not a folder"
    except OSError as err:
        return f"cannot write in {err.filename or folder}: {err.strerror or err}"
    return None


def _connect(host: str, port: int, timeout: float) -> str | None:
    """``None`` if a TCP connection to ``host:port`` opens within ``timeout`` seconds, name
    look-up included (it runs in a thread the wait does not outlast: a resolver that retries
    is not bounded by the socket's timeout), else why not."""
    result: list[str | None] = []

    def probe() -> None:
        try:
            with socket.create_connection((host, port), timeout=timeout):
                result.append(None)
        except TimeoutError:
            result.append(f"no answer within {timeout:g} s")
        except OSError as err:
            result.append(str(err.strerror or err))

    thread = threading.Thread(target=probe, daemon=True, name=f"reach {host}:{port}")
    thread.start()
    thread.join(timeout)
    return result[0] if result else f"no answer within {timeout:g} s"


def reach(url: str, timeout: float) -> str | None:
    """``None`` if a TCP connection to ``url``'s host and port (or to the proxy the
    environment names for it, ``https_proxy`` / ``no_proxy``) opens within ``timeout``
    seconds, else why not. A local store (``sqlite:///<file>``, ``file:``, a path) needs no
    network: ``None`` if its folder can be made and written (:func:`writable`), else why not.
    Only the connection is tried (no request, no credential sent)."""
    parts = urlsplit(url)
    if not parts.hostname:
        folder = local_store(url)
        return None if folder is None else writable(folder)
    scheme = parts.scheme.split("+")[0].lower()
    try:
        port = parts.port or _PORTS.get(scheme)
    except ValueError as err:  # a port that is not a number
        return str(err)
    if port is None:
        return None
    host = parts.hostname
    proxy = urllib.request.getproxies().get(scheme)
    if proxy and not urllib.request.proxy_bypass(host):
        via = urlsplit(proxy if "://" in proxy else f"http://{proxy}")
        host, port = via.hostname or host, via.port or 8080
    return _connect(host, port, timeout)
