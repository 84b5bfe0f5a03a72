"""The one table type of the project: :class:`SpecTable`, ``name -> entry`` for each kind of
component (variants, encoders, priors, metrics, map sources, text towers; ``resireg_train``'s
datasets, tasks, teachers and report sections).

A table is read before torch loads (the config checks, the report, the CLIs' ``--help``), so an
entry names its code lazily, ``"package.module:attribute"``, loaded by :func:`load` when
something is built. A table

- answers an unknown name with the closest ones (:meth:`SpecTable.get`, ``difflib``),
- finds the ``conf/<group>/*.yaml`` files of each entry by scanning the folder and reading
  each file's ``kind`` (its ``defaults`` parents followed), as open_clip scans its model
  configs, so no list of files is typed beside the files (:meth:`SpecTable.configs`),
- optionally takes entries from installed packages through an entry-point group, looked up
  only for a name the built-in entries lack (so checking a built-in name reads no package
  metadata).

Torch-free, and it imports nothing of ``resireg`` but :mod:`resireg.errors`.
"""

from __future__ import annotations

import difflib
import errno
import functools
import importlib
import os
from collections.abc import Callable, Iterable, Iterator, Mapping
from dataclasses import dataclass
from pathlib import Path
from typing import Any, Generic, TypeVar

from resireg.errors import ConfigError

__all__ = ["KindSpec", "SpecTable", "UnknownNameError", "compose_conf", "conf_dir", "load"]

E = TypeVar("E")


def load(target: str) -> Any:
    """The object a ``"package.module:attribute"`` path names (imported now); the attribute
    may be dotted (``"module:Class.builder"``, a classmethod)."""
    module, sep, attribute = target.partition(":")
    if not sep or not module or not attribute:
        raise ValueError(f"{target!r}: expected 'package.module:attribute'")
    return functools.reduce(getattr, attribute.split("."), importlib.import_module(module))


def conf_dir() -> Path:
    """The project's ``conf/`` folder: ``$RESIREG_CONFIG_DIR`` if set, else the checkout's."""
    env = os.environ.get("RESIREG_CONFIG_DIR")
    return Path(env) if env else Path(__file__).resolve().parents[3] / "conf"


@dataclass(frozen=True)
class KindSpec:
    """An entry that is only its ``kind`` (the ``kind:`` of its ``conf/`` files), its code
    (``"module:attribute"``, imported by :meth:`load`) and a one-line ``summary``: the entry
    type of the tables whose kinds need no more (text towers, teachers)."""

    kind: str
    target: str
    summary: str

    def load(self) -> Any:
        """The code (imported now)."""
        return load(self.target)


class UnknownNameError(ConfigError, KeyError):
    """A name a table does not hold; the message lists the closest names and every name."""

    def __str__(self) -> str:  # KeyError would quote the message
        return str(self.args[0]) if self.args else ""


def _read_yaml(path: Path) -> dict[str, Any]:
    import yaml  # PyYAML: a dependency of huggingface_hub and transformers, in every install

    data = yaml.safe_load(path.read_text()) or {}
    return data if isinstance(data, dict) else {}


def compose_conf(
    folder: str | os.PathLike,
    stem: str,
    read: Callable[[Path], dict[str, Any]] = _read_yaml,
    _seen: tuple[str, ...] = (),
) -> dict[str, tuple[Any, str]]:
    """``key -> (value, file)`` of ``<folder>/<stem>.yaml`` composed as Hydra composes a config
    group's file: its ``defaults`` in order (files of the same folder, or another group's file
    merged into this package, ``/<group>/<name>@_here_``: ``conf/protocol/ovss8.yaml`` into a
    dataset entry), its own keys where ``_self_`` stands (last when it is not listed); ``file``
    (``group/name.yaml``) is the one a value comes from. Interpolations stay as written. ``read``
    loads one file (PyYAML by default; the training package passes OmegaConf's loader). A
    missing file is a ``FileNotFoundError`` naming it. The one composition rule of the tables'
    scan, the live node's defaults and ``resireg_train.data.specs.dataset_conf``."""
    folder = Path(folder)
    path = folder / f"{stem}.yaml"
    if not path.is_file():
        raise FileNotFoundError(errno.ENOENT, "no such file", str(path))
    data = dict(read(path))
    parents = list(data.pop("defaults", None) or [])
    if "_self_" not in parents:
        parents.append("_self_")
    out: dict[str, tuple[Any, str]] = {}
    for parent in parents:
        if parent == "_self_":
            out.update({k: (v, f"{folder.name}/{stem}.yaml") for k, v in data.items()})
        elif isinstance(parent, str) and parent.startswith("/"):
            # another group's file merged here (Hydra's /<group>/<name>@_here_); the folder is
            # a sibling of this one (both under conf/), so no path leaves conf/
            group, _, name = parent[1:].removesuffix("@_here_").rpartition("/")
            if not group or "@" in name or ".." in group.split("/"):
                raise ValueError(f"{path}: defaults entry {parent!r}: expected "
                                 "/<group>/<name>@_here_")  # fmt: skip
            out.update(compose_conf(folder.parent / group, name, read, (*_seen, stem)))
        elif isinstance(parent, str) and parent not in _seen:
            out.update(compose_conf(folder, parent, read, (*_seen, stem)))
    return out


@functools.cache
def _conf_kinds(folder: str, stamp: float) -> dict[str, str]:
    """``file stem -> kind`` of the YAML files of ``folder``, each composed with its defaults
    (``stamp``: the folder's mtime, so a file added during a process is seen)."""
    kinds = {}
    for path in sorted(Path(folder).glob("*.yaml")):
        kind = compose_conf(folder, path.stem).get("kind")
        if kind is not None:
            kinds[path.stem] = str(kind[0])
    return kinds


