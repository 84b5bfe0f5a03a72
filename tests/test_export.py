"""Exports that prove their content (issue 34 item 4), ONNX graphs checked against torch, the
Hugging Face Hub folder and torch.hub entry (issue 39 items 1-2).

References are independent of the code under test: digests by ``hashlib``, operator sets by
``onnx.load``, the graphs' outputs against the torch model's own ``encode`` /
``encode_text`` and ``ReSiRegLite`` in its other exact form (factorised on the CPU), the model
card parsed by ``huggingface_hub.ModelCard``."""

import copy
import hashlib
import json
import os
import shutil
import subprocess
import sys
import warnings
from pathlib import Path

import numpy as np
import pytest
import torch
import torch.nn.functional as F

from resireg.integrity import IntegrityError, verify_digests
from resireg.method.lite import ReSiRegLite
from resireg.models import ResiregVLM

onnx = pytest.importorskip("onnx")
ort = pytest.importorskip("onnxruntime")
pytest.importorskip("onnxscript")

from resireg.deploy.onnx_export import ImageGraph, export_onnx  # noqa: E402

ROOT = Path(__file__).resolve().parents[1]


def _sha256(path):
    return hashlib.sha256(Path(path).read_bytes()).hexdigest()


def _same_weights(a, b):
    sa, sb = a.state_dict(), b.state_dict()
    return sa.keys() == sb.keys() and all(torch.equal(sa[k], sb[k]) for k in sa)


@pytest.fixture
def export_copy(tiny_export, tmp_path):
    dest = tmp_path / "export"
    shutil.copytree(tiny_export, dest)
    return dest


# ------------------------------------------------------------------ integrity (issue 34 item 4)
def test_export_records_each_files_sha256_and_follows_the_umask(tmp_path):
    from _tiny import TINY_BACKBONE, TINY_HEAD, TINY_TEXT

    old = os.umask(0o022)
    try:
        ResiregVLM.build(TINY_BACKBONE, TINY_HEAD, TINY_TEXT).save_pretrained(tmp_path / "e")
    finally:
        os.umask(old)
    cfg = json.loads((tmp_path / "e" / "config.json").read_text())
    assert cfg["digests"] == {
        name: _sha256(tmp_path / "e" / name) for name in ("frozen.safetensors", "model.safetensors")
    }
    for name in ("config.json", "frozen.safetensors", "model.safetensors"):
        assert (tmp_path / "e" / name).stat().st_mode & 0o777 == 0o644, name  # not 0600
    assert sorted(p.name for p in (tmp_path / "e").iterdir()) == [
        "config.json",
        "frozen.safetensors",
        "model.safetensors",
    ]  # fmt: skip  (no temporary file left)


