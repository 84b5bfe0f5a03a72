"""``resireg-runs rerun RUN [--out DIR] [--allow-drift] [--rtol X] [overrides...]``: a run
again, rebuilt from its record, in a new folder, and one verdict on the two records.

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

Before the job starts, what ran is compared with what would run (:func:`drift`): the code
(commit, each tracked change's digest, the untracked files' names, sizes and digests), the data
identity of every dataset, the digests of every input model, and the composed config against
the run's ``.hydra/config.yaml``. Any difference refuses the rerun, naming it, unless
``--allow-drift``: then the differences are recorded in the new run's record (``rerun.drift``).

When the job ends, the two records are compared (:func:`compare`) and one verdict printed:
``identical`` (every score bitwise equal and the outputs' digests equal), ``within tolerance``
(every score within ``--rtol`` of the run's, ``provenance.rerun_rtol`` by default) or
``differs`` (the scores that moved, by how much, and the provenance fields that differ). The
scores are the record's ``final`` and ``best`` values, the per-class IoU and a map's counts;
timings (``seconds``, ``provenance.time``) and system metrics are not. The outputs are the
files a run makes: an export's weights and configs, a map's tensors and PLY.
"""

from __future__ import annotations

import datetime as _dt
import math
import os
import re
import struct
import subprocess
import sys
from collections.abc import Mapping, Sequence
from dataclasses import dataclass, field
from pathlib import Path
from typing import Any, TextIO

import yaml

from resireg.errors import ResiregError
from resireg.secrets import MASK, mask_text
from resireg.specs.exports import REGISTRY_PREFIX
from resireg.specs.tree import MISSING, differences, flatten
from resireg_train.record.run_record import RunRecord, target_problem
from resireg_train.runs.index import Run, diff_runs, find_run

__all__ = [
    "JOBS",
    "RerunRefused",
    "Verdict",
    "compare",
    "compose_job",
    "drift",
    "hydra_value",
    "job_command",
    "main",
    "missing_models",
    "outputs",
    "plan",
    "rerun",
    "scores",
]

