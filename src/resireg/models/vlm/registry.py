"""Exports in MLflow's model registry: ``models:/NAME@ALIAS`` (``models:/resireg-vlm@champion``)
or ``models:/NAME/VERSION`` wherever an export folder is taken (``model_path=`` of
``resireg-eval`` / ``resireg-map``, ``resireg-segment --model-path``, ``resireg-export onnx``,
the ROS 2 node's ``model_path``, :meth:`ResiregVLM.from_pretrained`).

``resireg-runs register <export> --name NAME [--alias champion]`` puts an export there
(``resireg_train.runs.registry``): the export's files, its model card and its lineage as
artifacts and tags of one MLflow run, and a model version whose ``resireg.digests`` tag holds
each file's SHA-256.

:func:`registry_export` finds the version (an alias is resolved to its version on each call),
downloads its files once into the cache folder (:func:`cache_root`:
``$RESIREG_REGISTRY_CACHE``, else ``$XDG_CACHE_HOME/resireg/registry``, else
``~/.cache/resireg/registry``; one folder per model and version,
``<cache>/<NAME>/<VERSION>/``, written under a temporary name and renamed when complete) and
verifies it before every use: each file against the version's recorded digests and the
tensor files against the export's own ``config.json`` digests (:func:`resireg.integrity.
verify_digests`). A cached copy that no longer matches is downloaded again; a download that
does not match is an :class:`~resireg.integrity.IntegrityError` naming the file.

The registry is the one MLflow's own settings name (``MLFLOW_REGISTRY_URI``, else
``MLFLOW_TRACKING_URI``; credentials in ``MLFLOW_TRACKING_USERNAME`` /
``MLFLOW_TRACKING_PASSWORD``), else MLflow's default (``sqlite:///mlflow.db`` in the working
folder). Before MLflow is asked anything, a registry server must accept a connection within
``tracker.mlflow.check_timeout`` seconds (:func:`check_registry`: the trackers' check,
:func:`resireg.network.reach`), not after MLflow's minutes of retries. MLflow is imported only
here and only for a ``models:/`` source (the ``tracking`` extra); without it the error names
the extra.
"""

from __future__ import annotations

import json
import os
import shutil
import uuid
from dataclasses import dataclass
from pathlib import Path
from typing import Any
from urllib.parse import urlsplit

from resireg.errors import ResiregError
from resireg.integrity import IntegrityError, verify_digests
from resireg.models.vlm.folder import read_config
from resireg.network import reach
from resireg.secrets import mask_url
from resireg.specs.exports import registry_model

__all__ = [
    "CACHE_ENV",
    "DIGESTS_TAG",
    "RegistryError",
    "RegistryExport",
    "cache_root",
    "check_registry",
    "registry_export",
    "registry_timeout",
    "resolve",
]

#: The environment variable naming the cache folder.
CACHE_ENV = "RESIREG_REGISTRY_CACHE"
#: The model version tag holding ``{file: SHA-256}`` of every file registered.
DIGESTS_TAG = "resireg.digests"
_WHAT = "registered ResiregVLM export"


class RegistryError(ResiregError, FileNotFoundError):
    """An export in MLflow's model registry that cannot be had: MLflow missing, no such model,
    version or alias, a registry that cannot be reached (the message names the URI and the
    registry, its password masked)."""


@dataclass(frozen=True)
class RegistryExport:
    """One registered export, resolved: its local copy and where it came from."""

    uri: str
    name: str
    version: str
    folder: Path
    run_id: str | None
    source: str
    registry: str


def cache_root() -> Path:
    """The folder of downloaded registered exports (module docstring)."""
    if os.environ.get(CACHE_ENV):
        return Path(os.environ[CACHE_ENV]).expanduser()
    base = os.environ.get("XDG_CACHE_HOME") or Path.home() / ".cache"
    return Path(base) / "resireg" / "registry"


def _uris() -> tuple[str, str]:
    """MLflow's ``(tracking URI, registry URI)`` from its own settings."""
    import mlflow

    tracking = str(mlflow.get_tracking_uri())
    return tracking, str(mlflow.get_registry_uri() or tracking)


def registry_timeout(cfg: Any = None) -> float:
    """How long to wait for the model registry's server: ``tracker.mlflow.check_timeout``
    (``cfg``'s when it has one, else ``conf/tracker/mlflow.yaml``'s): the one setting of how long
    resireg waits for an MLflow server, its tracker's and its registry's."""
    from resireg.specs.table import compose_conf, conf_dir

    own = None
    if cfg is not None and hasattr(cfg, "get"):
        own = ((cfg.get("tracker") or {}).get("mlflow") or {}).get("check_timeout")
    if own is None:
        own = compose_conf(conf_dir() / "tracker", "mlflow")["mlflow"][0]["check_timeout"]
    return float(own)


def check_registry(uri: str | None = None, timeout: float | None = None, what: str = "") -> None:
    """Refuse at once a model registry that cannot be reached: the server of ``uri`` (else the
    one MLflow's settings name: ``MLFLOW_REGISTRY_URI``, ``MLFLOW_TRACKING_URI``) must accept a
    connection within ``timeout`` seconds (:func:`registry_timeout`), the check the trackers
    make (:func:`resireg.network.reach`; a local store: its folder writable), not MLflow's
    minutes of retries. A :class:`RegistryError` (one line) names it, its password masked;
    ``what``: whose registry (``model_path='models:/...'``)."""
    if uri is None:
        uri = _uris()[1]
    timeout = registry_timeout() if timeout is None else float(timeout)
    if (why := reach(uri, timeout)) is not None:
        raise RegistryError(
            f"{what + ': ' if what else ''}cannot reach the model registry {mask_url(uri)} "
            f"({why}); start it or set MLFLOW_TRACKING_URI (MLFLOW_REGISTRY_URI) to the one "
            f"that holds the model (the wait, {timeout:g} s: tracker.mlflow.check_timeout)"
        )


