"""The plan of a rerun (``resireg-runs rerun``): the job a run ran, rebuilt from its record,
ready to start in a new folder (:func:`plan`, :class:`Plan`).

The rerun is rebuilt from what the run's folder records, never from a command line read from
a file:

- the job kind from ``provenance.cli`` (``resireg-train``, ``resireg-eval``, ``resireg-map``),
  run through that command's own entry point (:data:`JOBS`) with this interpreter;
- the overrides of ``.hydra/overrides.yaml``, each checked as a search's worker checks a
  recorded one (:func:`resireg_train.search.workers.check_overrides`: no class to
  instantiate, no Hydra setting, no interpolation, no key the job's config lacks; a run's
  ``+model.init_from`` is kept); ``ckpt_path=last`` and the keys only a search sets are left
  out (the rerun trains from the start, as one run); the overrides given on the command line
  replace the recorded ones of the same key;
- the seeds of ``provenance.seeds`` (set again where today's config would compose another);
- torch's thread count (``provenance.machine.torch_threads``: a CPU result changes with it),
  given to the job as ``OMP_NUM_THREADS``;
- the export (``model_path``) or checkpoint (``model.init_from``, a ``ckpt_path`` file) it
  started from, by the same overrides, their digests compared.

A secret never comes from the record: the record masks a URL's password
(``http://user:***@host``), and the rerun drops the mask, so the tracker takes the password
from the user's environment (MLflow's ``MLFLOW_TRACKING_PASSWORD``, ...) or from the same
override given again on the command line; any other masked value is refused, naming the key.

What ran is compared with what would run before the job starts
(:func:`~resireg_train.runs.rerun.drift.drift`, called by :func:`plan`).

Imported by :mod:`~resireg_train.runs.rerun.command` and :mod:`resireg_train.runs.reproduce`
(its jobs composed as a rerun composes them).
"""

from __future__ import annotations

import os
import re
import sys
from collections.abc import Sequence
from dataclasses import dataclass, field
from pathlib import Path
from typing import Any

from resireg.errors import ResiregError
from resireg.secrets import MASK
from resireg.specs.exports import REGISTRY_PREFIX
from resireg.specs.tree import MISSING
from resireg_train.runs.index import Run
from resireg_train.runs.rerun.drift import LEFT_OUT, drift, missing_models

__all__ = [
    "JOBS",
    "Plan",
    "RerunRefused",
    "compose_job",
    "hydra_value",
    "job_command",
    "job_env",
    "plan",
]

#: ``provenance.cli`` -> (the Hydra config name, the module of its console script).
JOBS: dict[str, tuple[str, str]] = {
    "resireg-train": ("train", "resireg_train.cli.train"),
    "resireg-eval": ("eval", "resireg_train.cli.eval"),
    "resireg-map": ("map", "resireg_train.cli.map"),
}


class RerunRefused(ResiregError, ValueError):
    """A run that cannot be rerun as it ran (the message names why, one line per reason)."""


# ------------------------------------------------------------------------------- planning
@dataclass
class Plan:
    """A rerun, ready to start: the run, its job, the overrides, where it goes, the thread
    count, and what differs from when it ran."""

    run: Run
    job: str
    module: str
    overrides: list[str]
    out: Path
    threads: int | None
    drift: list[str] = field(default_factory=list)


def _key(override: str) -> str:
    from hydra.core.override_parser.overrides_parser import OverridesParser

    (parsed,) = OverridesParser.create().parse_overrides([override])
    return str(parsed.key_or_group)


def _unmasked(index: int, override: str, path: Path) -> str:
    """A recorded override with a masked URL password (``user:***@``) as ``user@``: the
    tracker then takes the password from the environment. Any other mask is refused."""
    text = re.sub(r"(://[^:/@\s'\"]*):" + re.escape(MASK) + "@", r"\1@", override)
    if MASK in text:
        raise RerunRefused(
            f"{path}: overrides[{index}]={override!r} holds a masked secret (a record never "
            f"keeps one): give {_key(override)}=... on the command line"
        )
    return text


def _recorded_overrides(run: Run, job: str, given: Sequence[str]) -> list[str]:
    """The run's overrides, checked (module docstring), less those left out or given again."""
    from resireg_train.config.keys import ADDABLE
    from resireg_train.config.moves import current_overrides
    from resireg_train.search.workers import SearchRecordError, check_overrides

    path = run.path / ".hydra" / "overrides.yaml"
    if not path.is_file():
        raise RerunRefused(f"{run.path}: no .hydra/overrides.yaml, so not a run of a resireg-* "
                           "command that can be rebuilt (a run started from Python?)")  # fmt: skip
    recorded = current_overrides(job, run.overrides)  # a renamed key in today's spelling
    if run.problems:  # not a YAML list of strings
        raise RerunRefused(run.problems[0])
    addable = frozenset(k for k in ADDABLE.get(job, ()) if not k.endswith("."))
    replaced = {_key(o) for o in given}
    keys = [_key(o) if _parses(o) else None for o in recorded]
    dropped = frozenset(i for i, key in enumerate(keys) if key in replaced or key in LEFT_OUT
                        or recorded[i].lstrip("+") == "ckpt_path=last")  # fmt: skip
    try:
        check_overrides(path, job, recorded, addable, dropped)
    except SearchRecordError as err:
        raise RerunRefused(f"{err} (give it on the command line to run it all the same)") from None
    return [_unmasked(i, o, path) for i, o in enumerate(recorded) if i not in dropped]


