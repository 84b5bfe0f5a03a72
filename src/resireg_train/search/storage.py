"""Where a search's study lives: Optuna's journal file in the sweep folder (the default), or a
database named by ``hparams_search.storage``; and how a database URL's password reaches the
processes that connect without ever being written down.

The password of a storage URL (``postgresql+psycopg://user:pass@host/db``) is masked
(``user:***@host``, :func:`resireg.secrets.mask_url`) in everything a search
writes or prints: ``search.json``, each trial's config and ``results.json``, the console. The
processes that connect get the whole URL from the environment variable :data:`STORAGE_ENV`:
the search sets it for its own jobs and the workers it starts; ``resireg-search worker`` takes
it from the user's environment or its ``--storage`` option. A URL without a password (libpq
reads ``PGPASSWORD`` or ``~/.pgpass`` itself) needs neither.
"""

from __future__ import annotations

import os
from pathlib import Path
from typing import Any

from resireg.secrets import MASK, mask_text, mask_url

__all__ = [
    "STORAGE_ENV",
    "STUDY_FILE",
    "load_study",
    "open_storage",
    "quiet_optuna",
    "recorded_storage",
    "storage_override",
    "storage_url",
]

#: The study's journal file in the sweep folder (default storage).
STUDY_FILE = "optuna.journal"
#: The whole storage URL, password included, for processes whose config holds it masked.
STORAGE_ENV = "RESIREG_SEARCH_STORAGE"


def quiet_optuna() -> Any:
    """Optuna, its messages through the logging configuration of the process (Hydra's: the
    job's log file and console, each line once, no colour codes) instead of its own handler."""
    import optuna

    optuna.logging.disable_default_handler()
    optuna.logging.enable_propagation()
    optuna.logging.set_verbosity(optuna.logging.WARNING)
    return optuna


def _is_journal(storage: str | None) -> bool:
    return storage in (None, "", "journal")


def recorded_storage(storage: str | None) -> str | None:
    """``hparams_search.storage`` as a search may write or print it: the password masked."""
    return None if _is_journal(storage) else mask_url(str(storage))


def storage_override(storage: str) -> str:
    """``hparams_search.storage=<the URL, masked>`` as a Hydra override (quoted: a URL's query
    holds ``=`` and ``&``), for the jobs and workers of a search."""
    masked = mask_url(str(storage)).replace("'", "\\'")
    return f"hparams_search.storage='{masked}'"


def storage_url(storage: str | None) -> str | None:
    """The URL to connect with for ``hparams_search.storage``: the value itself when it holds
    its password or needs none; for a masked one (``user:***@host``, as a trial's config or
    ``search.json`` holds it) the URL in :data:`STORAGE_ENV`, which must be the same URL
    once masked. ``None`` for the journal. A masked URL with no such variable is a
    ConfigError saying how to give the password."""
    if _is_journal(storage):
        return None
    storage = str(storage)
    if mask_url(storage) != storage or MASK not in storage:
        return storage  # typed with its password, or without one (PGPASSWORD, ~/.pgpass)
    given = os.environ.get(STORAGE_ENV)
    if given and mask_url(given) == storage:
        return given
    from resireg.errors import ConfigError

    found = f" (it holds another URL: {mask_url(given)!r})" if given else ""
    raise ConfigError(
        f"hparams_search.storage={storage!r}: its password is never recorded; give the whole URL "
        f"in the environment variable {STORAGE_ENV}{found} (resireg-search worker: or --storage)"
    )


def open_storage(storage: str | None, sweep_dir: str | Path) -> Any:
    """The study's storage: the journal file in ``sweep_dir`` (``storage`` unset or
    ``journal``; :func:`resireg_train.search.journal.open_journal`, which recovers a torn last
    line and refuses a damaged one), or Optuna's RDBStorage for a database URL
    (:func:`storage_url`). A database that cannot be reached is a ConfigError naming the key,
    its password masked."""
    optuna = quiet_optuna()
    url = storage_url(storage)
    if url is None:
        from resireg_train.search.journal import open_journal

        folder = Path(str(sweep_dir))
        folder.mkdir(parents=True, exist_ok=True)
        return open_journal(folder / STUDY_FILE)
    from resireg.errors import ConfigError

    try:
        return _rdb_storage(optuna, url)
    except Exception as err:  # sqlalchemy's errors: a wrong URL, a server that is down
        first = str(err).splitlines()[0] if str(err) else ""
        raise ConfigError(
            f"hparams_search.storage={mask_url(url)!r} cannot be opened: "
            f"{type(err).__name__}: {mask_text(first)}"
        ) from None


def _rdb_storage(optuna: Any, url: str, attempts: int = 5) -> Any:
    """Optuna's RDBStorage of ``url``. Opening it creates Optuna's tables in a new database, and
    two processes doing so at once race (PostgreSQL: a duplicate key in its catalogue, or "already
    exists"; optuna/optuna#1092, whose answer is to create them first): the one that loses opens
    the storage again, finding the tables the other made (``create_all`` skips a table that
    exists). By hand: neither Optuna nor SQLAlchemy retries a schema creation."""
    import time

    from sqlalchemy.exc import IntegrityError, ProgrammingError

    for attempt in range(1, attempts):
        try:
            return optuna.storages.RDBStorage(url)
        except (IntegrityError, ProgrammingError) as err:
            if "duplicate key" not in str(err) and "already exists" not in str(err):
                raise
            time.sleep(0.2 * attempt)
    return optuna.storages.RDBStorage(url)  # the last try: its error is the caller's


def load_study(sweep_dir: str | Path, storage: str | None = None, study_name: str | None = None):
    """The sweep's ``optuna.Study`` (its only study unless ``study_name``), or ``None``."""
    if _is_journal(storage) and not (Path(sweep_dir) / STUDY_FILE).is_file():
        return None
    optuna = quiet_optuna()
    store = open_storage(storage, sweep_dir)
    names = [s.study_name for s in optuna.get_all_study_summaries(store)]
    if study_name is None:
        if len(names) != 1:
            return None
        study_name = names[0]
    if study_name not in names:
        return None
    return optuna.load_study(study_name=study_name, storage=store)
