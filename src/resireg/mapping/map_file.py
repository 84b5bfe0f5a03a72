"""A saved map's files: ``map.json`` and its tensor file, their checks, and the earlier formats.

:meth:`SemanticMap.save <resireg.mapping.SemanticMap.save>` writes a :class:`MapSnapshot` (the
tensor file, then ``map.json``: the commit point); :func:`read_map` is
:meth:`SemanticMap.load <resireg.mapping.SemanticMap.load>`'s body: ``map.json``'s own digest and
the tensor file's SHA-256 verified, every field checked (:func:`record_errors`) before anything
is built from it, maps of the earlier formats (:data:`FORMATS`) read. :func:`map_folder` is the
one rule for an argument that names a map; :func:`remove_partial_saves` clears the temporary
files of saves killed midway.
"""

from __future__ import annotations

import hashlib
import json
import os
import uuid
import warnings
from collections.abc import Callable, Mapping, Sequence
from pathlib import Path
from typing import Any

import torch
from torch import Tensor

from resireg.errors import parameters
from resireg.integrity import IntegrityError, atomic_write, read_json, sha256_file, verify_digests
from resireg.mapping.compact import CompactSettings
from resireg.mapping.tensor_file import read_tensors, write_tensors
from resireg.specs.mapping import map_errors
from resireg.specs.variants import takes_prior

__all__ = [
    "FORMAT",
    "FORMATS",
    "MAP_JSON",
    "MAX_PARTS",
    "MapFormatWarning",
    "MapSnapshot",
    "encoder_dim",
    "inside_folder",
    "map_folder",
    "read_map",
    "record_digest",
    "record_errors",
    "remove_partial_saves",
]

#: The files of a saved map: the JSON (written last: the commit point) names its tensor file.
MAP_JSON = "map.json"
#: The format :meth:`SemanticMap.save` writes. It changes whenever what a reader needs changes:
#: ``/2`` holds each map's keys in row order with its hash table, its storage and basis.
FORMAT = "resireg.semantic_map/2"
#: The formats :meth:`SemanticMap.load` reads: ``/1`` (indices in lexicographic order; maps
#: saved before the digests were recorded load with a :class:`MapFormatWarning`) and ``/2``.
FORMATS = ("resireg.semantic_map/1", FORMAT)


class MapFormatWarning(UserWarning):
    """A saved map of an earlier format was loaded without what the current one proves."""


def inside_folder(folder: Path, name: Any, field: str, record: Path) -> Path:
    """``folder / name`` when ``name`` (read from ``record``'s ``field``) is a file name that
    stays inside ``folder``; else an :class:`IntegrityError` naming the field and the path
    (a record names its own files; it never points elsewhere)."""
    if not isinstance(name, str) or not name:
        raise IntegrityError(f"{record}: {field}={name!r}: expected a file name")
    path = folder / name
    inside = Path(name).name == name and not Path(name).is_absolute() and name not in (".", "..")
    if not inside or path.resolve().parent != folder.resolve():
        raise IntegrityError(
            f"{record}: {field}={name!r} names a file outside the map folder {folder} "
            "(a map's files stay in its folder)"
        )
    return path


def map_folder(path: str | Path) -> Path:
    """The saved map a "map" argument names: ``path`` itself when it holds ``map.json`` (a map
    folder), else its ``map`` folder (a ``resireg-map`` or ``resireg-map-merge`` run folder).
    The one rule for every argument that names a map (:meth:`SemanticMap.load`,
    ``compact.basis``, ``resireg-map-merge``'s maps); a :class:`FileNotFoundError` naming
    ``path`` when it is neither."""
    path = Path(path).expanduser()
    for folder in (path, path / "map"):
        if (folder / MAP_JSON).is_file():
            return folder
    raise FileNotFoundError(f"{str(path)!r} is neither a saved map (no {MAP_JSON}) nor a run "
                            f"folder holding one (no map/{MAP_JSON})")  # fmt: skip


def _integer(value: Any, least: int) -> bool:
    return isinstance(value, int) and not isinstance(value, bool) and value >= least


def _sha256_text(value: Any) -> bool:
    """``None`` or a SHA-256 as ``hexdigest`` writes it."""
    hexdigits = "0123456789abcdef"
    return value is None or (isinstance(value, str) and len(value) == 64
                             and all(c in hexdigits for c in value))  # fmt: skip


#: The most parts (:attr:`SemanticMap.parts`) a map may be made of (a merge of more is refused;
#: a record naming more is refused before it is read further).
MAX_PARTS = 4096