def _parses(override: str) -> bool:
    """Whether Hydra's grammar reads ``override`` (the check names one that it does not)."""
    try:
        _key(override)
    except Exception:
        return False
    return True


def _composed(job: str, overrides: Sequence[str]) -> Any:
    """:func:`compose_job`, a config Hydra refuses to compose (a key the job's config lacks,
    a value of the wrong type) refused in one line naming why."""
    from hydra.errors import HydraException
    from omegaconf.errors import OmegaConfBaseException

    try:
        return compose_job(job, overrides)
    except (HydraException, OmegaConfBaseException) as err:
        first = next((line for line in str(err).splitlines() if line.strip()), type(err).__name__)
        raise RerunRefused(f"resireg-{job}'s config does not compose with the overrides: "
                           f"{first.strip()}") from None  # fmt: skip


def compose_job(job: str, overrides: Sequence[str]) -> Any:
    """``conf/<job>.yaml`` composed with ``overrides`` (Hydra's compose API)."""
    from hydra import compose

    import resireg_train.checks.eval  # noqa: F401  the resireg_encoders resolver
    from resireg_train.config.paths import composing
    from resireg_train.search.space import register_search_resolvers

    register_search_resolvers()
    with composing():
        return compose(job, overrides=list(overrides))


def plan(run: Run, out: Path, given: Sequence[str] = (), allow_drift: bool = False) -> Plan:
    """The rerun of ``run`` into ``out`` with the overrides ``given`` on the command line:
    its job, overrides, thread count and drift (module docstring). Raises
    :class:`RerunRefused` naming every reason it cannot start (the drift among them unless
    ``allow_drift``)."""
    from omegaconf import OmegaConf

    cli = run.cli
    if cli not in JOBS:
        raise RerunRefused(f"{run.path}: provenance.cli={cli!r} is not a command a rerun starts "
                           f"(one of: {', '.join(JOBS)})")  # fmt: skip
    if run.may_be_running:
        raise RerunRefused(f"{run.path}: still running ({run.status}); rerun it once it has "
                           "ended")  # fmt: skip
    job, module = JOBS[cli]
    for override in given:
        if not _parses(override):
            raise RerunRefused(f"override {override!r}: not a key=value Hydra reads")
    overrides = [*_recorded_overrides(run, job, given), *given]
    given_keys = {_key(o) for o in given}
    cfg = _composed(job, overrides)
    # the seeds it ran with, where today's config would compose others
    seeds = []
    for key, value in (run.provenance.get("seeds") or {}).items():
        if key not in given_keys and OmegaConf.select(cfg, key, default=MISSING) != value:
            seeds.append(f"{key}={'null' if value is None else value}")
    if seeds:
        overrides += seeds
        cfg = _composed(job, overrides)
    if gone := missing_models(run, cfg, given_keys):  # one line each, before any drift
        raise RerunRefused(f"{run.path}: " + "\n".join(gone))
    registered = OmegaConf.select(cfg, "model_path", default=None)
    if isinstance(registered, str) and registered.startswith(REGISTRY_PREFIX):  # no long retries
        from resireg.models.vlm.registry import check_registry, registry_timeout

        check_registry(timeout=registry_timeout(cfg), what=f"model_path={registered!r}")
    threads = (run.provenance.get("machine") or {}).get("torch_threads")
    result = Plan(run, job, module, overrides, out, threads if isinstance(threads, int) else None)
    result.drift = drift(run, cfg, out, given_keys)
    if result.drift and not allow_drift:
        raise RerunRefused(
            f"{run.path} no longer matches what ran ({len(result.drift)} difference(s)):\n  "
            + "\n  ".join(result.drift)
            + "\nRestore them, or rerun anyway with --allow-drift (the differences are then "
            "recorded in the new run's results.json, rerun.drift)"
        )
    return result


# ---------------------------------------------------------------------------------- drift


# -------------------------------------------------------------------------------- running
def hydra_value(text: str) -> str:
    """A path as a Hydra override value (quoted where it holds what Hydra's grammar reads)."""
    if re.fullmatch(r"[\w/.\-:~+@%]+", text):
        return text
    return '"' + text.replace("\\", "\\\\").replace('"', '\\"') + '"'


def job_command(p: Plan) -> list[str]:
    """The job's command: this interpreter running the entry point of the run's kind with the
    rebuilt overrides, in the new folder, as one run."""
    return [sys.executable, "-m", p.module, *p.overrides,
            f"hydra.run.dir={hydra_value(str(p.out))}", "hydra.mode=RUN"]  # fmt: skip


def job_env(p: Plan) -> dict[str, str]:
    """The user's environment (its secrets stay there), with the run's thread count."""
    env = dict(os.environ)
    if p.threads is not None:
        env["OMP_NUM_THREADS"] = env["MKL_NUM_THREADS"] = str(p.threads)
    return env


# -------------------------------------------------------------------------------- verdict


# ---------------------------------------------------------------------------------- main