def _flip_bit(path):
    data = bytearray(path.read_bytes())
    data[len(data) // 2] ^= 0x01
    path.write_bytes(bytes(data))


def _overwrite_4k(path):
    data = bytearray(path.read_bytes())
    mid = len(data) // 2
    data[mid : mid + 4096] = b"\xff" * 4096
    path.write_bytes(bytes(data))


@pytest.mark.parametrize("damage", [_flip_bit, _overwrite_4k], ids=["one-bit", "4KB-of-0xFF"])
@pytest.mark.parametrize("name", ["model.safetensors", "frozen.safetensors"])
def test_a_damaged_tensor_file_is_an_error_naming_it(export_copy, damage, name):
    model = ResiregVLM.from_pretrained(export_copy)
    damage(export_copy / name)
    with pytest.raises(IntegrityError, match=rf"{export_copy / name}: SHA-256 .* does not match"):
        ResiregVLM.from_pretrained(export_copy)
    # stage 2's model.init_from=<export> loads the trained parts through load_trained
    with pytest.raises(IntegrityError, match=rf"{export_copy / name}: SHA-256"):
        model.load_trained(export_copy)


def test_a_truncated_file_is_an_error_naming_it_never_a_raw_safetensor_error(export_copy):
    cfg_file = export_copy / "config.json"
    # an export without digests (written before they were recorded) reads the file itself
    cfg = json.loads(cfg_file.read_text())
    del cfg["digests"]
    cfg_file.write_text(json.dumps(cfg))
    model = export_copy / "model.safetensors"
    model.write_bytes(model.read_bytes()[:1000])
    with pytest.warns(UserWarning, match="records no file digests"):
        with pytest.raises(IntegrityError, match=rf"{model}: not a readable safetensors file"):
            ResiregVLM.from_pretrained(export_copy)
    cfg_file.write_text(cfg_file.read_text()[:40])  # truncated JSON
    with pytest.raises(IntegrityError, match=rf"{cfg_file}: not a readable"):
        ResiregVLM.from_pretrained(export_copy)


def test_an_export_without_digests_loads_with_a_warning(tiny_export, export_copy):
    cfg_file = export_copy / "config.json"
    cfg = json.loads(cfg_file.read_text())
    del cfg["digests"]
    cfg_file.write_text(json.dumps(cfg))
    with pytest.warns(UserWarning, match=r"config.json: this export records no file digests"):
        old = ResiregVLM.from_pretrained(export_copy)
    with warnings.catch_warnings():
        warnings.simplefilter("error")  # the export with digests: no warning
        new = ResiregVLM.from_pretrained(tiny_export)
    assert _same_weights(old, new)


def test_resireg_eval_on_a_damaged_export_fails_naming_the_file(export_copy, tmp_path):
    from _run import run

    _overwrite_4k(export_copy / "model.safetensors")
    out = tmp_path / "eval"
    proc = run("resireg-eval", f"model_path={export_copy}", "dataset=synthetic", "num_workers=0",
               f"paths.output_dir={out}", check=False)  # fmt: skip
    assert proc.returncode != 0
    assert f"{export_copy / 'model.safetensors'}: SHA-256" in proc.stderr + proc.stdout
    results = out / "results.json"
    assert not results.exists() or json.loads(results.read_text())["status"] != "completed"


# ------------------------------------------------------------------------------ ONNX (item 1)
def _unit(x):
    return F.normalize(torch.as_tensor(np.asarray(x)).float(), dim=1)


def _run_onnx(path, **feeds):
    session = ort.InferenceSession(str(path), providers=["CPUExecutionProvider"])
    names = [o.name for o in session.get_outputs()]
    got = session.run(names, {k: v.numpy() for k, v in feeds.items()})
    return dict(zip(names, got, strict=True))


def _torch_reference(model, images):
    """The torch model itself: encode, then Lite as the CPU computes it by default
    (factorised: the other exact form of the graph's SDPA Lite)."""
    with torch.no_grad():
        out = model.encode(images.float())
        lite = ReSiRegLite()(out.intermediates, out.language)
    assert ReSiRegLite().resolve_attention(images.device) == "factorised"
    return {"intermediates": out.intermediates, "language": out.language,
            "embedding": out.embedding, "lite": lite}  # fmt: skip


def _check_fp32(graph, model, images):
    got = _run_onnx(graph, images=images)
    ref = _torch_reference(model, images)
    assert set(got) == set(ref)
    for name, value in ref.items():
        assert got[name].shape == tuple(value.shape), name
        diff = (_unit(got[name]) - _unit(value)).abs().max().item()
        assert diff <= 1e-4, (name, diff)


def _check_fp16(graph, model, images):
    got = _run_onnx(graph, images=images.half())
    ref = _torch_reference(model, images)
    for name, value in ref.items():
        assert got[name].dtype == np.float16, name
        cos = (_unit(got[name]) * _unit(value)).sum(1).min().item()
        assert cos >= 0.999, (name, cos)


def _check_text(graph, model, texts):
    tokens = model.text.tokenizer(texts).long()
    got = _run_onnx(graph, tokens=tokens)["text"]
    ref = model.encode_text(texts)
    assert got.shape == tuple(ref.shape)
    assert np.abs(got - ref.numpy()).max() <= 1e-4


def _check_manifest(result):
    manifest = json.loads(result.manifest.read_text())
    opsets = {op.domain: op.version for op in onnx.load(str(result.image)).opset_import}
    assert manifest["opsets"] == opsets == result.opsets and opsets[""] >= 18
    for name, digest in manifest["digests"].items():
        assert _sha256(result.image.parent / name) == digest
    return manifest


@pytest.fixture(scope="module")
def tiny_model(tiny_export):
    return ResiregVLM.from_pretrained(tiny_export)


@pytest.fixture(scope="module")
def dynamic_cli(tiny_export, tmp_path_factory):
    """``resireg-export onnx --lite --dynamic`` in a fresh process, as a user runs it."""
    out = tmp_path_factory.mktemp("onnx") / "model.onnx"
    proc = subprocess.run(
        [sys.executable, "-m", "resireg.deploy.cli", "export", "onnx", str(tiny_export),
         "--out", str(out), "--lite", "--dynamic"],
        capture_output=True, text=True, timeout=600, env={**os.environ, "HF_HUB_OFFLINE": "1"},
    )  # fmt: skip
    assert proc.returncode == 0, proc.stderr[-3000:]
    return out, proc.stdout


def test_the_export_command_writes_checked_graphs_and_reports_the_comparison(dynamic_cli):
    out, stdout = dynamic_cli
    assert out.is_file() and out.with_name("model.text.onnx").is_file()
    onnx.checker.check_model(str(out), full_check=True)
    onnx.checker.check_model(str(out.with_name("model.text.onnx")), full_check=True)
    for name in ("intermediates", "language", "embedding", "lite", "text"):
        assert f"onnxruntime vs torch, {name}: max |diff|" in stdout
    manifest = json.loads(Path(f"{out}.json").read_text())
    assert manifest["image"]["dynamic"] and manifest["image"]["outputs"][-1] == "lite"
    assert manifest["lite"] == {"alpha": 10.0, "tau": 0.0, "upscale": 2, "attention": "sdpa"}


@pytest.mark.parametrize(("batch", "size"), [(1, (48, 64)), (3, (64, 96))])
def test_dynamic_image_graph_matches_torch(dynamic_cli, tiny_model, batch, size):
    out, _ = dynamic_cli
    _check_fp32(out, tiny_model, torch.randn(batch, 3, *size))


@pytest.mark.parametrize("texts", [["floor"], ["a photo of a chair.", "table", "wall"]])
def test_dynamic_text_graph_matches_torch(dynamic_cli, tiny_model, texts):
    out, _ = dynamic_cli
    _check_text(out.with_name("model.text.onnx"), tiny_model, texts)


def test_fixed_graph_batch_3_matches_torch_and_takes_only_its_shape(tiny_model, tmp_path):
    result = export_onnx(tiny_model, tmp_path / "m.onnx", lite=True, height=48, width=64,
                         batch=3, text=False)  # fmt: skip
    _check_manifest(result)
    assert not result.text.exists()
    _check_fp32(result.image, tiny_model, torch.randn(3, 3, 48, 64))
    with pytest.raises(Exception, match="dimensions"):
        _run_onnx(result.image, images=torch.randn(1, 3, 48, 64))


def test_fp16_graphs_match_torch_fp32(tiny_model, tmp_path):
    result = export_onnx(tiny_model, tmp_path / "h.onnx", lite=True, fp16=True, height=48, width=64)
    manifest = _check_manifest(result)
    assert manifest["dtype"] == "float16" and manifest["image"]["shape"] == [1, 3, 48, 64]
    _check_fp16(result.image, tiny_model, torch.randn(1, 3, 48, 64))
    # the text graph stays float32 (onnxruntime 1.31 crashes on the float16 text tower)
    assert onnx.load(str(result.text)).graph.output[0].type.tensor_type.elem_type == 1
    _check_text(result.text, tiny_model, ["floor", "a chair"])
    assert next(tiny_model.parameters()).dtype == torch.float32  # the caller's model unchanged


def test_factorised_lite_does_not_export_and_is_refused_with_the_reason(tiny_model, tmp_path):
    graph = ImageGraph(copy.deepcopy(tiny_model), ReSiRegLite(attention="factorised")).eval()
    with pytest.raises(Exception, match="(?i)data.dependent|equal"):  # the documented reason
        torch.export.export(graph, (torch.randn(1, 3, 48, 64),))
    with pytest.raises(ValueError, match="attention='factorised'.*does not export"):
        export_onnx(tiny_model, tmp_path / "f.onnx", lite=True, attention="factorised")
    with pytest.raises(ValueError, match="height=50: expected a positive multiple of the patch"):
        export_onnx(tiny_model, tmp_path / "f.onnx", height=50, width=64)


@pytest.fixture(scope="module")
def vlm25m():
    from _common import build_model  # the 25M architecture, random weights (benchmarks/)

    torch.manual_seed(0)
    return build_model()


@pytest.mark.slow
def test_25m_dynamic_graph_with_lite_matches_torch(vlm25m, tmp_path):
    result = export_onnx(vlm25m, tmp_path / "m.onnx", lite=True, dynamic=True, text=False)
    _check_manifest(result)
    for batch, size in ((1, (64, 96)), (3, (48, 64))):
        _check_fp32(result.image, vlm25m, torch.randn(batch, 3, *size))


@pytest.mark.slow
def test_25m_fp16_graph_matches_torch_fp32(vlm25m, tmp_path):
    result = export_onnx(vlm25m, tmp_path / "h.onnx", lite=True, fp16=True, height=64, width=96,
                         text=False)  # fmt: skip
    _check_fp16(result.image, vlm25m, torch.randn(1, 3, 64, 96))


# ------------------------------------------------------------------- Hub and torch.hub (item 2)
def test_the_hub_folder_holds_the_export_a_parsable_card_and_the_digests(tiny_export, tmp_path):
    from huggingface_hub import ModelCard

    from resireg.models.vlm.card import hub_folder

    folder = hub_folder(tiny_export, tmp_path / "up", "someone/resireg-tiny", {"license": "mit"})
    names = sorted(p.name for p in folder.iterdir())
    assert names == ["README.md", "SHA256SUMS", "config.json", "frozen.safetensors",
                     "model.safetensors"]  # fmt: skip
    for name in ("config.json", "frozen.safetensors", "model.safetensors"):
        assert (folder / name).read_bytes() == (tiny_export / name).read_bytes()
    sums = dict(
        reversed(line.split("  ")) for line in (folder / "SHA256SUMS").read_text().splitlines()
    )
    assert sums == {n: _sha256(folder / n) for n in ("config.json", "frozen.safetensors",
                                                     "model.safetensors")}  # fmt: skip
    card = ModelCard.load(folder / "README.md")
    assert card.data.library_name == "resireg" and card.data.license == "mit"
    assert card.data.pipeline_tag == "image-segmentation" and "resireg" in card.data.tags
    assert all(digest in card.text for digest in sums.values())
    assert 'ResiregVLM.from_pretrained("someone/resireg-tiny")' in card.text


def test_push_to_hub_creates_the_repo_and_uploads_that_folder(tiny_export, tmp_path, monkeypatch):
    """The network is unavailable: HfApi's two calls are recorded (the one fake allowed), the
    folder they are given is copied before push_to_hub removes it, and checked."""
    from huggingface_hub import HfApi

    calls, uploaded = [], tmp_path / "uploaded"

    def create_repo(self, repo_id, **kwargs):
        calls.append(("create_repo", repo_id, kwargs))

    def upload_folder(self, **kwargs):
        calls.append(("upload_folder", kwargs["repo_id"], kwargs))
        shutil.copytree(kwargs["folder_path"], uploaded)
        return "commit-info"

    monkeypatch.setattr(HfApi, "create_repo", create_repo)
    monkeypatch.setattr(HfApi, "upload_folder", upload_folder)
    model = ResiregVLM.from_pretrained(tiny_export)
    with torch.no_grad():  # weights changed since loading: the upload is the model as it is
        model.head.proj.bias.add_(0.5)
    assert model.push_to_hub("someone/resireg-tiny", private=True) == "commit-info"
    (c_name, c_repo, c_kw), (u_name, u_repo, u_kw) = calls
    assert (c_name, c_repo, u_name, u_repo) == ("create_repo", "someone/resireg-tiny",
                                                "upload_folder", "someone/resireg-tiny")  # fmt: skip
    assert c_kw == {"private": True, "repo_type": "model", "exist_ok": True}
    assert u_kw["repo_type"] == "model" and u_kw["revision"] is None
    assert not Path(u_kw["folder_path"]).exists()  # a temporary folder, removed
    assert {p.name for p in uploaded.iterdir()} >= {"README.md", "SHA256SUMS", "config.json",
                                                    "model.safetensors"}  # fmt: skip
    verify_digests(uploaded, json.loads((uploaded / "config.json").read_text())["digests"], "up")
    assert _same_weights(ResiregVLM.from_pretrained(uploaded), model)


def test_push_to_hub_refuses_a_damaged_export(export_copy, monkeypatch):
    from huggingface_hub import HfApi

    model = ResiregVLM.from_pretrained(export_copy)
    _flip_bit(export_copy / "model.safetensors")
    called = []
    monkeypatch.setattr(HfApi, "create_repo", lambda self, *a, **k: called.append(a))
    monkeypatch.setattr(HfApi, "upload_folder", lambda self, *a, **k: called.append(a))
    with pytest.raises(IntegrityError, match="model.safetensors: SHA-256"):
        model.push_to_hub("someone/x", export=export_copy)
    assert called == []


def test_torch_hub_load_of_the_checkout_equals_from_pretrained(tiny_export):
    hub = torch.hub.load(str(ROOT), "resireg_vlm", path_or_repo=str(tiny_export), source="local")
    ref = ResiregVLM.from_pretrained(tiny_export)
    assert type(hub) is ResiregVLM and _same_weights(hub, ref) and not hub.training
    images = torch.randn(1, 3, 48, 64)
    with torch.no_grad():
        assert torch.equal(hub.encode(images).language, ref.encode(images).language)
    assert torch.equal(hub.encode_text(["floor"]), ref.encode_text(["floor"]))
    image = np.random.default_rng(0).integers(0, 256, (48, 64, 3), dtype=np.uint8)
    result = torch.hub.load(str(ROOT), "resireg_segment", image, "floor,chair",
                            path_or_repo=str(tiny_export), source="local")  # fmt: skip
    from resireg.deploy.segment import segment

    np.testing.assert_array_equal(result.label_map, segment(image, "floor,chair", ref).label_map)