def _safe(name: str) -> str:
    """A registered model's name as one folder name."""
    return "".join(c if c.isalnum() or c in "-_." else "_" for c in name).lstrip(".") or "_"


def _verify(folder: Path, recorded: dict[str, str]) -> None:
    """The registered files against the digests recorded at registration, then the tensor
    files against the export's own ``config.json`` (IntegrityError naming the file)."""
    if recorded:
        verify_digests(folder, recorded, _WHAT)
    read_config(folder)


def resolve(uri: str, timeout: float | None = None) -> RegistryExport:
    """The registered export of ``uri`` (``models:/NAME@ALIAS`` or ``models:/NAME/VERSION``),
    downloaded once into :func:`cache_root` and verified (module docstring); its registry's
    server checked first (:func:`check_registry`, ``timeout`` seconds, default
    :func:`registry_timeout`)."""
    parsed = registry_model(uri)
    if parsed is None:
        raise ValueError(f"{uri!r} is not a model registry URI (models:/NAME@ALIAS)")
    name, alias, version = parsed
    try:
        from mlflow import MlflowClient
        from mlflow.exceptions import MlflowException
    except ImportError:
        raise RegistryError(f"{uri!r} is in MLflow's model registry, and MLflow is not "
                            "installed: pip install 'resireg[tracking]'") from None  # fmt: skip
    tracking, registry = _uris()
    where = f"registry {mask_url(registry)} (MLFLOW_TRACKING_URI / MLFLOW_REGISTRY_URI)"
    if registry.startswith("sqlite:///") and not Path(registry[len("sqlite:///") :]).is_file():
        raise RegistryError(f"{uri!r}: no {where}: set MLFLOW_TRACKING_URI to the store the "
                            "export was registered in")  # fmt: skip
    for server in dict.fromkeys((registry, tracking)):  # the files come from the tracking one
        if urlsplit(server).hostname:  # a local store is only read here: nothing made
            check_registry(server, timeout, what=repr(uri))
    client = MlflowClient(tracking_uri=tracking, registry_uri=registry)
    try:
        found = (client.get_model_version_by_alias(name, alias) if alias
                 else client.get_model_version(name, version))  # fmt: skip
    except MlflowException as err:
        raise RegistryError(f"{uri!r}: not in the {where}: {err.message}") from None
    except OSError as err:  # the server cannot be reached
        raise RegistryError(f"{uri!r}: cannot reach the {where}: {err}") from None
    recorded = json.loads((found.tags or {}).get(DIGESTS_TAG) or "{}")
    folder = cache_root() / _safe(name) / str(found.version)
    if folder.is_dir():
        try:
            _verify(folder, recorded)
        except (IntegrityError, FileNotFoundError) as err:
            import warnings

            warnings.warn(f"{folder}: the cached copy of {uri} no longer matches ({err}); "
                          "downloading it again", stacklevel=2)  # fmt: skip
            shutil.rmtree(folder)
    if not folder.is_dir():
        _download(name, str(found.version), folder, recorded, uri, where)
    return RegistryExport(uri=uri, name=name, version=str(found.version), folder=folder,
                          run_id=found.run_id, source=str(found.source),
                          registry=mask_url(registry))  # fmt: skip


def _download(name: str, version: str, folder: Path, recorded: dict[str, str], uri: str,
              where: str) -> None:  # fmt: skip
    """The version's files into ``folder``: downloaded into a temporary folder beside it,
    verified, then renamed (another process that finished first wins; its copy is used)."""
    from mlflow.artifacts import download_artifacts
    from mlflow.exceptions import MlflowException

    folder.parent.mkdir(parents=True, exist_ok=True)
    tmp = folder.with_name(f".{folder.name}.{os.getpid()}.{uuid.uuid4().hex[:8]}.tmp")
    try:
        tmp.mkdir()
        try:
            tracking, registry = _uris()
            got = Path(download_artifacts(artifact_uri=f"models:/{name}/{version}",
                                          dst_path=str(tmp), tracking_uri=tracking,
                                          registry_uri=registry))  # fmt: skip
        except MlflowException as err:
            raise RegistryError(f"{uri!r}: version {version}'s files could not be downloaded "
                                f"from the {where}: {err.message}") from None  # fmt: skip
        if got != tmp and got.is_dir():  # the files came in a subfolder: lift them up
            for path in list(got.iterdir()):
                os.replace(path, tmp / path.name)
            got.rmdir()
        _verify(tmp, recorded)
        try:
            os.replace(tmp, folder)
        except OSError:
            if not (folder / "config.json").is_file():
                raise
    finally:
        shutil.rmtree(tmp, ignore_errors=True)


def registry_export(uri: str, timeout: float | None = None) -> Path:
    """The verified local folder of the registered export ``uri`` (:func:`resolve`)."""
    return resolve(uri, timeout).folder