class SpecTable(Mapping[str, E], Generic[E]):
    """``name -> entry`` of one kind, in the order given (the report's order where it has one).

    Args:
        what: what an entry is, for messages (``"encoder kind"``).
        entries: the built-in entries.
        name: the attribute of an entry that is its name (``"name"``, ``"kind"``).
        where: the module that holds the table, for messages (``"resireg.specs.encoders"``).
        conf: the ``conf/`` group whose files hold the entries' defaults (``"encoder"``), or
            ``None``.
        entry_points: an entry-point group whose entries (each naming an entry object) add
            names, or ``None``.
    """

    def __init__(
        self,
        what: str,
        entries: Iterable[E],
        *,
        name: str = "name",
        where: str = "",
        conf: str | None = None,
        entry_points: str | None = None,
    ) -> None:
        self.what = what
        self.where = where
        self.conf = conf
        self.entry_points = entry_points
        self._name = name
        self._entries: dict[str, E] = {}
        for entry in entries:
            key = getattr(entry, name)
            if key in self._entries:
                raise ValueError(f"{where}: {what} {key!r} is listed twice")
            self._entries[key] = entry
        self._type = type(next(iter(self._entries.values()))) if self._entries else object

    # -- Mapping: the built-in entries ------------------------------------------------------
    def __getitem__(self, name: str) -> E:
        return self.get(name)

    def __iter__(self) -> Iterator[str]:
        return iter(self._entries)

    def __len__(self) -> int:
        return len(self._entries)

    def __contains__(self, name: object) -> bool:
        return name in self._entries

    def __setitem__(self, name: str, entry: E) -> None:
        """Add (or replace) an entry at run time: a notebook's or a test's own kind. Its name
        must be the entry's own."""
        if getattr(entry, self._name) != name:
            raise ValueError(f"{self.what} {name!r}: the entry's {self._name} is "
                             f"{getattr(entry, self._name)!r}")  # fmt: skip
        self._entries[name] = entry

    def __delitem__(self, name: str) -> None:
        del self._entries[name]

    def __repr__(self) -> str:
        return f"SpecTable({self.what!r}, {list(self._entries)})"

    # -- lookups ----------------------------------------------------------------------------
    def names(self) -> tuple[str, ...]:
        """The built-in names, in table order."""
        return tuple(self._entries)

    def find(self, name: Any) -> E | None:
        """The entry of ``name`` (built-in first, then installed packages'), or ``None``."""
        if not isinstance(name, str):
            return None
        if name in self._entries:
            return self._entries[name]
        return self.plugins().get(name)

    def get(self, name: Any, *default: Any) -> E:  # type: ignore[override]
        """The entry of ``name``; for an unknown name, ``default`` if given, else
        :class:`UnknownNameError` naming the closest names and every name."""
        entry = self.find(name)
        if entry is not None:
            return entry
        if default:
            return default[0]
        raise UnknownNameError(self.unknown(name))

    def unknown(self, name: Any, setting: str | None = None) -> str:
        """The message of an unknown ``name``: ``unknown <what> 'fulll'; did you mean 'full'?
        (choose from [...])``, or with ``setting``, ``<setting>='fulll': expected one of [...];
        did you mean 'full'?``."""
        every = list(self.everything())
        close = difflib.get_close_matches(str(name), every, n=3, cutoff=0.6)
        hint = f"; did you mean {' or '.join(repr(c) for c in close)}?" if close else ""
        if setting is not None:
            return f"{setting}={name!r}: expected one of {every}{hint}"
        source = f" ({self.where})" if self.where else ""
        return f"unknown {self.what} {name!r}{hint} (choose from {every}{source})"

    def everything(self) -> dict[str, E]:
        """Every entry: the built-in ones, then those of installed packages."""
        return {**self._entries, **self.plugins()}

    # -- entry points -----------------------------------------------------------------------
    def plugins(self) -> dict[str, E]:
        """The entries installed packages add (entry points of :attr:`entry_points`)."""
        if self.entry_points is None:
            return {}
        return _plugins(self)

    # -- conf files -------------------------------------------------------------------------
    def configs(self, name: str) -> tuple[str, ...]:
        """The ``conf/<conf>/`` files (stems) whose ``kind`` is ``name``, sorted: found by
        scanning the folder."""
        if self.conf is None:
            return ()
        folder = conf_dir() / self.conf
        if not folder.is_dir():
            return ()
        kinds = _conf_kinds(str(folder), folder.stat().st_mtime)
        return tuple(stem for stem, kind in kinds.items() if kind == name)

    def all_configs(self) -> tuple[str, ...]:
        """Every built-in entry's ``conf/`` files, by entry in table order: what a sweep over
        every entry lists."""
        return tuple(c for name in self._entries for c in self.configs(name))

    def load(self, name: str) -> Any:
        """The code of ``name``'s entry (``entry.load()``)."""
        return self.get(name).load()  # type: ignore[attr-defined]


@functools.cache
def _plugins_cached(group: str, name: str, builtins: tuple[str, ...], kind: type) -> dict:
    from importlib.metadata import entry_points

    found = {}
    for point in entry_points(group=group):
        entry = point.load()
        if kind is not object and not isinstance(entry, kind):
            raise TypeError(
                f"entry point {point.name} = {point.value!r} ({group}): expected a "
                f"{kind.__name__}, got {type(entry).__name__}"
            )
        key = getattr(entry, name)
        if key in builtins:
            raise ValueError(f"entry point {point.value!r} ({group}): {key!r} is built in")
        found[key] = entry
    return found


def _plugins(table: SpecTable) -> dict:
    assert table.entry_points is not None
    return _plugins_cached(table.entry_points, table._name, table.names(), table._type)
