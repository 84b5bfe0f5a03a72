"""What produced a run: the ``provenance`` block of every ``results.json`` (``resireg-train``,
``resireg-eval``, ``resireg-map``, each job of a multirun or search).

:func:`start_provenance` writes it when the run starts, before anything heavy is imported:

- ``run_id``: twelve hex digits drawn once per run folder (a resumed run keeps its own), and
  ``cli``: the command (``resireg-train``, ``resireg-eval``, ``resireg-map``);
- ``code``: the package version and, when the code runs from a git checkout of the project,
  its commit, branch and a dirty flag; untracked files by name, size and SHA-256 (never their
  content unless ``provenance.untracked_content`` opts in); tracked files' text changes (and
  the opted-in files) saved as ``code.diff`` (mode 0600) in the run folder, at most
  ``provenance.diff_max_bytes``, so ``git apply code.diff`` on that commit gives the code that
  ran; what was left out named with its size, SHA-256 and reason (:func:`code_provenance`);
  each tracked file that differs from the commit by path and SHA-256 of its content
  (``changes``) and one digest over them (``diff_sha256``), which ``resireg-runs rerun``
  compares whatever ``code.diff`` could hold.
  Outside a checkout (an installed wheel) only the version is recorded; nothing fails;
- ``environment``: Python, the command line (URL passwords masked), the digest of the
  resolved config, and the versions of the packages that change numbers (read with
  :mod:`importlib.metadata`, no import); never an environment variable;
- ``machine``: host, CPU model, cores, memory, PID and world size;
- ``seeds``: every config key named ``seed`` or ``*_seed``;
- ``data``: the identity of every dataset the config names (:func:`data_identity`);
- ``models``: the export a run reads (``model_path``: its files' SHA-256; a frozen part's file
  given outside it, ``encoder.external``: its SHA-256 under ``external``), the checkpoint a
  run starts from (``model.init_from``, or a ``ckpt_path`` file: its SHA-256) and the encoder's
  config entry (hub repo, ref, weights path) (:func:`input_provenance`, with ``data``).

:func:`finish_provenance` completes it at the end (success or failure): end time, wall seconds,
CPU-hours (this process and its children, from ``getrusage``), GPU-hours where CUDA ran (wall
time x the GPUs the run's processes used), torch's CUDA / cuDNN versions, each GPU's name
and memory, and torch's intra-op thread count (``machine.torch_threads``: a CPU result can
change with it, so ``resireg-runs rerun`` runs with the same). Nothing here is typed twice: exports copy their run's block (``provenance.json``
in the export folder, :func:`write_export_provenance`), evaluations and maps read it from there.
"""

from __future__ import annotations

import datetime as _dt
import fnmatch
import hashlib
import importlib.metadata as md
import json
import os
import platform
import re
import shlex
import socket
import stat
import subprocess
import sys
import uuid
from collections.abc import Callable, Iterator, Mapping
from pathlib import Path
from typing import Any

from resireg.secrets import mask_text

__all__ = [
    "CODE_DIFF",
    "EXPORT_PROVENANCE",
    "PACKAGES",
    "code_provenance",
    "config_digest",
    "data_identity",
    "export_identity",
    "file_list_fingerprint",
    "finish_provenance",
    "input_provenance",
    "machine_provenance",
    "package_versions",
    "provenance_settings",
    "start_provenance",
    "write_export_provenance",
]

#: The uncommitted change of a dirty checkout, saved in the run folder.
CODE_DIFF = "code.diff"
#: The training run's provenance, copied into every export it writes.
EXPORT_PROVENANCE = "provenance.json"
#: Distributions whose versions can change a number (those installed are recorded).
PACKAGES = (
    "resireg", "torch", "torchvision", "lightning", "hydra-core", "omegaconf", "timm",
    "open_clip_torch", "transformers", "tokenizers", "numpy", "scipy", "scikit-learn",
    "safetensors", "datasets", "huggingface_hub", "pillow", "torchmetrics", "einops",
    "segment-anything", "optuna", "mlflow", "wandb", "rosbags", "rerun-sdk", "onnx",
    "onnxruntime",
)  # fmt: skip
#: CPU seconds this process (and its children) had used when each run folder's run started.
_CPU_AT_START: dict[str, float] = {}


