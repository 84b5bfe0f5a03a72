"""Where this process's runs are configured and named: the project's ``conf/`` folder and the
run id. Imported by the CLIs' task wrapper (``cli/task.py``, which re-exports both), the trackers
and the playground, so that none of them reaches up into ``cli/``."""

from __future__ import annotations

import os
import secrets
from pathlib import Path

__all__ = ["CONFIG_DIR", "RUN_ID"]


def _config_dir() -> Path:
    env = os.environ.get("RESIREG_CONFIG_DIR")
    return Path(env) if env else Path(__file__).resolve().parents[2] / "conf"


#: The project's ``conf/`` folder (``$RESIREG_CONFIG_DIR`` overrides it).
CONFIG_DIR = _config_dir()

#: A short random token drawn once per process: two runs started in the same second (a job
#: array, a shell loop) still get two run folders.
RUN_ID = secrets.token_hex(3)
