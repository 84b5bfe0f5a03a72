"""Class paths and config keys that changed between releases, so that a run folder written by an
older version still resumes and reruns, and a command typed in a key's old spelling still runs.

A run folder keeps the config it was started with (``.hydra/config.yaml``), whose ``_target_``
entries name classes by module path. When a module moves, a resume would see a difference in
every moved ``_target_`` and refuse; :func:`current_targets` rewrites the stored paths to
today's before the comparison (``resireg_train.checks.resume.check_resume``). One entry per
``_target_`` that a ``conf/`` file of an earlier release named and that has moved since (a class
moved again: point its old entries at the new path, and add the path it leaves). The module
moves behind them are listed in ``CHANGELOG.md``.

A config key or group users type that is renamed keeps its old spelling for one release
(:data:`RENAMED_KEYS`, the one table of renamed keys): a command-line override in the old
spelling (``logger=mlflow``, ``+logger=...``, ``~logger``, ``logger.mlflow.check_timeout=3``, a
multirun's ``logger=csv,mlflow``) is rewritten to the new one with one warning line naming it,
before Hydra parses the command line (:func:`current_argv`, called by every Hydra main's entry
point); the old and the new spelling given together are refused in one line naming both; from
the release that removes the old spelling it is refused, naming that release. A stored run
folder's config and overrides in the old spelling are read in the new one without a warning
(:func:`current_spelling`, :func:`current_overrides`), and one that names a class of ours that
no longer exists and is in no table here is refused naming it (:func:`check_stored_targets`).
"""

from __future__ import annotations

import ast
import importlib.util
import re
from collections.abc import Callable, Sequence
from dataclasses import dataclass
from typing import Any

import yaml

from resireg.errors import ConfigError
from resireg_train.config.paths import CONFIG_DIR

__all__ = [
    "MOVED_TARGETS",
    "RENAMED_KEYS",
    "RELEASE",
    "RenamedKey",
    "check_stored_targets",
    "current_argv",
    "current_keys",
    "current_overrides",
    "current_spelling",
    "current_targets",
]

#: The release this code is (CHANGELOG.md's [Unreleased], the one after 0.1.0): a renamed key's
#: old spelling is read while this is before its ``removed`` release, and refused from it on.
RELEASE = "0.2.0"


@dataclass(frozen=True)
class RenamedKey:
    """A top-level config key or group whose name changed: ``old`` -> ``new`` in the release
    ``since``; the old spelling is read (with a warning on the command line) until ``removed``.
    ``configs``: the ``conf/<name>.yaml`` configs it is a key of (the others are left alone:
    ``rerun`` is a key of ``map.yaml`` only)."""

    old: str
    new: str
    since: str
    removed: str
    configs: tuple[str, ...]


#: Renamed top-level keys and config groups, by their old spelling (issue 52: one word per
#: meaning; "logger" keeps only Python's logging meaning, "rerun" means running a job again)
RENAMED_KEYS: dict[str, RenamedKey] = {
    "logger": RenamedKey("logger", "tracker", "0.2.0", "0.3.0",
                         ("train", "eval", "map", "map_merge")),  # fmt: skip
    "rerun": RenamedKey("rerun", "viewer", "0.2.0", "0.3.0", ("map",)),
    # resireg-map's one ReSiReg variant: what resireg-eval's variants= lists
    "configuration": RenamedKey("configuration", "variant", "0.2.0", "0.3.0", ("map",)),
}

#: ``_target_`` in an earlier release's conf/ -> today's
MOVED_TARGETS: dict[str, str] = {
    # 0.1 -> the layout by role (resireg_train.ovss -> evaluation/ovss, tracking -> runs/)
    "resireg_train.ovss.callback.ReSiRegEval": "resireg_train.evaluation.ovss.callback.ReSiRegEval",
    "resireg_train.tracking.wandb_logger": "resireg_train.record.trackers.wandb.wandb_logger",
    # the trackers' table (resireg_train.runs.trackers): W&B's logger factory with the others
    "resireg_train.runs.tracking.wandb_logger": "resireg_train.record.trackers.wandb.wandb_logger",
    # issue 52: the Hydra callbacks leave the CLI's door for the jobs (cli/job.py split by idea)
    "resireg_train.cli.job.RunFolderLock": "resireg_train.jobs.run_folder.RunFolderLock",
    "resireg_train.cli.job.SweepRecords": "resireg_train.jobs.summary.SweepRecords",
    "resireg_train.cli.train.RunFolderCheck": "resireg_train.jobs.train.RunFolderCheck",
    # issue 52: the pruning glue joined the search (training/pruning -> sweeps/ -> search/)
    "resireg_train.training.pruning.OptunaPruning": "resireg_train.search.pruning.OptunaPruning",
    # the run record apart from the run tools, sweeps/ -> search/ (issue 52: record/trackers/
    # holds one module per tracker; "sweep" is a Hydra multirun, the Optuna search is search/)
    "resireg_train.runs.loggers.wandb_logger": "resireg_train.record.trackers.wandb.wandb_logger",
    "resireg_train.sweeps.pruning.OptunaPruning": "resireg_train.search.pruning.OptunaPruning",
}


