"""What a run reads: the ``data``, ``models`` and ``seeds`` parts of its provenance and the
digest of its config.

- ``data``: the identity of every dataset the config names (:func:`data_identity`);
- ``models``: the export a run reads (``model_path``: its files' SHA-256; a frozen part's file
  given outside it, ``encoder.external``: its SHA-256 under ``external``), the checkpoint a
  run starts from (``model.init_from``, or a ``ckpt_path`` file: its SHA-256) and the encoder's
  config entry (hub repo, ref, weights path) (:func:`input_provenance`, with ``data``);
- ``seeds``: every config key named ``seed`` or ``*_seed`` (:func:`seeds`);
- :func:`config_digest`: the SHA-256 of the resolved config.

Imported by :mod:`resireg_train.record.provenance.block` and by ``resireg-runs rerun``, which
computes the identities again to find what changed.
"""

from __future__ import annotations

import hashlib
import json
import os
from collections.abc import Callable, Iterator, Mapping
from pathlib import Path
from typing import Any

__all__ = [
    "EXPORT_PROVENANCE",
    "config_digest",
    "data_identity",
    "export_identity",
    "file_list_fingerprint",
    "guarded",
    "input_provenance",
    "seeds",
]

#: The training run's provenance, copied into every export it writes.
EXPORT_PROVENANCE = "provenance.json"


def config_digest(cfg: Any) -> str:
    """SHA-256 of the resolved config as YAML (unresolvable values kept as written)."""
    from omegaconf import OmegaConf

    try:
        text = OmegaConf.to_yaml(cfg, resolve=True, sort_keys=True)
    except Exception:  # a value that resolves only inside Hydra's runtime, or a missing ???
        text = OmegaConf.to_yaml(cfg, resolve=False, sort_keys=True)
    return hashlib.sha256(text.encode()).hexdigest()


def seeds(container: Any, prefix: str = "") -> dict[str, Any]:
    found = {}
    if isinstance(container, Mapping):
        for key, value in container.items():
            path = f"{prefix}{key}"
            if str(key) == "seed" or str(key).endswith("_seed"):
                if isinstance(value, (int, float, str)) or value is None:
                    found[path] = value
            found.update(seeds(value, f"{path}."))
    return found


def file_list_fingerprint(paths: list[Path], base: Path) -> dict[str, Any]:
    """SHA-256 over every file's relative name, size and modification time (no contents: a
    dataset of terabytes costs one ``stat`` per file), with the file and byte counts."""
    h = hashlib.sha256()
    files = size = 0
    for path in sorted(paths):
        st = path.stat()
        rel = path.relative_to(base) if path != base else Path(path.name)
        h.update(f"{rel.as_posix()}\t{st.st_size}\t{st.st_mtime_ns}\n".encode())
        files += 1
        size += st.st_size
    return {"fingerprint": h.hexdigest(), "files": files, "bytes": size}


def _walk(root: Path) -> Iterator[Path]:
    if root.is_file():
        yield root
        return
    for folder, dirs, names in os.walk(root):
        dirs.sort()
        for name in names:
            path = Path(folder) / name
            if path.is_file():
                yield path


def data_identity(entry: Mapping[str, Any]) -> dict[str, Any]:
    """What identifies one dataset entry (a ``conf/dataset/`` entry, a caption source, a
    ``resireg-map`` source):

    - generated data (``kind``/``path`` ``synthetic...``): the generator's settings;
    - a local file or folder (``path``, or the files of ``data_files``): the
      :func:`file_list_fingerprint` of the files the run reads (the ``scenes`` listed, else
      the ``split``'s subfolder where there is one, else every file);
    - otherwise a Hugging Face hub dataset: repo, config, split and revision.
    """
    spec = {k: v for k, v in entry.items() if not isinstance(v, (Mapping, list)) or k in (
        "image_size", "scenes", "data_files")}  # fmt: skip
    kind = str(entry.get("kind") or "")
    path = entry.get("path")
    if kind.startswith("synthetic") or kind.endswith("_synthetic") or path == "synthetic":
        return {"kind": "generated", "settings": dict(spec)}
    patterns = entry.get("data_files")
    if patterns:
        import glob

        listed = [patterns] if isinstance(patterns, str) else list(patterns)
        files = [Path(p) for pattern in listed for p in glob.glob(str(pattern), recursive=True)]
        files = [p for p in files if p.is_file()]
        if files:
            base = Path(os.path.commonpath([str(p.parent) for p in files]))
            return {"kind": "local", "path": str(base.resolve()), "data_files": listed,
                    **file_list_fingerprint(files, base)}  # fmt: skip
    if path not in (None, "", "???"):
        local = Path(str(path)).expanduser()
        if local.exists():
            base = local.resolve()
            # only what the run reads: the listed scenes (ScanNet), else the split's folder
            # (ORAD-3D's validation/), else the whole folder
            parts = [base / str(s) for s in entry.get("scenes") or []]
            if not parts and entry.get("split") and (base / str(entry["split"])).is_dir():
                parts = [base / str(entry["split"])]
            files = [f for part in (parts or [base]) if part.exists() for f in _walk(part)]
            return {"kind": "local", "path": str(base),
                    **file_list_fingerprint(files, base)}  # fmt: skip
        return {
            "kind": "hub",
            "repo": str(path),
            "config": entry.get("config") or entry.get("name"),
            "split": entry.get("split"),
            "revision": entry.get("revision") or "main",
        }
    return {"kind": "unknown", "settings": dict(spec)}