def _now() -> str:
    return _dt.datetime.now(_dt.timezone.utc).isoformat(timespec="milliseconds")


# --------------------------------------------------------------------------------- code
def _git(root: Path, *args: str) -> subprocess.CompletedProcess[str]:
    return subprocess.run(["git", "-C", str(root), *args], capture_output=True, text=True,
                          timeout=60, check=False)  # fmt: skip


def _checkout_root(package_dir: Path) -> Path | None:
    """The git checkout whose ``src/`` holds ``package_dir``, else ``None`` (an installed
    package, or a virtual environment that merely lives inside some other repository)."""
    try:
        top = _git(package_dir, "rev-parse", "--show-toplevel")
    except (OSError, subprocess.SubprocessError):
        return None  # no git on this machine
    if top.returncode != 0:
        return None
    root = Path(top.stdout.strip()).resolve()
    return root if (root / "src" / package_dir.name).resolve() == package_dir.resolve() else None


def provenance_settings(cfg: Any = None) -> dict[str, Any]:
    """The ``provenance`` block of ``cfg`` over ``conf/provenance/default.yaml``'s values (all
    of them when ``cfg`` has none: a config composed without it, a call from Python)."""
    from resireg.specs.table import compose_conf, conf_dir

    settings = {k: v for k, (v, _) in compose_conf(conf_dir() / "provenance", "default").items()}
    block = cfg.get("provenance") if isinstance(cfg, Mapping) or hasattr(cfg, "get") else None
    if block:
        from omegaconf import OmegaConf

        settings.update(OmegaConf.to_container(block, resolve=True) if OmegaConf.is_config(block)
                        else block)  # fmt: skip
    return settings


def _sha256(path: Path) -> str:
    h = hashlib.sha256()
    with open(path, "rb") as f:
        for block in iter(lambda: f.read(1 << 20), b""):
            h.update(block)
    return h.hexdigest()


def _binary(path: Path) -> bool:
    """git's own test: a NUL byte in the first 8000 bytes."""
    with open(path, "rb") as f:
        return b"\0" in f.read(8000)


def _identity(root: Path, name: str, hash_max: int) -> dict[str, Any]:
    """What a file of the checkout is, without its content: ``{"path", "size", "sha256"}``
    (``sha256`` null above ``hash_max`` bytes), ``{"path", "link"}`` for a symbolic link (its
    target as written, never followed: it may dangle), ``{"path", "error"}`` if unreadable."""
    path = root / name
    try:
        st = path.lstat()
        if stat.S_ISLNK(st.st_mode):
            return {"path": name, "link": os.readlink(path)}
        if not stat.S_ISREG(st.st_mode):
            return {"path": name, "kind": "not a regular file"}
        digest = _sha256(path) if st.st_size <= hash_max else None
        return {"path": name, "size": st.st_size, "sha256": digest}
    except OSError as err:
        return {"path": name, "error": err.strerror or str(err)}


def _tracked_changes(root: Path) -> list[tuple[str, bool, str]]:
    """``(path, binary, patch)`` per tracked file that differs from ``HEAD``: ``git diff HEAD``
    as text (a binary file's patch is git's one line), split at each file's ``diff --git``."""
    plain = ("-c", "core.quotepath=off", "diff", "HEAD", "--no-color", "--no-ext-diff",
             "--no-textconv")  # fmt: skip
    text = _git(root, *plain).stdout
    stats = _git(root, *plain, "--numstat", "-z").stdout.split("\0")
    entries: list[tuple[str, bool]] = []
    i = 0
    while i < len(stats) - 1:
        added, _, rest = stats[i].partition("\t")
        _, _, path = rest.partition("\t")
        if path:  # one path
            entries.append((path, added == "-"))
            i += 1
        else:  # a rename: "added\tdeleted\t", then the old and the new path
            entries.append((stats[i + 2], added == "-"))
            i += 3
    chunks = [c for c in re.split(r"(?m)^(?=diff --git )", text) if c]
    if len(chunks) != len(entries):  # not split as expected: one piece, never lost
        return [("(tracked changes)", False, text)] if text else []
    return [(path, binary, chunk) for (path, binary), chunk in zip(entries, chunks, strict=True)]