def current_targets(tree: Any) -> Any:
    """A copy of a config tree (dicts and lists) with every moved ``_target_`` value replaced
    by today's path (:data:`MOVED_TARGETS`); other values unchanged."""
    if isinstance(tree, dict):
        return {
            key: MOVED_TARGETS.get(value, value)
            if key == "_target_" and isinstance(value, str)
            else current_targets(value)
            for key, value in tree.items()
        }
    if isinstance(tree, list):
        return [current_targets(value) for value in tree]
    return tree


#: the config group whose keys an evaluation dataset entry written before the OVSS protocols
#: (0.1) leaves out: such an entry ran the paper's 2D protocol, which that file spells out
PROTOCOL_BEFORE_KEYS = "protocol/paper.yaml"


def current_keys(tree: Any) -> Any:
    """A copy of a config tree in which every evaluation dataset entry (a mapping with a
    ``kind`` under a ``datasets`` key) that lacks a protocol key gets the value the release
    that wrote it ran with (:data:`PROTOCOL_BEFORE_KEYS`, read from ``conf/``), so a run
    written before the keys were spelled out compares equal to today's composition of the
    same command. Keys present are kept as they are."""
    before = yaml.safe_load((CONFIG_DIR / PROTOCOL_BEFORE_KEYS).read_text())

    def walk(node: Any, under_datasets: bool = False) -> Any:
        if isinstance(node, list):
            return [walk(value) for value in node]
        if not isinstance(node, dict):
            return node
        if under_datasets:
            return {
                key: {**before, **walk(entry)}
                if isinstance(entry, dict) and "kind" in entry
                else walk(entry)
                for key, entry in node.items()
            }
        return {key: walk(value, key == "datasets") for key, value in node.items()}

    return walk(tree)


def _release(text: str) -> tuple[int, ...]:
    return tuple(int(part) for part in re.findall(r"\d+", text)[:3])


def _renames(config_name: str | None) -> dict[str, RenamedKey]:
    return {old: r for old, r in RENAMED_KEYS.items()
            if config_name is None or config_name in r.configs}  # fmt: skip


#: an override's parts: its prefix (``+``, ``++``, ``~``), its key's first name, the rest
_OVERRIDE = re.compile(r"^(?P<prefix>\+\+|\+|~)?(?P<head>[A-Za-z_][\w-]*)(?P<rest>(?:[./@=].*)?)$",
                       re.DOTALL)  # fmt: skip


def _respelled(override: str, renames: dict[str, RenamedKey]) -> tuple[str, RenamedKey | None]:
    """``override`` in today's spelling, and the rename it went through (``None``: none)."""
    match = _OVERRIDE.match(override)
    if not match or match["head"] not in renames:
        return override, None
    rename = renames[match["head"]]
    return f"{match['prefix'] or ''}{rename.new}{match['rest']}", rename


def _head(override: str) -> str | None:
    match = _OVERRIDE.match(override)
    return match["head"] if match else None


def current_overrides(config_name: str | None, overrides: Sequence[str]) -> list[str]:
    """A stored run's overrides (``.hydra/overrides.yaml``) in today's spelling, silently: what
    the run was given is not the user's command (``resireg-runs rerun``, a resume's command)."""
    renames = _renames(config_name)
    return [_respelled(str(o), renames)[0] for o in overrides]


