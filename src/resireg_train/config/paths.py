"""Where this process's runs are configured and named: the project's ``conf/`` folder and the
run id. Imported by the CLIs' task wrapper (``cli/job.py``, which re-exports both), the trackers
and the playground, so that none of them reaches up into ``cli/``."""

from __future__ import annotations

import contextlib
import secrets
from collections.abc import Iterator

from resireg.specs.table import conf_dir

__all__ = ["CONFIG_DIR", "RUN_ID", "composing"]

#: The project's ``conf/`` folder (``$RESIREG_CONFIG_DIR`` overrides it; the spec tables scan
#: the same folder, :func:`resireg.specs.table.conf_dir`).
CONFIG_DIR = conf_dir()

#: A short random token drawn once per process: two runs started in the same second (a job
#: array, a shell loop) still get two run folders.
RUN_ID = secrets.token_hex(3)


@contextlib.contextmanager
def composing() -> Iterator[None]:
    """Hydra's compose API ready for the block: inside a Hydra app, its own config search path;
    elsewhere (a search worker's check, ``resireg-runs rerun``), :data:`CONFIG_DIR`."""
    from hydra import initialize_config_dir
    from hydra.core.global_hydra import GlobalHydra

    if GlobalHydra.instance().is_initialized():
        yield
    else:
        with initialize_config_dir(str(CONFIG_DIR), version_base="1.3"):
            yield