def _changes_digest(changes: list[dict[str, Any]]) -> str:
    """SHA-256 over the tracked changes (each file's path, size and content digest, sorted;
    a deleted file by its path): with the commit, it names the tracked code exactly. Content,
    not ``git diff``'s text: a binary change is one line there."""
    lines = sorted(f"{c['path']}\t{c.get('size')}\t{c.get('sha256')}\n" for c in changes)
    return hashlib.sha256("".join(lines).encode()).hexdigest()


def _write_private(path: Path, text: str) -> Path:
    """``path`` written atomically and created 0600 (it can hold uncommitted edits)."""
    from resireg.integrity import atomic_write

    def write(tmp: Path) -> None:
        fd = os.open(tmp, os.O_WRONLY | os.O_CREAT | os.O_EXCL, 0o600)
        with os.fdopen(fd, "w") as f:
            f.write(text)

    return atomic_write(path, write, what="uncommitted change", mode=0o600)


def code_provenance(
    out: Path | None,
    package_dir: Path | None = None,
    settings: Mapping[str, Any] | None = None,
) -> dict[str, Any]:
    """``{"version", "git": {...} | None}`` of the code that runs (``package_dir``: this
    package's folder; ``settings``: the ``provenance`` block, :func:`provenance_settings`).

    From a git checkout, ``git`` holds the commit, branch, a dirty flag and:

    - ``untracked``: every untracked file that git does not ignore, by name, size and SHA-256
      (a symbolic link by its target, never followed), never by content: the first
      ``untracked_max_files``, their count in ``untracked_files``;
    - ``diff``: ``code.diff`` (written 0600 into ``out``) when some change was inlined:
      tracked files' text changes, and the content of untracked files matching
      ``untracked_content`` (an explicit opt-in; never a binary file or one whose name looks
      secret, :func:`resireg.secrets.looks_secret`), at most ``diff_max_bytes`` in
      all, so ``git apply code.diff`` on the commit gives the code that ran;
    - ``left_out``: each change not inlined, by path, size, SHA-256 and reason (binary, a
      secret-looking name, over ``diff_max_bytes``), and ``diff_bytes``;
    - ``changes``: every tracked file that differs from the commit, by path, size and SHA-256
      of its content now (a deleted one by path and error), and ``diff_sha256``, one digest
      over them: what ``resireg-runs rerun`` compares.

    Nothing here fails a run: a git error is recorded as ``git.error``."""
    try:
        version = md.version("resireg")
    except md.PackageNotFoundError:
        import resireg

        version = resireg.__version__
    package_dir = package_dir or Path(__file__).resolve().parents[2]  # resireg_train/
    root = _checkout_root(package_dir)
    if root is None:
        return {"version": version, "git": None}
    try:
        return {"version": version, "git": _git_record(root, out, settings or
                                                       provenance_settings())}  # fmt: skip
    except Exception as err:  # provenance never fails a run: say what could not be read
        return {"version": version, "git": {"root": str(root),
                                            "error": f"{type(err).__name__}: {err}"}}  # fmt: skip


