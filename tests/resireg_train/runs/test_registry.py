"""The model registry (issue 47, item 4): ``resireg-runs register`` puts an export (its files,
card and lineage) into a real `mlflow server` the test starts, and ``resireg-eval
model_path=models:/NAME@champion`` scores the same as the export folder; the copy is
downloaded once, checked against the recorded digests, and a tampered registry copy is
refused."""

from __future__ import annotations

import hashlib
import json
import os
import shutil
from pathlib import Path

import pytest

from helpers.run import evaluate_export, run
from resireg.integrity import IntegrityError
from resireg.specs.exports import export_source_problem, registry_model
from resireg_train.cli.runs import main as runs_main

pytest.importorskip("mlflow")


def _sha256(path: Path) -> str:
    return hashlib.sha256(path.read_bytes()).hexdigest()


def _export_with_lineage(tiny_export: Path, root: Path, commit: str) -> Path:
    """A copy of the tiny export inside a training run folder, with what resireg-train
    writes beside the weights: provenance.json (the training run) and the model card, and
    the training run's record naming its MLflow run."""
    run_dir = root / "train"
    export = run_dir / "export"
    shutil.copytree(tiny_export, export)
    (export / "provenance.json").write_text(json.dumps({
        "run_dir": str(run_dir), "run_id": "ab12cd",
        "checkpoint": {"path": str(run_dir / "checkpoints/last.ckpt"), "sha256": "f" * 64},
        "provenance": {"run_id": "ab12cd", "code": {"git": {"commit": commit}},
                       "data": {"data.sources.synthetic": {"kind": "generated"}}},
    }))  # fmt: skip
    (export / "README.md").write_text("---\nlicense: apache-2.0\n---\n# tiny-vlm\n\nThe card.\n")
    (run_dir / "results.json").write_text(json.dumps({
        "status": "completed", "tracking": {"mlflow_run_id": "0123456789abcdef"},
        "provenance": {"run_id": "ab12cd"}}))  # fmt: skip
    return export


def test_the_model_uri_forms_are_checked_before_anything_loads():
    assert registry_model("models:/resireg-vlm@champion") == ("resireg-vlm", "champion", None)
    assert registry_model("models:/resireg-vlm/3") == ("resireg-vlm", None, "3")
    assert registry_model("owner/name") is None
    for bad in ("models:/resireg-vlm", "models:/resireg-vlm/latest", "models:/a@b/c"):
        assert "expected models:/NAME@ALIAS" in export_source_problem(bad)
    assert export_source_problem("models:/resireg-vlm@champion") is None  # mlflow installed


