"""``resireg-runs register <export> --name NAME [--alias champion]``: an export into MLflow's
model registry, loadable afterwards as ``model_path=models:/NAME@champion`` (or
``models:/NAME/VERSION``) wherever an export folder is taken (:mod:`resireg.models.vlm.registry`
downloads and verifies it).

One registration is one MLflow run, ``register <NAME>``, in the experiment ``--experiment``
(``resireg``), holding:

- the export's files as artifacts under ``export/`` (weights, ``config.json`` with its
  digests, the model card ``README.md``, ``provenance.json``, the evaluation settings);
- its lineage as tags: the training run's id, folder, MLflow run (when it was tracked) and
  last checkpoint's SHA-256 (``resireg.training.*``), and the training run's provenance
  (``provenance.*``: commit, packages, data, models), URL passwords masked;

and a model version of ``NAME`` whose source is that run's ``export/`` folder, tagged with
every file's SHA-256 (``resireg.digests``: what a download is verified against) and the
lineage, its description the card's text; ``--alias`` points the alias at it.

The registry is ``--tracking-uri`` when given, else the one MLflow's own settings name
(``MLFLOW_TRACKING_URI``, ``MLFLOW_REGISTRY_URI``; default ``sqlite:///mlflow.db``), the same
rule the loader follows, so ``models:/`` finds what was registered. A new experiment keeps the
registrations' files where the trackers' runs keep theirs
(:func:`resireg_train.record.trackers.mlflow.artifact_location`: beside a SQLite database, in
``mlartifacts/``), never in ``./mlruns`` of the current folder.
"""

from __future__ import annotations

import json
from pathlib import Path
from typing import Any

from resireg.models.vlm.registry import DIGESTS_TAG, check_registry
from resireg.secrets import mask_text, mask_url
from resireg.specs.tree import flatten
from resireg_train.record.provenance.inputs import EXPORT_PROVENANCE
from resireg_train.record.run_record import RecordError, RunRecord

__all__ = ["check_name", "command", "register"]

#: MLflow's limits: a tag value's length, a version description's.
_TAG_MAX, _DESCRIPTION_MAX = 5000, 5000


def _lineage(folder: Path) -> dict[str, str]:
    """The export's lineage as tags: its training run (``provenance.json``) and, where the
    training run's record sits beside the export, the MLflow run it was tracked in."""
    path = folder / EXPORT_PROVENANCE
    if not path.is_file():
        return {}
    try:
        made = json.loads(path.read_text())
    except (OSError, json.JSONDecodeError):
        return {}
    if not isinstance(made, dict):
        return {}
    tags = {"resireg.training.run_id": made.get("run_id"),
            "resireg.training.run_dir": made.get("run_dir"),
            "resireg.training.checkpoint_sha256": (made.get("checkpoint") or {}).get("sha256")}  # fmt: skip
    run_dir = Path(str(made.get("run_dir") or ""))
    if made.get("run_dir") and RunRecord.exists(run_dir):
        try:
            tracking = RunRecord.read(run_dir).get("tracking") or {}
            tags["resireg.training.mlflow_run_id"] = tracking.get("mlflow_run_id")
        except (OSError, RecordError):
            pass
    tags.update(flatten(made.get("provenance") or {}, "provenance"))
    return {k: mask_text(str(v))[:_TAG_MAX] for k, v in tags.items() if v is not None}


def check_name(name: str, alias: str | None = None) -> None:
    """A registered model's name and alias that MLflow keeps and ``models:/NAME@ALIAS`` (or
    ``models:/NAME/VERSION``) reads back as the same model; else a :class:`ValueError`
    naming the option. Checked before anything is written."""
    from mlflow.exceptions import MlflowException
    from mlflow.utils import validation  # the rules MLflow's server applies

    from resireg.specs.exports import registry_model

    if name in (".", "..") or "@" in name:
        raise ValueError(f"--name {name!r}: not a registered model's name ('.', '..' and '@' "
                         "cannot be read back from models:/NAME@ALIAS)")  # fmt: skip
    reserved = getattr(validation, "_validate_model_alias_name_reserved", lambda _: None)
    for option, value, checks in (
        ("--name", name, (validation._validate_model_name,)),
        ("--alias", alias, (validation._validate_model_alias_name, reserved)),
    ):
        if value is None:
            continue
        try:
            for validate in checks:
                validate(value)
        except MlflowException as err:
            raise ValueError(f"{option} {value!r}: {err.message}") from None
    uri = f"models:/{name}@{alias}" if alias else f"models:/{name}/1"
    try:
        parsed = registry_model(uri)
    except ValueError as err:
        raise ValueError(f"--name {name!r}: {err}") from None
    if parsed is None or parsed[0] != name or parsed[1] != alias:
        raise ValueError(f"--name {name!r}: {uri} would not read back as this model")