def _git_record(root: Path, out: Path | None, settings: Mapping[str, Any]) -> dict[str, Any]:
    from resireg.secrets import looks_secret

    cap = int(settings["diff_max_bytes"])
    hash_max = int(settings["hash_max_bytes"])
    patterns = [str(p) for p in settings.get("untracked_content") or []]
    commit = _git(root, "rev-parse", "HEAD").stdout.strip() or None
    branch = _git(root, "rev-parse", "--abbrev-ref", "HEAD").stdout.strip() or None
    tracked = _tracked_changes(root)
    names = [n for n in _git(root, "ls-files", "--others", "--exclude-standard", "-z")
             .stdout.split("\0") if n]  # fmt: skip
    listed = [_identity(root, n, hash_max) for n in names[: int(settings["untracked_max_files"])]]
    inlined: list[str] = []
    left_out: list[dict[str, Any]] = []
    used = 0

    def leave(name: str, reason: str) -> None:
        known = next((e for e in listed if e["path"] == name), None) or _identity(
            root, name, hash_max)  # fmt: skip
        left_out.append({**known, "reason": reason})

    def take(name: str, patch: str, binary: bool) -> None:
        nonlocal used
        size = len(patch.encode())
        if binary:
            leave(name, "binary")
        elif looks_secret(name):
            leave(name, "a secret-looking name: never inlined")
        elif used + size > cap:
            leave(name, f"over provenance.diff_max_bytes={cap}")
        else:
            inlined.append(patch)
            used += size

    for name, binary, patch in tracked:
        take(name, patch, binary)
    for entry in listed:
        name = entry["path"]
        if not any(fnmatch.fnmatch(name, p) for p in patterns) or "size" not in entry:
            continue  # not opted in, or a link / not a regular file: recorded by name only
        if looks_secret(name):
            leave(name, "a secret-looking name: never inlined")
            continue
        if _binary(root / name):
            leave(name, "binary")
            continue
        # its diff against /dev/null: `git apply` creates it (exit code 1: they differ)
        take(name, _git(root, "diff", "--no-index", "--", os.devnull, name).stdout, False)
    changes = [_identity(root, name, hash_max) for name, _, _ in tracked]
    record: dict[str, Any] = {"commit": commit, "branch": branch,
                              "dirty": bool(tracked or names), "diff": None,
                              "root": str(root), "changes": changes,
                              "diff_sha256": _changes_digest(changes),
                              "untracked": listed}  # fmt: skip
    if len(names) > len(listed):
        record["untracked_files"] = len(names)
    if left_out:
        record["left_out"] = left_out
    if inlined and out is not None:
        _write_private(Path(out) / CODE_DIFF, "".join(inlined))
        record["diff"] = CODE_DIFF
        record["diff_bytes"] = used
    return record


# -------------------------------------------------------------------------- environment
def package_versions(names: tuple[str, ...] = PACKAGES) -> dict[str, str]:
    """``{distribution: version}`` of the installed ones among ``names``."""
    versions = {}
    for name in names:
        try:
            versions[name] = md.version(name)
        except md.PackageNotFoundError:
            continue
    return versions


def config_digest(cfg: Any) -> str:
    """SHA-256 of the resolved config as YAML (unresolvable values kept as written)."""
    from omegaconf import OmegaConf

    try:
        text = OmegaConf.to_yaml(cfg, resolve=True, sort_keys=True)
    except Exception:  # a value that resolves only inside Hydra's runtime, or a missing ???
        text = OmegaConf.to_yaml(cfg, resolve=False, sort_keys=True)
    return hashlib.sha256(text.encode()).hexdigest()


def _cpu_model() -> str:
    try:
        for line in Path("/proc/cpuinfo").read_text().splitlines():
            if line.lower().startswith("model name"):
                return line.split(":", 1)[1].strip()
    except OSError:
        pass
    return platform.processor() or platform.machine()


def machine_provenance() -> dict[str, Any]:
    """Host, CPU model and cores, memory (GiB), PID, OS and the world size (``WORLD_SIZE``,
    set by Lightning's and torchrun's launchers; 1 otherwise)."""
    try:
        memory = os.sysconf("SC_PAGE_SIZE") * os.sysconf("SC_PHYS_PAGES") / 2**30
    except (ValueError, OSError, AttributeError):
        memory = None
    return {
        "host": socket.gethostname(),
        "cpu": _cpu_model(),
        "cores": os.cpu_count(),
        "memory_gib": round(memory, 1) if memory else None,
        "pid": os.getpid(),
        "os": platform.platform(),
        "world_size": int(os.environ.get("WORLD_SIZE", "1")),
    }