def _datasets(plain: Mapping[str, Any]) -> dict[str, Any]:
    """Every dataset entry a run reads: ``dataset`` (resireg-eval), ``source``
    (resireg-map), ``data.sources.*`` (training captions) and the validation sets of the
    ReSiReg callback (``callbacks.resireg_eval.datasets.*``)."""
    found: dict[str, Any] = {}
    for key in ("dataset", "source"):
        if isinstance(plain.get(key), Mapping):
            found[key] = plain[key]
    sources = (
        (plain.get("data") or {}).get("sources") if isinstance(plain.get("data"), Mapping) else None
    )
    for name, entry in (sources or {}).items():
        if isinstance(entry, Mapping):
            found[f"data.sources.{name}"] = entry
    callbacks = plain.get("callbacks") or {}
    evaluation = callbacks.get("resireg_eval") if isinstance(callbacks, Mapping) else None
    for name, entry in ((evaluation or {}).get("datasets") or {}).items():
        if isinstance(entry, Mapping):
            found[f"callbacks.resireg_eval.datasets.{name}"] = entry
    return found


def export_identity(path: str | os.PathLike) -> dict[str, Any]:
    """An export folder's path, each file's SHA-256 and (when the export carries one) the
    provenance of the training run that wrote it: ``{"path", "files", "training_run"}``; for
    an export in MLflow's model registry (``models:/NAME@ALIAS``) those of its local copy
    (downloaded now, once: :mod:`resireg.models.vlm.registry`) with ``uri`` and ``registry``
    (name, version, MLflow run, source)."""
    from resireg.integrity import sha256_file
    from resireg.specs.exports import registry_model

    text = os.fspath(path)
    try:
        registered = registry_model(text) is not None
    except ValueError as err:
        return {"path": text, "files": None, "error": str(err)}
    if registered:
        try:
            from resireg.models.vlm.registry import resolve

            found = resolve(text)
        except Exception as err:  # the run reports it when it loads the model
            return {"path": text, "uri": text, "files": None,
                    "error": f"{type(err).__name__}: {err}"}  # fmt: skip
        registry = {"name": found.name, "version": found.version, "run_id": found.run_id,
                    "source": found.source, "registry": found.registry}  # fmt: skip
        return {**export_identity(found.folder), "uri": text, "registry": registry}
    folder = Path(path).expanduser().resolve()
    if not folder.is_dir():
        return {"path": str(path), "files": None}  # a hub id: resolved by the loader
    files = {p.name: sha256_file(p) for p in sorted(folder.iterdir())
             if p.is_file() and p.suffix in (".safetensors", ".json")
             and p.name != EXPORT_PROVENANCE}  # fmt: skip
    record: dict[str, Any] = {"path": str(folder), "files": files}
    made_by = folder / EXPORT_PROVENANCE
    if made_by.is_file():
        try:
            record["training_run"] = json.loads(made_by.read_text())
        except (OSError, json.JSONDecodeError):
            record["training_run"] = None
    return record


def _models(plain: Mapping[str, Any]) -> dict[str, Any]:
    from resireg.integrity import sha256_file

    models: dict[str, Any] = {}
    if plain.get("model_path"):
        models["export"] = export_identity(str(plain["model_path"]))
    model = plain.get("model")
    init_from = model.get("init_from") if isinstance(model, Mapping) else None
    if init_from:
        path = Path(str(init_from)).expanduser()
        models["init_from"] = {"path": str(path.resolve()),
                               "sha256": sha256_file(path) if path.is_file() else None}  # fmt: skip
    ckpt_path = plain.get("ckpt_path")
    if ckpt_path not in (None, "last"):  # a checkpoint file another run wrote
        path = Path(str(ckpt_path)).expanduser()
        models["ckpt_path"] = {"path": str(path.resolve()),
                               "sha256": sha256_file(path) if path.is_file() else None}  # fmt: skip
    encoder = plain.get("encoder")
    if isinstance(encoder, Mapping):
        models["encoder"] = {k: v for k, v in encoder.items()
                             if isinstance(v, (str, int, float, bool)) or v is None}  # fmt: skip
        external = encoder.get("external")
        given = {f"{part}.{key}": value for part, keys in (external or {}).items()
                 if isinstance(keys, Mapping) for key, value in keys.items() if value}  # fmt: skip
        if given:  # a frozen part's file outside the export, given by the user
            models["external"] = {name: _file_identity(value) for name, value in given.items()}
    return models


def _file_identity(value: Any) -> dict[str, Any]:
    """``{"path", "sha256"}`` of a file the user named (a folder: ``files``, each file's
    SHA-256 by its path inside it; ``None`` where it is missing)."""
    from resireg.integrity import sha256_file

    path = Path(str(value)).expanduser()
    if path.is_dir():
        files = {str(p.relative_to(path)): sha256_file(p) for p in sorted(path.rglob("*"))
                 if p.is_file()}  # fmt: skip
        return {"path": str(path.resolve()), "files": files}
    return {"path": str(path.resolve()), "sha256": sha256_file(path) if path.is_file() else None}


def guarded(what: Callable[[], Any]) -> Any:
    """``what()``, or ``{"error": ...}`` naming why it could not be read: provenance never
    fails a run (a dangling link in a data folder, a file removed meanwhile)."""
    try:
        return what()
    except Exception as err:
        return {"error": f"{type(err).__name__}: {err}"}


def input_provenance(plain: Mapping[str, Any]) -> dict[str, Any]:
    """``{"data", "models"}`` of a resolved config (plain values): what a run reads, as its
    record holds it. ``resireg-runs rerun`` computes it again to find what changed."""
    return {
        "data": {
            key: guarded(lambda e=entry: data_identity(e))
            for key, entry in _datasets(plain).items()
        },  # fmt: skip
        "models": guarded(lambda: _models(plain)),
    }