def _parts_ok(value: Any) -> bool:
    """A map's ``parts``: 1 to :data:`MAX_PARTS` distinct ids, each 32 (a uuid4's hex) or 64
    (a SHA-256) lowercase hex digits."""
    hexdigits = "0123456789abcdef"
    return (isinstance(value, list) and 0 < len(value) <= MAX_PARTS
            and all(isinstance(x, str) and len(x) in (32, 64) and all(c in hexdigits for c in x)
                    for x in value)
            and len(set(value)) == len(value))  # fmt: skip


def _params_ok(value: Any) -> bool:
    """A map's ``params``: variant name -> ``None`` or its keyword arguments."""
    return isinstance(value, dict) and all(
        isinstance(k, str) and (x is None or isinstance(x, dict)) for k, x in value.items()
    )


#: The fields of ``map.json`` that :meth:`SemanticMap.load` reads beside the digests and the
#: tensor file's name: (required, rule, what the rule expects).
_RECORD_FIELDS: dict[str, tuple[bool, Callable[[Any], bool], str]] = {
    "settings": (True, lambda v: isinstance(v, dict), "a mapping of the map's settings"),
    "dim": (True, lambda v: v is None or _integer(v, 1), "null or an integer >= 1"),
    "stored_dim": (False, lambda v: v is None or _integer(v, 1), "null or an integer >= 1"),
    "basis_sha256": (False, _sha256_text, "null or a SHA-256 (64 lowercase hex digits)"),
    "voxels": (True, lambda v: _integer(v, 0), "an integer >= 0"),
    "frames": (True, lambda v: _integer(v, 0), "an integer >= 0"),
    "windows": (True, lambda v: _integer(v, 0), "an integer >= 0"),
    "meta": (False, lambda v: v is None or isinstance(v, dict), "null or a mapping"),
    "parts": (
        False,
        _parts_ok,
        f"a list of 1 to {MAX_PARTS} distinct ids of 32 or 64 lowercase hex digits",
    ),
}
#: The keys of a record's ``settings`` that are not rules of MAP_RULES: their rule here.
_SETTING_TYPES: dict[str, tuple[Callable[[Any], bool], str]] = {
    "configuration": (lambda v: isinstance(v, str) and bool(v), "a configuration name"),
    "params": (_params_ok, "a mapping of variant name -> null or a mapping of its arguments"),
    "colour": (lambda v: isinstance(v, bool), "true or false"),
    "compact": (lambda v: v is None or isinstance(v, dict), "null or a mapping"),
}


def record_errors(record: Mapping[str, Any], names: Sequence[str]) -> list[str]:
    """``field=value: expected ...`` for each field of a map record that :meth:`SemanticMap.load`
    cannot take (:data:`_RECORD_FIELDS`; ``settings.<key>`` by the map settings' own rules,
    :data:`~resireg.specs.mapping.MAP_RULES`, and :data:`_SETTING_TYPES`; ``names``: the
    setting keys a map has), so a record is refused whole before anything is built from it."""
    errors = []
    for name, (required, ok, expected) in _RECORD_FIELDS.items():
        if name not in record:
            if required:
                errors.append(f"{name}: missing")
        elif not ok(record[name]):
            errors.append(f"{name}={_shown(record[name])}: expected {expected}")
    settings = record.get("settings")
    if not isinstance(settings, dict):
        return errors
    errors += [f"settings.{k}: no such setting (expected one of {sorted(names)})"
               for k in settings if k not in names]  # fmt: skip
    errors += [f"settings.{k}: missing" for k in ("configuration", "params", "voxel_size")
               if k not in settings]  # fmt: skip
    for key, (ok, expected) in _SETTING_TYPES.items():
        if key in settings and not ok(settings[key]):
            errors.append(f"settings.{key}={_shown(settings[key])}: expected {expected}")
    ruled = {k: v for k, v in settings.items() if k != "compact" or isinstance(v, dict)}
    return errors + map_errors(ruled, prefix="settings.")


def _shown(value: Any) -> str:
    """A value as an error names it: its repr, cut to 80 characters."""
    text = repr(value)
    return text if len(text) <= 80 else text[:77] + "..."


def record_digest(record: Mapping[str, Any]) -> str:
    """SHA-256 of a map record's canonical JSON without its ``record_sha256`` field: an edit of
    ``map.json`` (a ``voxel_size``, a count) no longer matches the digest written with it."""
    body = {k: v for k, v in record.items() if k != "record_sha256"}
    return hashlib.sha256(json.dumps(body, sort_keys=True).encode()).hexdigest()


@torch.no_grad()
def encoder_dim(encoder: Any) -> int | None:
    """The dimension of ``encoder``'s dense text queries (that of the features it fuses), or
    ``None`` for an encoder without a text path."""
    try:
        return int(encoder.dense_text(encoder.text_features(["a"])).shape[-1])
    except NotImplementedError:
        return None