#: ``provenance.cli`` -> (the Hydra config name, the module of its console script).
JOBS: dict[str, tuple[str, str]] = {
    "resireg-train": ("train", "resireg_train.cli.train"),
    "resireg-eval": ("eval", "resireg_train.cli.eval"),
    "resireg-map": ("map", "resireg_train.cli.map"),
}
#: Recorded overrides a rerun leaves out: a resume of the run's own folder, and the keys only
#: a search sets for its jobs (the rerun is one run, not a trial of the study).
_LEFT_OUT = ("hparams_search.workers", "hparams_search.storage", "hparams_search.trial")
#: Keys whose difference changes nothing a run computes (its trackers, what its record keeps).
_UNCOMPARED = ("logger", "provenance")
#: What ``final`` holds that is not a score: timings and system metrics.
_NOT_SCORES = ("time/", "system/", "perf/")


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
    from resireg_train.search.workers import SearchRecordError, check_overrides

    path = run.path / ".hydra" / "overrides.yaml"
    if not path.is_file():
        raise RerunRefused(f"{run.path}: no .hydra/overrides.yaml, so not a run of a resireg-* "
                           "command that can be rebuilt (a run started from Python?)")  # fmt: skip
    recorded = run.overrides
    if run.problems:  # not a YAML list of strings
        raise RerunRefused(run.problems[0])
    addable = frozenset(k for k in ADDABLE.get(job, ()) if not k.endswith("."))
    replaced = {_key(o) for o in given}
    keys = [_key(o) if _parses(o) else None for o in recorded]
    dropped = frozenset(i for i, key in enumerate(keys) if key in replaced or key in _LEFT_OUT
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

    import resireg_train.config.eval  # noqa: F401  the resireg_encoders resolver
    from resireg_train.config.paths import composing
    from resireg_train.search.space import register_search_resolvers

    register_search_resolvers()
    with composing():
        return compose(job, overrides=list(overrides))


def _plain(cfg: Any, out: Path) -> dict[str, Any]:
    """The composed config as plain values, resolved where it can be, its run folder ``out``."""
    from omegaconf import OmegaConf, open_dict

    cfg = cfg.copy()
    with open_dict(cfg):
        OmegaConf.update(cfg, "paths.output_dir", str(out), force_add=True)
    try:
        return OmegaConf.to_container(cfg, resolve=True)
    except Exception:  # a value only Hydra's runtime resolves
        return OmegaConf.to_container(cfg, resolve=False)


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
def _short(value: Any) -> str:
    """A value as shown: a SHA-256 cut to 12 digits, ``<absent>`` for a missing one."""
    if value is MISSING:
        return "<absent>"
    if isinstance(value, str) and re.fullmatch(r"[0-9a-f]{64}", value):
        return value[:12]
    return mask_text(repr(value) if not isinstance(value, str) else value)


def _files(entries: Any) -> dict[str, tuple[Any, ...]]:
    """``{path: (size, sha256, link, error)}`` of a provenance file list."""
    return {str(e.get("path")): (e.get("size"), e.get("sha256"), e.get("link"), e.get("error"))
            for e in entries or [] if isinstance(e, Mapping)}  # fmt: skip


#: How a file of the checkout differs: (in the run only, now only, both but changed).
_TRACKED = (
    "{} is back at the commit (the run had it changed)",
    "{} changed since the run (uncommitted, sha256 now {})",
    "{} changed since the run (sha256 {} -> {})",
)
_UNTRACKED = ("untracked {} is gone (the run had it)", "untracked {} is new (sha256 {})",
              "untracked {} changed since the run (sha256 {} -> {})")  # fmt: skip


def _file_lines(texts: tuple[str, str, str], then: Any, now: Any) -> list[str]:
    a, b = _files(then), _files(now)
    lines = []
    for path in sorted(set(a) | set(b)):
        if path not in b:
            lines.append("code: " + texts[0].format(path))
        elif path not in a:
            lines.append("code: " + texts[1].format(path, _short(b[path][1])))
        elif a[path] != b[path]:
            lines.append("code: " + texts[2].format(path, _short(a[path][1]), _short(b[path][1])))
    return lines


def _commit_files(root: str | None, a: str, b: str) -> str:
    """The files two commits differ in (``git diff --name-only``), or why not known."""
    if not root:
        return "its files cannot be listed"
    try:
        proc = subprocess.run(["git", "-C", root, "diff", "--name-only", a, b],
                              capture_output=True, text=True, timeout=60, check=False)  # fmt: skip
    except (OSError, subprocess.SubprocessError):
        return "its files cannot be listed (no git)"
    if proc.returncode != 0:
        return f"the run's commit is not in {root}"
    names = proc.stdout.split()
    shown = ", ".join(names[:10]) + (f" and {len(names) - 10} more" if len(names) > 10 else "")
    return f"changed files: {shown or 'none'}"


def code_drift(then: Mapping[str, Any], now: Mapping[str, Any]) -> list[str]:
    """What differs between the code a run recorded (``provenance.code``) and the code now."""
    lines = []
    if then.get("version") != now.get("version"):
        lines.append(f"code: version {then.get('version')} -> {now.get('version')}")
    a, b = then.get("git"), now.get("git")
    if not a and not b:
        return lines
    if not a or not b:
        where = "a git checkout" if a else "no git checkout"
        lines.append(f"code: the run ran from {where}, this rerun would not")
        return lines
    if a.get("error") or b.get("error"):
        lines.append(f"code: cannot be compared ({a.get('error') or b.get('error')})")
        return lines
    if a.get("commit") != b.get("commit"):
        files = _commit_files(b.get("root"), str(a.get("commit")), str(b.get("commit")))
        lines.append(f"code: commit {str(a.get('commit'))[:10]} -> {str(b.get('commit'))[:10]} "
                     f"({files})")  # fmt: skip
    if "changes" not in a and a.get("dirty"):
        lines.append("code: the run's record holds no digest of its uncommitted changes (a "
                     "release before rerun): they cannot be compared")  # fmt: skip
    else:
        lines += _file_lines(_TRACKED, a.get("changes"), b.get("changes"))
    lines += _file_lines(_UNTRACKED, a.get("untracked"), b.get("untracked"))
    if a.get("untracked_files") != b.get("untracked_files"):
        lines.append(f"code: {a.get('untracked_files')} -> {b.get('untracked_files')} untracked "
                     "files (more than were listed)")  # fmt: skip
    return lines


def _tree_lines(section: str, then: Any, now: Any) -> list[str]:
    then = then if isinstance(then, Mapping) else {}
    now = now if isinstance(now, Mapping) else {}
    return [f"{section}.{key}: {_short(a)} -> {_short(b)}" for key, a, b in differences(then, now)]


def _given(key: str, given: set[str]) -> bool:
    """Whether the command line sets ``key``, a key under it or one above it."""
    return any(key == g or key.startswith(f"{g}.") or g.startswith(f"{key}.") for g in given)


#: ``provenance.models`` entries -> the config key that names each.
_MODEL_KEYS = {"export": "model_path", "init_from": "model.init_from", "ckpt_path": "ckpt_path"}


def config_drift(run: Run, cfg: Any, given: set[str]) -> list[str]:
    """The keys whose composed value differs from the run's ``.hydra/config.yaml`` (but those
    the command line sets, and its trackers and record settings), or ``[]`` without one."""
    from omegaconf import OmegaConf

    from resireg_train.config.moves import current_targets
    from resireg_train.record.masking import masked_tree

    path = run.path / ".hydra" / "config.yaml"
    if not path.is_file():
        return []
    try:
        recorded = yaml.safe_load(path.read_text())
    except (OSError, yaml.YAMLError) as err:
        return [f"config: {path} cannot be read ({' '.join(str(err).split())})"]
    if not isinstance(recorded, dict):
        return [f"config: {path} is not a YAML mapping"]
    now = OmegaConf.to_container(cfg, resolve=False)
    now.pop("hydra", None)
    rows = differences(masked_tree(current_targets(recorded)), masked_tree(now), _UNCOMPARED)
    return [f"config.{key}: {_short(a)} -> {_short(b)}" for key, a, b in rows
            if not _given(key, given) and not key.startswith(_LEFT_OUT)]  # fmt: skip


def drift(run: Run, cfg: Any, out: Path, given: set[str] = frozenset()) -> list[str]:
    """What differs between what ``run`` ran with and what its rerun (config ``cfg``, folder
    ``out``; ``given``: the keys the command line sets) would run with, one line each: the
    code, the data identity of every dataset, the inputs' digests, the config."""
    from resireg_train.record.provenance.code import code_provenance
    from resireg_train.record.provenance.inputs import input_provenance
    from resireg_train.record.settings import provenance_settings

    then = run.provenance
    plain = _plain(cfg, out)
    now = input_provenance(plain)
    lines = code_drift(then.get("code") or {},
                       code_provenance(None, settings=provenance_settings(cfg)))  # fmt: skip
    data_then, data_now = then.get("data") or {}, now["data"]
    for key in sorted(set(data_then) | set(data_now)):
        if _given(key, given):
            continue
        lines += _tree_lines(f"data.{key}", data_then.get(key), data_now.get(key))
    models_then, models_now = then.get("models") or {}, now["models"]
    gone = _gone(models_then, models_now)
    for key in sorted(set(models_then) | set(models_now)):
        if key == "encoder" or key in gone or _given(_MODEL_KEYS.get(key, key), given):
            continue  # the encoder's entry: compared with the config; a gone one: one line
        lines += _tree_lines(f"models.{key}", models_then.get(key), models_now.get(key))
    return lines + config_drift(run, cfg, given)


def _gone(then: Any, now: Any) -> dict[str, str]:
    """``{provenance.models key: its path}`` of each input model the run read (its files'
    digests recorded) that is no longer there (the export folder or checkpoint file gone)."""
    then = then if isinstance(then, Mapping) else {}
    now = now if isinstance(now, Mapping) else {}
    found = {}
    for key, entry in then.items():
        if (key == "encoder" or not isinstance(entry, Mapping) or not entry.get("path")
                or entry.get("uri")):  # fmt: skip
            continue  # (a registry model: its local copy is downloaded again)
        read = entry.get("files") if key == "export" else entry.get("sha256")
        current = now.get(key) if isinstance(now.get(key), Mapping) else {}
        if read and not current.get("uri") and not Path(str(current.get("path") or
                                                              entry["path"])).exists():  # fmt: skip
            found[key] = str(current.get("path") or entry["path"])
    return found


def missing_models(run: Run, cfg: Any, given: set[str] = frozenset()) -> list[str]:
    """One line per input model of ``run`` (``provenance.models``: its export, ``init_from``
    or ``ckpt_path``) that is gone from where the rerun (config ``cfg``; ``given``: the keys
    the command line sets) would read it, naming the config key and the path."""
    from omegaconf import OmegaConf

    now: dict[str, Any] = {}
    for key, setting in _MODEL_KEYS.items():
        try:
            value = OmegaConf.select(cfg, setting, default=None)
        except Exception:  # a value only Hydra's runtime resolves
            continue
        if isinstance(value, str) and value and not value.startswith(REGISTRY_PREFIX):
            now[key] = {"path": str(Path(value).expanduser().resolve())}
    lines = []
    for key, path in _gone(run.provenance.get("models"), now).items():
        setting = _MODEL_KEYS.get(key, key)
        what = "export folder" if key == "export" else "file or folder"
        if not _given(setting, given):
            lines.append(f"{setting}={path}: no such {what} (the run read its model there); "
                         f"restore it, or give {setting}=... on the command line")  # fmt: skip
    return lines


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
def _number(value: Any) -> bool:
    return isinstance(value, (int, float)) and not isinstance(value, bool)


def scores(record: Mapping[str, Any]) -> dict[str, float]:
    """A record's scores (module docstring): ``final/<k>``, ``best/<k>`` and its epoch,
    ``per_class_iou/<variant>/<class>`` and a map's counts; NaN where the record holds one."""
    from resireg_train.record.trackers.base import map_counts

    found: dict[str, float] = {}
    for key, value in (record.get("final") or {}).items():
        if _number(value) and not str(key).startswith(_NOT_SCORES):
            found[f"final/{key}"] = value
    for key, best in (record.get("best") or {}).items():
        if isinstance(best, Mapping) and _number(best.get("value")):
            found[f"best/{key}"] = best["value"]
            if _number(best.get("epoch")):
                found[f"best/{key}/epoch"] = best["epoch"]
    for key, value in flatten(record.get("per_class_iou") or {}).items():
        if _number(value):
            found[f"per_class_iou/{key.replace('.', '/')}"] = value
    for key, value in map_counts(record).items():
        found[key] = value
    return found


def outputs(record: Mapping[str, Any], folder: Path) -> dict[str, str]:
    """The SHA-256 of the files a run made: its export's weights and configs
    (``export/<file>``), a map's tensors (``map/tensors[<n>]``: their names are drawn per
    save, their content is the map) and ``map.ply``."""
    from resireg.integrity import sha256_file
    from resireg_train.record.provenance.inputs import export_identity

    found = {}
    export = record.get("export")
    if isinstance(export, str) and Path(export).is_dir():
        for name, digest in (export_identity(export)["files"] or {}).items():
            found[f"export/{name}"] = digest
    smap = record.get("map") if isinstance(record.get("map"), Mapping) else {}
    if smap:
        tensors = sorted(sha256_file(p) for p in (folder / "map").glob("*.safetensors"))
        found.update({f"map/tensors[{i}]": d for i, d in enumerate(tensors)})
        ply = folder / "map.ply"
        if ply.is_file():
            found["map.ply"] = sha256_file(ply)
    return found


def _bits(value: float) -> bytes:
    return struct.pack("<d", float(value)) if not math.isnan(value) else b"nan"


@dataclass
class Verdict:
    """The comparison of a run and its rerun (:func:`compare`)."""

    kind: str  # "identical", "within tolerance", "differs"
    rtol: float
    compared: int
    moved: list[tuple[str, Any, Any, str]] = field(default_factory=list)  # beyond rtol
    nudged: list[tuple[str, Any, Any, str]] = field(default_factory=list)  # within rtol
    outputs: list[str] = field(default_factory=list)  # output files whose digest differs
    provenance: list[tuple[str, Any, Any]] = field(default_factory=list)
    config: list[tuple[str, Any, Any]] = field(default_factory=list)
    status: tuple[str, str] = ("completed", "completed")

    def record(self) -> dict[str, Any]:
        """What the new run's record keeps of it (``rerun.verdict``, ``rerun.moved``)."""
        return {"verdict": self.kind, "rtol": self.rtol, "scores": self.compared,
                "moved": {k: {"run": a, "rerun": b, "change": c} for k, a, b, c in self.moved},
                "outputs_differ": self.outputs}  # fmt: skip

    def lines(self) -> list[str]:
        """The verdict as printed: one line, then what supports it."""
        if self.kind == "identical":
            head = (f"verdict: identical ({self.compared} scores bitwise equal"
                    f"{', outputs equal' if not self.outputs else ''})")  # fmt: skip
        elif self.kind == "within tolerance":
            head = (f"verdict: within tolerance ({len(self.nudged)} of {self.compared} scores "
                    f"moved, none by more than rtol={self.rtol:g})")  # fmt: skip
        else:
            reason = (f"status {self.status[0]} -> {self.status[1]}" if
                      self.status[0] != self.status[1] else
                      f"{len(self.moved)} of {self.compared} scores moved beyond "
                      f"rtol={self.rtol:g}")  # fmt: skip
            head = f"verdict: differs ({reason})"
        lines = [head]
        if self.moved:
            lines.append("scores that moved:")
            lines += [f"  {k}: {_shown(a)} -> {_shown(b)} ({c})" for k, a, b, c in self.moved]
        if self.nudged and self.kind != "identical":
            lines.append(f"scores within rtol={self.rtol:g}:")
            lines += [f"  {k}: {_shown(a)} -> {_shown(b)} ({c})" for k, a, b, c in self.nudged]
        if self.outputs:
            lines.append("outputs whose SHA-256 differs: " + ", ".join(self.outputs))
        if self.provenance and self.kind != "identical":
            lines.append("provenance that differs:")
            lines += [f"  {k}: {_shown(a)} -> {_shown(b)}" for k, a, b in self.provenance]
        if self.config:
            lines.append("config that differs:")
            lines += [f"  {k}: {_shown(a)} -> {_shown(b)}" for k, a, b in self.config]
        return lines


def _shown(value: Any, width: int = 100) -> str:
    """A value as a verdict shows it: a float to 8 digits, a long one cut at ``width``."""
    if value is None or value is MISSING:
        return "<absent>"
    if isinstance(value, float):
        return f"{value:.8g}"
    text = _short(value)
    return text if len(text) <= width else f"{text[: width - 1]}…"


def _change(a: Any, b: Any) -> str:
    if not (_number(a) and _number(b)):
        return "absent on one side"
    if math.isnan(a) or math.isnan(b):
        return "NaN on one side"
    delta = b - a
    relative = f", {delta / abs(a):+.3%}" if a else ""
    return f"{delta:+.6g}{relative}"


def compare(a: Run, b: Run, rtol: float) -> Verdict:
    """The verdict on run ``a`` and its rerun ``b`` (module docstring): every score of either
    compared bitwise, then within ``rtol`` (relative to the larger magnitude), the outputs'
    digests, and the provenance and config that differ (:func:`resireg_train.runs.index.
    diff_runs`: what is the same for every rerun of a run is left out)."""
    sa, sb = scores(a.results), scores(b.results)
    keys = sorted(set(sa) | set(sb))
    moved, nudged = [], []
    for key in keys:
        x, y = sa.get(key), sb.get(key)
        if x is not None and y is not None and _bits(x) == _bits(y):
            continue
        row = (key, x, y, _change(x, y))
        close = (x is not None and y is not None and not math.isnan(x) and not math.isnan(y)
                 and abs(x - y) <= rtol * max(abs(x), abs(y)))  # fmt: skip
        (nudged if close else moved).append(row)
    oa, ob = outputs(a.results, a.path), outputs(b.results, b.path)
    differ = sorted(k for k in set(oa) | set(ob) if oa.get(k) != ob.get(k))
    status = (str(a.results.get("status")), str(b.results.get("status")))
    if moved or status[0] != status[1]:
        kind = "differs"
    elif nudged or differ:
        kind = "within tolerance"
    else:
        kind = "identical"
    found = diff_runs(a, b)
    config = [r for r in found["config"] if r[0].split(".")[0] not in _UNCOMPARED]
    return Verdict(kind, rtol, len(keys), moved, nudged, differ, found["provenance"], config,
                   status)  # fmt: skip


# ---------------------------------------------------------------------------------- main
def default_out(run: Run) -> Path:
    """``outputs/rerun/<run id>_<date>_<time>`` under the working folder."""
    stamp = _dt.datetime.now().strftime("%Y-%m-%d_%H-%M-%S")
    return Path("outputs") / "rerun" / f"{run.run_id}_{stamp}"


def rerun(
    spec: str,
    roots: Sequence[str],
    out: str | None = None,
    given: Sequence[str] = (),
    allow_drift: bool = False,
    rtol: float | None = None,
    stream: TextIO = sys.stdout,
) -> Verdict | None:
    """Rerun the run ``spec`` (a folder or run id under ``roots``) into ``out`` and print the
    verdict on ``stream`` (module docstring). Returns the verdict, ``None`` when the rerun's
    job failed (its record and log say why). Raises :class:`RerunRefused` (a ``ValueError``)
    before anything is written when the run cannot be rerun as it ran."""
    from resireg_train.record.settings import provenance_settings
    from resireg_train.runs.index import read_run

    run = find_run(spec, roots)
    folder = Path(out) if out else default_out(run)
    if problem := target_problem(folder, folder=True):
        raise RerunRefused(f"--out {folder}: {problem}; give the rerun a new folder")
    tolerance = float(provenance_settings()["rerun_rtol"] if rtol is None else rtol)
    if not tolerance >= 0:
        raise RerunRefused(f"--rtol {rtol}: expected a number >= 0")
    p = plan(run, folder.resolve(), given, allow_drift)
    if p.drift:
        stream.write("rerun despite (--allow-drift):\n" + "".join(f"  {d}\n" for d in p.drift))
    stream.write(f"rerun of {run.run_id} ({run.path}) into {p.out}"
                 f"{f' with {p.threads} torch thread(s)' if p.threads else ''}\n")  # fmt: skip
    stream.flush()
    code = subprocess.run(job_command(p), env=job_env(p), check=False).returncode
    record = RunRecord(p.out)
    if not record.exists(p.out):
        stream.write(f"the rerun did not start (exit status {code}); see above\n")
        return None
    block: dict[str, Any] = {"of": {"run_id": run.run_id, "path": str(run.path)},
                             "drift": p.drift, "allowed_drift": bool(p.drift)}  # fmt: skip
    new = read_run(p.out)
    if code != 0 or new.results.get("status") != "completed":
        record.update(rerun=block)
        error = new.results.get("error") or f"exit status {code}"
        stream.write(f"the rerun failed: {mask_text(str(error))} (its record: {p.out})\n")
        return None
    verdict = compare(run, new, tolerance)
    record.update(rerun={**block, **verdict.record()})
    stream.write("\n".join(verdict.lines()) + "\n")
    return verdict


def main(args: Any) -> int:
    """``resireg-runs rerun``'s parsed arguments run (:func:`rerun`); the exit status: 0 for
    identical or within tolerance, 1 when the rerun differs or failed."""
    verdict = rerun(args.run, args.root, args.out, args.overrides, args.allow_drift, args.rtol)
    return 0 if verdict is not None and verdict.kind != "differs" else 1