@pytest.mark.slow
def test_register_then_evaluate_by_alias(tmp_path, tiny_export, mlflow_server, monkeypatch):
    from mlflow import MlflowClient

    uri, artifacts = mlflow_server.uri, mlflow_server.store / "artifacts"
    export = _export_with_lineage(tiny_export, tmp_path, commit="c0ffee" * 6 + "abcd")
    runs_main(["register", str(export), "--name", "tiny-vlm", "--alias", "champion",
               "--tracking-uri", uri])  # fmt: skip

    # the registry holds the files, the card, the lineage and every file's digest
    client = MlflowClient(tracking_uri=uri, registry_uri=uri)
    version = client.get_model_version_by_alias("tiny-vlm", "champion")
    assert version.version == "1"
    files = sorted(p.name for p in export.iterdir())
    assert json.loads(version.tags["resireg.digests"]) == {n: _sha256(export / n) for n in files}
    assert version.tags["resireg.training.run_id"] == "ab12cd"
    assert version.tags["resireg.training.mlflow_run_id"] == "0123456789abcdef"
    assert version.description == (export / "README.md").read_text()
    registration = client.get_run(version.run_id)
    assert registration.data.tags["provenance.code.git.commit"] == "c0ffee" * 6 + "abcd"
    assert (
        sorted(Path(a.path).name for a in client.list_artifacts(version.run_id, "export")) == files
    )

    # resireg-eval model_path=models:/tiny-vlm@champion scores as the export folder does
    cache = tmp_path / "cache"
    env = {**os.environ, "MLFLOW_TRACKING_URI": uri, "RESIREG_REGISTRY_CACHE": str(cache)}
    out = tmp_path / "eval-registry"
    common = ["dataset=synthetic", "dataset.size=4", "num_workers=0", "full.n_prototypes=12",
              "variants=[bb,full]"]  # fmt: skip
    run("resireg-eval", "model_path=models:/tiny-vlm@champion", *common, f"hydra.run.dir={out}",
        env=env, threads=1)  # fmt: skip
    by_alias = json.loads((out / "results.json").read_text())
    direct = evaluate_export(
        export, tmp_path / "eval-folder", "dataset.size=4", "variants=[bb,full]"
    )
    assert by_alias["status"] == "completed"
    assert by_alias["final"] == pytest.approx(direct, rel=1e-6)
    copy = cache / "tiny-vlm" / "1"
    assert {n: _sha256(copy / n) for n in files} == {n: _sha256(export / n) for n in files}
    model = by_alias["provenance"]["models"]["export"]
    assert model["uri"] == "models:/tiny-vlm@champion" and model["path"] == str(copy.resolve())
    assert model["registry"]["version"] == "1" and model["registry"]["run_id"] == version.run_id
    assert model["training_run"]["run_id"] == "ab12cd"

    # downloaded once: a second use reads the cache (no download), verified
    from mlflow import artifacts as mlflow_artifacts

    from resireg.models import ResiregVLM, build_encoder
    from resireg.models.vlm.registry import resolve

    monkeypatch.setenv("MLFLOW_TRACKING_URI", uri)
    monkeypatch.setenv("RESIREG_REGISTRY_CACHE", str(cache))

    def no_download(*args, **kwargs):
        raise AssertionError("downloaded again")

    with monkeypatch.context() as patched:
        patched.setattr(mlflow_artifacts, "download_artifacts", no_download)
        assert resolve("models:/tiny-vlm/1").folder == copy
        loaded = ResiregVLM.from_pretrained("models:/tiny-vlm@champion")
        # what resireg-map, the ROS 2 node and resireg-segment build from model_path
        built = build_encoder(kind="resireg_vlm", path="models:/tiny-vlm/1")
        assert built.export_source == "models:/tiny-vlm/1"
    reference = ResiregVLM.from_pretrained(export)
    for (name, a), (_, b) in zip(loaded.state_dict().items(), reference.state_dict().items(),
                                 strict=True):  # fmt: skip
        assert a.equal(b), name
    assert loaded.export_source == "models:/tiny-vlm@champion"

    # a cached copy that changed is downloaded again
    weights = copy / "model.safetensors"
    weights.write_bytes(weights.read_bytes()[:-8] + b"\0" * 8)
    with pytest.warns(UserWarning, match="no longer matches"):
        assert resolve("models:/tiny-vlm@champion").folder == copy
    assert _sha256(weights) == _sha256(export / "model.safetensors")

    # the alias moves to a second version; version 1 stays reachable by number
    second = tmp_path / "second"
    shutil.copytree(export, second)
    reference.head.proj.weight.data.mul_(2)
    reference.save_pretrained(second)
    runs_main(["register", str(second), "--name", "tiny-vlm", "--alias", "champion",
               "--tracking-uri", uri])  # fmt: skip
    assert resolve("models:/tiny-vlm@champion").version == "2"
    assert resolve("models:/tiny-vlm/1").folder == copy

    # a registry copy altered after registration is refused, naming the file
    (stored,) = [p for p in artifacts.rglob("model.safetensors") if "export" in p.parts and
                 _sha256(p) == _sha256(second / "model.safetensors")]  # fmt: skip
    stored.write_bytes(stored.read_bytes()[:-8] + b"\1" * 8)
    shutil.rmtree(cache / "tiny-vlm" / "2")
    with pytest.raises(IntegrityError, match="model.safetensors"):
        resolve("models:/tiny-vlm/2")
    assert not (cache / "tiny-vlm" / "2").exists()  # nothing half-kept


def test_a_missing_model_and_a_missing_store_are_named(tmp_path, monkeypatch):
    from resireg.models.vlm.registry import RegistryError, resolve

    monkeypatch.setenv("MLFLOW_TRACKING_URI", f"sqlite:///{tmp_path}/nothing.db")
    with pytest.raises(RegistryError, match=r"no registry sqlite:///.*nothing\.db"):
        resolve("models:/tiny-vlm@champion")
    assert not (tmp_path / "nothing.db").exists()  # no empty store left behind
    from mlflow import MlflowClient

    store = f"sqlite:///{tmp_path}/store.db"
    MlflowClient(tracking_uri=store).search_experiments()  # an empty store
    monkeypatch.setenv("MLFLOW_TRACKING_URI", store)
    with pytest.raises(RegistryError, match="'models:/tiny-vlm@champion': not in the registry"):
        resolve("models:/tiny-vlm@champion")


def test_register_refuses_what_is_not_an_intact_export(tmp_path, tiny_export, capsys):
    broken = tmp_path / "broken"
    shutil.copytree(tiny_export, broken)
    weights = broken / "model.safetensors"
    weights.write_bytes(weights.read_bytes()[:-4] + b"\0\0\0\0")
    for folder, expected in ((tmp_path / "nope", "no such folder"),
                             (tmp_path, "holds no config.json"),
                             (broken, "model.safetensors")):  # fmt: skip
        with pytest.raises(SystemExit) as code:
            runs_main(["register", str(folder), "--name", "x",
                       "--tracking-uri", f"sqlite:///{tmp_path}/r.db"])  # fmt: skip
        assert code.value.code == 2
        err = capsys.readouterr().err
        assert expected in err and err.count("\n") == 1, err
    with pytest.raises(SystemExit):
        runs_main(["register", str(tiny_export), "--name", "x",
                   "--tracking-uri", "http://user:secret@127.0.0.1:9/"])  # fmt: skip
    err = capsys.readouterr().err
    assert "MLFLOW_TRACKING_PASSWORD" in err and "secret" not in err