def _seeds(container: Any, prefix: str = "") -> dict[str, Any]:
    found = {}
    if isinstance(container, Mapping):
        for key, value in container.items():
            path = f"{prefix}{key}"
            if str(key) == "seed" or str(key).endswith("_seed"):
                if isinstance(value, (int, float, str)) or value is None:
                    found[path] = value
            found.update(_seeds(value, f"{path}."))
    return found


# ---------------------------------------------------------------------------------- data
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


def _datasets(cfg: Mapping[str, Any]) -> dict[str, Any]:
    """Every dataset entry a run reads: ``dataset`` (resireg-eval), ``source``
    (resireg-map), ``data.sources.*`` (training captions) and the validation sets of the
    ReSiReg callback (``callbacks.resireg_eval.datasets.*``)."""
    found: dict[str, Any] = {}
    for key in ("dataset", "source"):
        if isinstance(cfg.get(key), Mapping):
            found[key] = cfg[key]
    sources = (
        (cfg.get("data") or {}).get("sources") if isinstance(cfg.get("data"), Mapping) else None
    )
    for name, entry in (sources or {}).items():
        if isinstance(entry, Mapping):
            found[f"data.sources.{name}"] = entry
    callbacks = cfg.get("callbacks") or {}
    evaluation = callbacks.get("resireg_eval") if isinstance(callbacks, Mapping) else None
    for name, entry in ((evaluation or {}).get("datasets") or {}).items():
        if isinstance(entry, Mapping):
            found[f"callbacks.resireg_eval.datasets.{name}"] = entry
    return found


# -------------------------------------------------------------------------------- models
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


def _models(cfg: Mapping[str, Any]) -> dict[str, Any]:
    from resireg.integrity import sha256_file

    models: dict[str, Any] = {}
    if cfg.get("model_path"):
        models["export"] = export_identity(str(cfg["model_path"]))
    model = cfg.get("model")
    init_from = model.get("init_from") if isinstance(model, Mapping) else None
    if init_from:
        path = Path(str(init_from)).expanduser()
        models["init_from"] = {"path": str(path.resolve()),
                               "sha256": sha256_file(path) if path.is_file() else None}  # fmt: skip
    ckpt_path = cfg.get("ckpt_path")
    if ckpt_path not in (None, "last"):  # a checkpoint file another run wrote
        path = Path(str(ckpt_path)).expanduser()
        models["ckpt_path"] = {"path": str(path.resolve()),
                               "sha256": sha256_file(path) if path.is_file() else None}  # fmt: skip
    encoder = cfg.get("encoder")
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


# ------------------------------------------------------------------------------- records
def _cli() -> str | None:
    """``resireg-train`` / ``resireg-eval`` / ``resireg-map``: the Hydra main running."""
    from hydra.core.hydra_config import HydraConfig

    if not HydraConfig.initialized():
        return None
    return f"resireg-{HydraConfig.get().job.config_name}"


def _guarded(what: Callable[[], Any]) -> Any:
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
            key: _guarded(lambda e=entry: data_identity(e))
            for key, entry in _datasets(plain).items()
        },  # fmt: skip
        "models": _guarded(lambda: _models(plain)),
    }


def start_provenance(cfg: Any, out: Path, previous: Mapping[str, Any] | None = None) -> dict:
    """The provenance block written when a run starts (module docstring). ``previous``: the
    block of the run this one resumes (its ``run_id`` is kept). The command line is recorded
    with every URL's password masked; environment variables are never recorded."""
    from omegaconf import OmegaConf

    try:
        plain = OmegaConf.to_container(cfg, resolve=True)
    except Exception:
        plain = OmegaConf.to_container(cfg, resolve=False)
    run_id = (previous or {}).get("run_id") or uuid.uuid4().hex[:12]
    _CPU_AT_START[str(Path(out).resolve())] = _cpu_seconds()
    return {
        "run_id": run_id,
        "cli": _cli(),
        "code": _guarded(lambda: code_provenance(out, settings=provenance_settings(cfg))),
        "environment": {
            "python": platform.python_version(),
            # every URL's password masked (a search's storage, a tracking URI)
            "command": mask_text(shlex.join([Path(sys.argv[0]).name, *sys.argv[1:]])),
            "config_sha256": config_digest(cfg),
            "packages": package_versions(),
        },
        "machine": machine_provenance(),
        "time": {"start": _now(), "end": None, "wall_seconds": None},
        "seeds": _seeds(plain),
        **input_provenance(plain),
    }


