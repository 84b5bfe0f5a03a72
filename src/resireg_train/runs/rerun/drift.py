"""What changed since a run ran, before its rerun starts (:func:`drift`): the code (commit,
each tracked change's digest, the untracked files' names, sizes and digests), the data identity
of every dataset, the digests of every input model, and the composed config against the run's
``.hydra/config.yaml``. Any difference refuses the rerun, naming it, unless ``--allow-drift``:
then the differences are recorded in the new run's record (``rerun.drift``).
:func:`missing_models`: the input models the rerun cannot find at all.

Imported by :mod:`~resireg_train.runs.rerun.plan`.
"""

from __future__ import annotations

import re
import subprocess
from collections.abc import Mapping
from pathlib import Path
from typing import Any

import yaml

from resireg.secrets import mask_text
from resireg.specs.exports import REGISTRY_PREFIX
from resireg.specs.tree import MISSING, differences
from resireg_train.runs.index import Run

__all__ = [
    "LEFT_OUT",
    "UNCOMPARED",
    "code_drift",
    "config_drift",
    "drift",
    "missing_models",
    "short",
]

#: Recorded overrides a rerun leaves out: a resume of the run's own folder, and the keys only
#: a search sets for its jobs (the rerun is one run, not a trial of the study).
LEFT_OUT = ("hparams_search.workers", "hparams_search.storage", "hparams_search.trial")


#: Keys whose difference changes nothing a run computes (its trackers, what its record keeps).
UNCOMPARED = ("tracker", "provenance")


def short(value: Any) -> str:
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
            lines.append("code: " + texts[1].format(path, short(b[path][1])))
        elif a[path] != b[path]:
            lines.append("code: " + texts[2].format(path, short(a[path][1]), short(b[path][1])))
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
    return [f"{section}.{key}: {short(a)} -> {short(b)}" for key, a, b in differences(then, now)]


def _given(key: str, given: set[str]) -> bool:
    """Whether the command line sets ``key``, a key under it or one above it."""
    return any(key == g or key.startswith(f"{g}.") or g.startswith(f"{key}.") for g in given)


#: ``provenance.models`` entries -> the config key that names each.
_MODEL_KEYS = {"export": "model_path", "init_from": "model.init_from", "ckpt_path": "ckpt_path"}


def config_drift(run: Run, cfg: Any, given: set[str]) -> list[str]:
    """The keys whose composed value differs from the run's ``.hydra/config.yaml`` (but those
    the command line sets, and its trackers and record settings), or ``[]`` without one."""
    from omegaconf import OmegaConf

    from resireg_train.config.moves import check_stored_targets, current_spelling, current_targets
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
    recorded = current_spelling(current_targets(recorded))  # (a gone class: refused, named)
    check_stored_targets(recorded, str(path), (run.provenance.get("code") or {}).get("version"))
    rows = differences(masked_tree(recorded), masked_tree(now), UNCOMPARED)
    return [f"config.{key}: {short(a)} -> {short(b)}" for key, a, b in rows
            if not _given(key, given) and not key.startswith(LEFT_OUT)]  # fmt: skip


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