def _running(pid: int) -> bool:
    """Whether a process ``pid`` runs on this machine (signal 0 probes it)."""
    try:
        os.kill(pid, 0)
    except ProcessLookupError:
        return False
    except (PermissionError, OverflowError):
        return True  # another user's (or an id no process can have: kept, to be safe)
    return True


def remove_partial_saves(folder: str | Path) -> list[Path]:
    """Remove from a map folder the temporary files of saves whose process no longer runs:
    :func:`~resireg.integrity.atomic_write` names them ``.<file>.<pid>.<id>.tmp``, and one
    killed mid-save (SIGKILL, a power cut) leaves its file behind (the committed map is
    untouched). A save of this or another running process is left alone. Returns the files
    removed; :meth:`SemanticMap.save` calls it, and the commands that write a map folder at
    their start."""
    removed = []
    for tmp in Path(folder).glob(".map*.tmp"):
        parts = tmp.name.split(".")
        if len(parts) >= 5 and parts[-3].isdigit() and not _running(int(parts[-3])):
            tmp.unlink(missing_ok=True)
            removed.append(tmp)
    return removed


class MapSnapshot:
    """A map's tensors (lists of blocks, by file name) and record, as :meth:`SemanticMap.save`
    writes them (:meth:`SemanticMap.snapshot`)."""

    def __init__(self, tensors: dict[str, list[Tensor]], record: dict[str, Any]) -> None:
        self.tensors, self.record = tensors, record

    @classmethod
    def of(cls, smap: Any, copy: bool = True) -> MapSnapshot:
        """What :meth:`SemanticMap.save <resireg.mapping.SemanticMap.save>` writes of ``smap``,
        taken now (a compact map's waiting windows fitted first); with ``copy`` the tensors
        are copied, so the snapshot is written while the map goes on changing."""
        smap.fit_pending()
        tensors = smap.store.tensors()
        if copy:
            tensors = {k: [b.clone() for b in v] for k, v in tensors.items()}
        record = {
            "format": FORMAT,
            "settings": smap.settings(),
            "dim": smap.dim,
            "stored_dim": smap.stored_dim,
            "basis_sha256": smap.basis_sha256,
            "voxels": len(smap),
            "frames": smap.frames,
            "windows": smap.windows,
            "meta": json.loads(json.dumps(smap.meta)),
            "parts": list(smap.parts),
        }
        return cls(tensors, record)

    def write(self, folder: str | Path) -> Path:
        """Write the tensor file, then ``map.json`` (the commit point), then remove older
        tensor files (:meth:`SemanticMap.save`)."""
        folder = Path(folder)
        folder.mkdir(parents=True, exist_ok=True)
        remove_partial_saves(folder)
        name = f"map-{uuid.uuid4().hex[:12]}.safetensors"
        digest: dict[str, str] = {}
        try:
            atomic_write(
                folder / name, lambda tmp: digest.update({name: write_tensors(tmp, self.tensors)})
            )
            record = {**self.record, "tensors": name, "sha256": digest}
            record["record_sha256"] = record_digest(record)
            text = json.dumps(record, indent=2, sort_keys=True)
            atomic_write(folder / MAP_JSON, lambda tmp: tmp.write_text(text))
        except BaseException:
            (folder / name).unlink(missing_ok=True)  # not committed: map.json names the old one
            raise
        for old in folder.glob("map-*.safetensors"):
            if old.name != name:
                old.unlink(missing_ok=True)
        return folder