def register(
    export: str | Path,
    name: str,
    alias: str | None = None,
    tracking_uri: str | None = None,
    experiment: str = "resireg",
) -> dict[str, Any]:
    """Register the export folder ``export`` as a new version of ``name`` (module docstring);
    returns ``{"name", "version", "alias", "uri", "run_id", "registry", "files"}``. A folder
    that is not an intact export is a :class:`ValueError` naming it and why."""
    import mlflow
    from mlflow import MlflowClient
    from mlflow.exceptions import MlflowException
    from mlflow.protos.databricks_pb2 import RESOURCE_ALREADY_EXISTS, ErrorCode

    from resireg.errors import ConfigError
    from resireg.integrity import IntegrityError, sha256_file
    from resireg.models.vlm.model import read_config
    from resireg.specs.exports import export_source_problem
    from resireg_train.record.cards import CARD_FILE
    from resireg_train.record.trackers.base import mlflow_key
    from resireg_train.record.trackers.mlflow import artifact_location

    check_name(name, alias)  # nothing is written for a name the registry refuses
    folder = Path(export).expanduser().resolve()
    if not folder.is_dir():
        raise ValueError(f"{export}: no such folder (an export: <training run>/export)")
    if problem := export_source_problem(folder):
        raise ValueError(problem)
    try:
        read_config(folder)  # the tensor files against the export's own digests
    except (IntegrityError, FileNotFoundError, ValueError) as err:
        raise ValueError(f"{export}: {err}") from None
    files = sorted(p for p in folder.iterdir() if p.is_file() and not p.name.startswith("."))
    digests = {p.name: sha256_file(p) for p in files}
    card = (folder / CARD_FILE).read_text() if (folder / CARD_FILE).is_file() else ""
    lineage = _lineage(folder)

    check_registry(tracking_uri, what=f"--name {name}")
    client = MlflowClient(tracking_uri=tracking_uri, registry_uri=tracking_uri)
    try:
        found = client.get_experiment_by_name(experiment)
        if found is None:  # a new one keeps its files where the trackers' runs would
            try:
                where = artifact_location(str(tracking_uri or mlflow.get_tracking_uri()))
            except ConfigError as err:
                raise ValueError(f"--experiment {experiment!r} is new: {err}; or create it "
                                 "first with its artifact location") from None  # fmt: skip
        experiment_id = (found.experiment_id if found
                         else client.create_experiment(experiment, artifact_location=where))  # fmt: skip
    except MlflowException as err:
        raise ValueError(f"--experiment {experiment!r}: {err.message}") from None
    tags = {"resireg.export": str(folder), "resireg.registered_as": name, **lineage}
    run_id = client.create_run(experiment_id, run_name=f"register {name}",
                               tags={mlflow_key(k)[:250]: v for k, v in tags.items()}).info.run_id  # fmt: skip
    # from here on, a failure leaves the registration's run marked FAILED (and says so)
    try:
        for path in files:
            client.log_artifact(run_id, str(path), artifact_path="export")
        try:
            client.create_registered_model(name, description=f"ResiregVLM exports ({experiment})")
        except MlflowException as err:
            if err.error_code != ErrorCode.Name(RESOURCE_ALREADY_EXISTS):
                raise
        version_tags = {DIGESTS_TAG: json.dumps(digests, sort_keys=True),
                        **{mlflow_key(k)[:250]: v for k, v in lineage.items()
                           if k.startswith("resireg.")}}  # fmt: skip
        version = client.create_model_version(
            name, f"runs:/{run_id}/export", run_id=run_id, tags=version_tags,
            description=card[:_DESCRIPTION_MAX] or None,
        )  # fmt: skip
        if alias:
            client.set_registered_model_alias(name, alias, version.version)
    except BaseException as err:
        client.set_tag(run_id, "resireg.registration", "failed")
        client.set_terminated(run_id, "FAILED")
        if not isinstance(err, Exception):  # Ctrl-C: marked, then as it came
            raise
        why = err.message if isinstance(err, MlflowException) else f"{type(err).__name__}: {err}"
        raise ValueError(f"--name {name}: the registration failed and its MLflow run {run_id} "
                         f"is marked FAILED: {' '.join(str(why).split())}") from None  # fmt: skip
    client.set_terminated(run_id, "FINISHED")
    registry = tracking_uri or mlflow.get_registry_uri()
    return {"name": name, "version": str(version.version), "alias": alias,
            "uri": f"models:/{name}@{alias}" if alias else f"models:/{name}/{version.version}",
            "run_id": run_id, "registry": mask_url(str(registry)),
            "files": sorted(digests)}  # fmt: skip


def command(args: Any) -> None:
    """``resireg-runs register`` (module docstring): prints the version and its URI."""
    from urllib.parse import urlsplit

    if args.tracking_uri and urlsplit(args.tracking_uri).password is not None:
        raise ValueError("--tracking-uri: give the password in MLFLOW_TRACKING_PASSWORD (and "
                         "the user in MLFLOW_TRACKING_USERNAME), not in the URI")  # fmt: skip
    done = register(args.export, args.name, args.alias, args.tracking_uri, args.experiment)
    print(
        f"registered {args.export} as {done['name']} version {done['version']}"
        + (f" (alias {done['alias']})" if done["alias"] else "")
        + f" in {done['registry']}: {len(done['files'])} files, MLflow run {done['run_id']}"
    )
    print(f"load it with model_path={done['uri']}")