def _gpus() -> tuple[list[dict[str, Any]], dict[str, Any]]:
    torch = sys.modules.get("torch")  # only if the run imported it: no import here
    if torch is None:
        return [], {}
    versions = {"cuda": torch.version.cuda}
    if torch.backends.cudnn.is_available():
        versions["cudnn"] = torch.backends.cudnn.version()
    if not torch.cuda.is_initialized():
        return [], versions
    gpus = []
    for i in range(torch.cuda.device_count()):
        props = torch.cuda.get_device_properties(i)
        gpus.append({"name": props.name, "memory_gib": round(props.total_memory / 2**30, 1)})
    return gpus, versions


def _cpu_seconds() -> float:
    import resource

    usage = [resource.getrusage(who) for who in (resource.RUSAGE_SELF, resource.RUSAGE_CHILDREN)]
    return sum(u.ru_utime + u.ru_stime for u in usage)


def finish_provenance(block: Mapping[str, Any], out: Path | None = None) -> dict[str, Any]:
    """``block`` completed at the run's end: end time, wall seconds, CPU-hours (``getrusage``
    of this process and its children since the run in ``out`` started), GPU-hours (wall x the
    world size, where CUDA ran), torch's CUDA / cuDNN versions and the GPUs."""
    done = json.loads(json.dumps(block))  # a copy
    clock = done.setdefault("time", {})
    end = _dt.datetime.now(_dt.timezone.utc)
    wall = (end - _dt.datetime.fromisoformat(clock["start"])).total_seconds() if clock.get(
        "start") else None  # fmt: skip
    start_cpu = _CPU_AT_START.get(str(Path(out).resolve()), 0.0) if out is not None else 0.0
    cpu_seconds = _cpu_seconds() - start_cpu
    gpus, versions = _gpus()
    world = int((done.get("machine") or {}).get("world_size") or 1)
    clock.update(
        end=end.isoformat(timespec="milliseconds"),
        wall_seconds=round(wall, 3) if wall is not None else None,
        cpu_hours=round(cpu_seconds / 3600, 6),
        gpu_hours=round(wall * world / 3600, 6) if gpus and wall is not None else None,
    )
    done.setdefault("machine", {})["gpus"] = gpus
    torch = sys.modules.get("torch")  # only if the run imported it
    if torch is not None:
        done["machine"]["torch_threads"] = torch.get_num_threads()
    done.setdefault("environment", {}).update({f"torch_{k}": v for k, v in versions.items()})
    return done


def write_export_provenance(export: Path, out: Path, block: Mapping[str, Any]) -> Path:
    """``<export>/provenance.json``: the training run that wrote the export (its folder, its
    provenance block) and the SHA-256 of its last checkpoint, so an evaluation of the export
    can name the run, the code and the data that made it."""
    from resireg.integrity import atomic_write, sha256_file

    last = Path(out) / "checkpoints" / "last.ckpt"
    record = {
        "run_dir": str(Path(out).resolve()),
        "run_id": block.get("run_id"),
        "checkpoint": {
            "path": str(last.resolve()),
            "sha256": sha256_file(last) if last.is_file() else None,
        },  # fmt: skip
        "provenance": {k: v for k, v in block.items() if k != "time"},
    }
    return atomic_write(export / EXPORT_PROVENANCE, json.dumps(record, indent=2),
                        what="export provenance")  # fmt: skip