def read_map(
    cls: Any,
    folder: str | Path,
    encoder: Any,
    prior: Callable[[Tensor], Tensor] | None,
    device: torch.device | str | None,
    overrides: Mapping[str, Any],
) -> Any:
    """:meth:`resireg.mapping.SemanticMap.load`: a map of class ``cls`` rebuilt from ``folder``
    (its storage fills itself from the tensors: ``store.restore``); a map of an earlier format
    too (:data:`FORMATS`). ``folder``: the map folder or a run folder holding it in ``map/``
    (:func:`map_folder`).

    Before any tensor is read, ``map.json``'s own digest and its tensor file's SHA-256 are
    verified: a truncated, edited or damaged file is an
    :class:`~resireg.integrity.IntegrityError` naming it, and so is a record that names a
    file outside ``folder``. Then every field of the record is checked (its type and
    range, the settings by their rules) and every size it gives against the tensors'
    shapes, before anything is allocated by it: a record edited with its digests
    recomputed is refused in one line naming the file and the field, and a load allocates
    no more than its file holds. A map saved before maps recorded their digests loads with
    a :class:`~resireg.mapping.map_file.MapFormatWarning`. The tensors are memory-mapped
    (copy-on-write: the file never changes). An ``encoder`` whose text features have
    another dimension than the map's is refused here, not at the first query (the weights
    themselves are the caller's to check: ``resireg-map`` records a digest of them in
    ``meta``). ``overrides`` replace saved settings that do not change the content
    (``max_voxels``). The record keeps its field names whatever the constructor's keywords
    (``settings.configuration`` is the variant's name): maps saved before and after the keyword
    became ``variant`` load alike."""
    folder = map_folder(folder)
    path = folder / MAP_JSON
    record = read_json(path, "saved map record")
    fmt = record.get("format") if isinstance(record, dict) else type(record).__name__
    if not isinstance(record, dict) or fmt not in FORMATS:
        raise IntegrityError(f"{path}: format {_shown(fmt)}, expected one of {list(FORMATS)}")
    tensor_file = inside_folder(folder, record.get("tensors"), "tensors", path)
    if "record_sha256" not in record and "sha256" not in record and fmt == FORMATS[0]:
        warnings.warn(
            f"{path}: a map saved before maps recorded their digests (format {fmt} without "
            "sha256): loaded unverified; save it again to record them",
            MapFormatWarning,
            stacklevel=3,
        )
    else:
        if "record_sha256" not in record or "sha256" not in record:
            raise IntegrityError(f"{path}: no record_sha256 / sha256 (an edited record): "
                                 "make the map again")  # fmt: skip
        if record["record_sha256"] != record_digest(record):
            raise IntegrityError(
                f"{path}: its content does not match the record_sha256 written with it (the "
                "file was edited or damaged; a map's settings cannot change after it is made)"
            )
        if not isinstance(record["sha256"], dict):
            raise IntegrityError(f"{path}: sha256={_shown(record['sha256'])}: expected a "
                                 "mapping")  # fmt: skip
        for name in record["sha256"]:
            inside_folder(folder, name, "sha256", path)
        if tensor_file.name not in record["sha256"]:
            raise IntegrityError(f"{path}: records no SHA-256 of {tensor_file.name}")
        verify_digests(folder, record["sha256"], "saved map")
    # Every field is checked before anything is built from it: a record whose digests were
    # recomputed after an edit is refused here, naming the field, not deep in the code.
    names = set(parameters(cls)) - {"encoder", "variant", "prior", "prior_input", "device"}
    errors = record_errors(record, sorted(names))
    if errors:
        raise IntegrityError(f"{path}: " + "; ".join(errors))
    bad = set(overrides) - {"max_voxels"}
    if bad:
        raise ValueError(f"load(): {sorted(bad)} cannot change on a saved map")
    errors = map_errors(overrides, keys=list(overrides))
    if errors:
        raise ValueError("load(): " + "; ".join(errors))
    settings = {**record["settings"], **overrides}
    config = settings.pop("configuration")
    params = settings.pop("params")
    voxel_size = settings.pop("voxel_size")
    if encoder is not None and record["dim"] is not None:
        enc_dim = encoder_dim(encoder)
        if enc_dim is not None and enc_dim != int(record["dim"]):
            raise ValueError(
                f"{path}: the map holds {record['dim']}-d features, the encoder given to "
                f"load() makes {enc_dim}-d ones (another model: load the map with the "
                "encoder it was built with)"
            )
    compact = settings.get("compact")
    if compact is not None:  # the basis comes from the file, not from where it came from
        settings["compact"] = {**compact, "basis": None}
    try:
        smap = cls(encoder if encoder is not None else None, config, voxel_size,
                   params=params, prior=prior,
                   device=device or (encoder.device if encoder is not None else "cpu"),
                   **settings)  # fmt: skip
        if smap.store.compact is not None and compact is not None:
            smap.store.compact = CompactSettings.of(compact)
    except (TypeError, ValueError) as err:
        if encoder is not None and prior is None and takes_prior(config):
            raise  # the caller's: a +prior configuration loaded without prior=
        raise IntegrityError(f"{path}: settings: {err}") from err
    tensors = read_tensors(tensor_file, "saved map")
    try:
        smap.store.restore(record, tensors, old=record["format"] == FORMATS[0])
    except (KeyError, ValueError, RuntimeError) as err:
        raise IntegrityError(f"{tensor_file}: does not hold the map its record {path} "
                             f"describes ({err})") from err  # fmt: skip
    smap.frames, smap.windows = record["frames"], record["windows"]
    smap.meta = dict(record.get("meta") or {})
    # A map saved before maps recorded their parts is one part: its tensor file's SHA-256.
    smap.parts = (
        list(record["parts"])
        if "parts" in record
        else [(record.get("sha256") or {}).get(tensor_file.name) or sha256_file(tensor_file)]
    )
    return smap