def current_argv(
    config_name: str, argv: Sequence[str], warn: Callable[[str], None]
) -> list[str]:
    """The command line ``argv`` (the words after the program's name) of the Hydra main of
    ``conf/<config_name>.yaml`` with every override in a renamed key's old spelling rewritten to
    the new one, before Hydra parses it; ``warn`` gets one line per renamed key used, naming the
    new key and the release that removes the old spelling. Flags (``-m``, ``--cfg job``) and
    their values are kept as they are.

    Raises :class:`ConfigError` (one line) when a key is given in both spellings (naming
    both), or in an old spelling the running release no longer reads (naming the release that
    removed it)."""
    renames = _renames(config_name)
    out: list[str] = []
    used: dict[str, list[str]] = {}
    heads = {_head(w) for w in argv if not w.startswith("-")}
    for word in argv:
        new, rename = (word, None) if word.startswith("-") else _respelled(word, renames)
        if rename is not None:
            if _release(RELEASE) >= _release(rename.removed):
                raise ConfigError(
                    f"{word}: {rename.old!r} was renamed {rename.new!r} in {rename.since} and "
                    f"its old spelling was removed in {rename.removed}: write {new}"
                )
            if rename.new in heads:
                both = " ".join(w for w in argv if _head(w) in (rename.old, rename.new)
                                and not w.startswith("-"))  # fmt: skip
                raise ConfigError(
                    f"{both}: {rename.old!r} and {rename.new!r} name one setting "
                    f"({rename.old!r} is the old spelling of {rename.new!r}): give it once, "
                    f"as {rename.new!r}"
                )
            used.setdefault(rename.old, []).append(f"{word} -> {new}")
        out.append(new)
    for old, words in used.items():
        rename = renames[old]
        warn(f"{old!r} is now {rename.new!r} (renamed in {rename.since}; the old spelling goes "
             f"in {rename.removed}): read {', '.join(words)}")  # fmt: skip
    return out


def current_spelling(tree: Any, config_name: str | None = None) -> Any:
    """A copy of a stored config tree (``.hydra/config.yaml`` as dicts and lists) whose
    top-level keys in a renamed key's old spelling take the new one (:data:`RENAMED_KEYS`; for
    ``config_name``'s renames, every rename when ``None``), silently; other keys unchanged. A
    tree holding both spellings keeps both (the comparison with today's config names them)."""
    if not isinstance(tree, dict):
        return tree
    renames = _renames(config_name)
    return {
        (renames[key].new if key in renames and renames[key].new not in tree else key): value
        for key, value in tree.items()
    }


#: the packages whose class paths the moves table covers (a library's own class is its own)
_OURS = ("resireg", "resireg_train", "hydra_plugins")


def _defines(dotted: str) -> bool:
    """Whether the module path ``dotted`` of ours (``pkg.module.Name``) names something that
    exists today, read from the module's source (nothing is imported: the check runs before
    torch loads)."""
    module, _, name = dotted.rpartition(".")
    try:
        spec = importlib.util.find_spec(module) if module else None
    except (ImportError, ValueError):  # a parent that is no package
        spec = None
    if spec is None or not spec.origin or not spec.origin.endswith(".py"):
        try:  # a module itself (a package's submodule named by the path)
            return importlib.util.find_spec(dotted) is not None
        except (ImportError, ValueError):
            return False
    with open(spec.origin, encoding="utf-8") as handle:
        tree = ast.parse(handle.read())
    for node in tree.body:
        if isinstance(node, (ast.ClassDef, ast.FunctionDef, ast.AsyncFunctionDef)):
            if node.name == name:
                return True
        elif isinstance(node, (ast.Assign, ast.AnnAssign)):
            targets = node.targets if isinstance(node, ast.Assign) else [node.target]
            if any(isinstance(t, ast.Name) and t.id == name for t in targets):
                return True
        elif isinstance(node, (ast.Import, ast.ImportFrom)):
            if any((a.asname or a.name).split(".")[0] == name for a in node.names):
                return True
    return False


def check_stored_targets(tree: Any, where: str, written_by: str | None = None) -> None:
    """Refuse a stored config (``where``: its file) naming a ``_target_`` of ours that no
    longer exists and that no entry of :data:`MOVED_TARGETS` maps (``tree`` read through
    :func:`current_targets` first): one :class:`ConfigError` naming its key and value, the
    release that no longer has it and the one that wrote the run (``written_by``, when
    recorded), instead of a traceback from Hydra's instantiate."""
    gone: list[str] = []

    def walk(node: Any, path: str) -> None:
        if isinstance(node, dict):
            for key, value in node.items():
                at = f"{path}.{key}" if path else str(key)
                if (key == "_target_" and isinstance(value, str)
                        and value.split(".")[0] in _OURS and not _defines(value)):  # fmt: skip
                    gone.append(f"{at}={value}")
                else:
                    walk(value, at)
        elif isinstance(node, list):
            for i, value in enumerate(node):
                walk(value, f"{path}[{i}]")

    walk(tree, "")
    if gone:
        wrote = f" (the run was written by {written_by})" if written_by else ""
        raise ConfigError(
            f"{where}: {'; '.join(gone)}: no such class in release {RELEASE}{wrote}, and no "
            "entry of the moves table (resireg_train.config.moves.MOVED_TARGETS) maps it, so "
            "this run cannot be resumed or rerun by this release"
        )
