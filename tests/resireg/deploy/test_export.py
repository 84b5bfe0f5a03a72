"""Exports that prove their content (issue 34 item 4), ONNX graphs checked against torch, the
Hugging Face Hub folder and torch.hub entry (issue 39 items 1-2).

References are independent of the code under test: digests by ``hashlib``, operator sets by
``onnx.load``, the graphs' outputs against the torch model's own ``encode`` /
``encode_text`` and ``ReSiRegLite`` in its other exact form (factorised on the CPU), the model
card parsed by ``huggingface_hub.ModelCard``."""

import hashlib
import json
import os
import re
import shutil
import subprocess
import sys
import warnings
from pathlib import Path

import numpy as np
import pytest
import torch

from helpers.paths import ROOT
from helpers.run import run
from resireg.integrity import IntegrityError, verify_digests
from resireg.method.lite import ReSiRegLite
from resireg.models import ResiregVLM

onnx = pytest.importorskip("onnx")
ort = pytest.importorskip("onnxruntime")
pytest.importorskip("onnxscript")
from resireg.deploy import open_graph  # noqa: E402
from resireg.deploy.onnx_export import export_onnx  # noqa: E402


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
    from helpers.tiny import TINY_BACKBONE, TINY_HEAD, TINY_TEXT

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


@pytest.mark.slow
def test_resireg_eval_on_a_damaged_export_fails_naming_the_file(export_copy, tmp_path):
    from helpers.run import run

    _overwrite_4k(export_copy / "model.safetensors")
    out = tmp_path / "eval"
    proc = run("resireg-eval", f"model_path={export_copy}", "dataset=synthetic", "num_workers=0",
               f"hydra.run.dir={out}", check=False)  # fmt: skip
    assert proc.returncode != 0
    assert f"{export_copy / 'model.safetensors'}: SHA-256" in proc.stderr + proc.stdout
    results = out / "results.json"
    assert not results.exists() or json.loads(results.read_text())["status"] != "completed"


# ------------------------------------------------- paths that leave the export (issue 44 item 6)
def _frozen_outside(export, tmp_path, absolute):
    """The export's frozen.safetensors, its values changed, moved out of the export, and
    config.json pointing at it with its digest recomputed (what anyone editing files does)."""
    from safetensors.torch import load_file, save_file

    outside = tmp_path / "outside" / "w.safetensors"
    outside.parent.mkdir()
    tensors = {k: v + 1.0 for k, v in load_file(export / "frozen.safetensors").items()}
    save_file(tensors, str(outside))
    (export / "frozen.safetensors").unlink()
    name = str(outside) if absolute else "../outside/w.safetensors"
    assert (export / name).resolve() == outside.resolve()  # it names that file
    cfg_file = export / "config.json"
    cfg = json.loads(cfg_file.read_text())
    del cfg["digests"]["frozen.safetensors"]
    cfg["frozen_weights"] = name
    cfg["digests"][name] = _sha256(outside)
    cfg_file.write_text(json.dumps(cfg))
    return name


@pytest.mark.parametrize("absolute", [False, True], ids=["dot-dot", "absolute"])
def test_an_export_naming_weights_outside_itself_is_refused(export_copy, tmp_path, absolute):
    name = _frozen_outside(export_copy, tmp_path, absolute)
    field = f"{export_copy / 'config.json'}: frozen_weights={name!r}: "
    with pytest.raises(IntegrityError) as err:
        ResiregVLM.from_pretrained(export_copy)
    assert str(err.value).startswith(field) and "refused" in str(err.value)
    # only the digests naming it: the same refusal, from the digests field
    cfg = json.loads((export_copy / "config.json").read_text())
    cfg["frozen_weights"] = "frozen.safetensors"
    (export_copy / "config.json").write_text(json.dumps(cfg))
    with pytest.raises(IntegrityError, match=rf"config\.json: digests={re.escape(repr(name))}: "):
        ResiregVLM.from_pretrained(export_copy)
    from resireg.models.vlm.card import hub_folder  # (it copies the files the digests name)

    with pytest.raises(IntegrityError, match=r"config\.json: digests="):
        hub_folder(export_copy, tmp_path / "up", "someone/x")
    assert not (tmp_path / "up").exists()


def test_resireg_export_on_an_export_naming_weights_outside_fails_in_one_line(
    export_copy, tmp_path
):
    from helpers.run import run

    name = _frozen_outside(export_copy, tmp_path, absolute=False)
    out = tmp_path / "graphs" / "model.onnx"
    proc = run("resireg-export", "onnx", export_copy, "--out", out, "--no-validate", check=False)
    assert proc.returncode == 2
    assert proc.stderr.splitlines() == [proc.stderr.strip()]  # one line, no traceback
    assert f"config.json: frozen_weights={name!r}: leaves the folder, refused" in proc.stderr
    assert not (tmp_path / "graphs").exists()


# ------------------------------------------------------------------------------ ONNX (item 1)
def _run_onnx(path, **feeds):
    """A graph run as the project opens one: verified against its manifest first."""
    session = open_graph(path)
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


def _close(got, ref, tolerance, name):
    """Every value of ``got`` within ``tolerance`` x the output's largest magnitude of the
    torch value (no normalisation: a scale error at any position shows), and each position's
    norm over channels within ``tolerance`` of the reference's (relative)."""
    got, ref = np.asarray(got, dtype=np.float32), ref.float().numpy()
    assert got.shape == ref.shape, name
    diff = np.abs(got - ref).max() / np.abs(ref).max()
    assert diff <= tolerance, (name, diff)
    norm_got, norm_ref = np.linalg.norm(got, axis=1), np.linalg.norm(ref, axis=1)
    scale = np.abs(norm_got / norm_ref - 1).max()
    assert scale <= tolerance, (name, scale)


def _check_fp32(graph, model, images):
    got = _run_onnx(graph, images=images)
    ref = _torch_reference(model, images)
    assert set(got) == set(ref)
    for name, value in ref.items():
        _close(got[name], value, 1e-4, name)


def _check_fp16(graph, model, images):
    got = _run_onnx(graph, images=images.half())
    ref = _torch_reference(model, images)
    for name, value in ref.items():
        assert got[name].dtype == np.float16, name
        _close(got[name], value, 5e-3, name)  # float16's step is ~1e-3 of a value


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
    proc = run(sys.executable, "-m", "resireg.deploy.cli", "export", "onnx", tiny_export,
               "--out", out, "--lite", "--dynamic")  # fmt: skip
    return out, proc.stdout


@pytest.mark.slow
def test_the_export_command_writes_checked_graphs_and_reports_the_comparison(dynamic_cli):
    out, stdout = dynamic_cli
    assert sorted(p.name for p in out.parent.iterdir()) == [
        "model.onnx",
        "model.onnx.json",
        "model.text.onnx",
    ]  # fmt: skip  (no staging left)
    onnx.checker.check_model(str(out), full_check=True)
    onnx.checker.check_model(str(out.with_name("model.text.onnx")), full_check=True)
    for name in ("intermediates", "language", "embedding", "lite", "text"):
        assert f"onnxruntime vs torch, {name}: max |diff|" in stdout
    manifest = json.loads(Path(f"{out}.json").read_text())
    assert manifest["image"]["dynamic"] and manifest["image"]["outputs"][-1] == "lite"
    assert manifest["lite"] == {"alpha": 10.0, "tau": 0.0, "upscale": 2, "attention": "sdpa"}


@pytest.mark.slow
@pytest.mark.parametrize(("batch", "size"), [(1, (48, 64)), (3, (64, 96))])
def test_dynamic_image_graph_matches_torch(dynamic_cli, tiny_model, batch, size):
    out, _ = dynamic_cli
    _check_fp32(out, tiny_model, torch.randn(batch, 3, *size))


@pytest.mark.slow
@pytest.mark.parametrize("texts", [["floor"], ["a photo of a chair.", "table", "wall"]])
def test_dynamic_text_graph_matches_torch(dynamic_cli, tiny_model, texts):
    out, _ = dynamic_cli
    _check_text(out.with_name("model.text.onnx"), tiny_model, texts)


# ------------------------------------------- graphs open only verified (issue 44 item 7)
@pytest.fixture
def graphs(dynamic_cli, tmp_path):
    """A copy of the command's graphs and manifest, to damage."""
    out, _ = dynamic_cli
    dest = tmp_path / "graphs"
    shutil.copytree(out.parent, dest)
    return dest / "model.onnx", dest / "model.text.onnx"


@pytest.mark.slow
def test_open_graph_opens_both_graphs_of_an_intact_export(graphs):
    image, text = graphs
    assert [i.name for i in open_graph(image).get_inputs()] == ["images"]
    assert [o.name for o in open_graph(text, threads=1).get_outputs()] == ["text"]


@pytest.mark.slow
@pytest.mark.parametrize("which", [0, 1], ids=["image", "text"])
def test_open_graph_refuses_a_damaged_graph_naming_it(graphs, which):
    graph = graphs[which]
    _flip_bit(graph)
    onnx.load(str(graph))  # still a graph onnx reads: only the digest tells
    with pytest.raises(
        IntegrityError, match=rf"^{re.escape(str(graph))}: SHA-256 .* does not match"
    ):
        open_graph(graph)


@pytest.mark.slow
def test_open_graph_refuses_a_swapped_graph_and_one_without_its_manifest(graphs):
    image, text = graphs
    shutil.copyfile(text, image)  # the text graph where the image graph was
    with pytest.raises(IntegrityError, match=rf"^{re.escape(str(image))}: SHA-256 .* image graph"):
        open_graph(image)
    alone = image.parent / "alone" / "model.text.onnx"
    alone.parent.mkdir()
    shutil.copyfile(text, alone)
    with pytest.raises(IntegrityError, match=rf"^{re.escape(str(alone))}: no manifest"):
        open_graph(alone)


@pytest.mark.slow
def test_open_graph_refuses_a_manifest_naming_a_file_outside(graphs, tmp_path):
    image, _ = graphs
    manifest = Path(f"{image}.json")
    record = json.loads(manifest.read_text())
    record["image"]["file"] = "../model.onnx"
    manifest.write_text(json.dumps(record))
    with pytest.raises(
        IntegrityError, match=r"model\.onnx\.json: image\.file='\.\./model\.onnx': "
    ):
        open_graph(image)


# ------------------------------------------------ resireg-export's faults (issue 44 item 12)
def _one_line(proc):
    assert proc.returncode == 2, proc.stdout + proc.stderr
    assert proc.stderr.count("\n") == 1 and proc.stderr.startswith("error: "), proc.stderr
    return proc.stderr.strip()


def test_resireg_export_checks_the_export_and_out_before_it_starts(tiny_export, tmp_path):
    from helpers.run import run

    (tmp_path / "file").write_text("x")
    (tmp_path / "out" / "m.text.onnx").mkdir(parents=True)
    cases = {  # arguments -> what the one line says
        ("someone/missing", "--out", tmp_path / "a" / "m.onnx"):
            "someone/missing: ResiregVLM 'someone/missing' (no such local folder; as a Hugging "
            "Face repo id it is not cached) is not cached and HF_HUB_OFFLINE is set",
        (tiny_export, "--out", tmp_path / "file" / "sub" / "m.onnx"):
            f"--out='{tmp_path / 'file' / 'sub' / 'm.onnx'}': {tmp_path / 'file'} is a regular "
            "file, not a folder",
        (tiny_export, "--out", tmp_path / "out" / "m.onnx"):
            f"--out='{tmp_path / 'out' / 'm.onnx'}': the text graph's path "
            f"{tmp_path / 'out' / 'm.text.onnx'} is a folder",
    }  # fmt: skip
    for args, said in cases.items():
        line = _one_line(run("resireg-export", "onnx", *args, check=False))
        assert line.startswith(f"error: {said}"), line
    assert sorted(p.name for p in tmp_path.rglob("*")) == ["file", "m.text.onnx", "out"]


@pytest.mark.slow
def test_a_write_failing_midway_leaves_nothing_at_out(tiny_export, tmp_path):
    """A real failed write: the process may not write files over 4 MB (RLIMIT_FSIZE, as a full
    disk or a quota would refuse); the tiny image graph (~1.4 MB) is written, the text graph
    (~13 MB) is not. Neither, nor the manifest, nor a staging folder is left."""
    import resource
    import signal

    def limit():
        signal.signal(signal.SIGINT, signal.SIG_DFL)
        signal.signal(signal.SIGXFSZ, signal.SIG_IGN)  # a write past the limit fails (EFBIG)
        resource.setrlimit(resource.RLIMIT_FSIZE, (4 << 20, 4 << 20))

    out = tmp_path / "graphs" / "model.onnx"
    proc = subprocess.run(
        [sys.executable, "-m", "resireg.deploy.cli", "export", "onnx", str(tiny_export), "--out",
         str(out), "--no-validate"], capture_output=True, text=True, timeout=600,
        preexec_fn=limit, env={**os.environ, "HF_HUB_OFFLINE": "1"},
    )  # fmt: skip
    line = _one_line(proc)
    assert (
        line == f"error: --out='{out}': could not write the graphs (File too large); none was left"
    )
    assert list(tmp_path.iterdir()) == []


@pytest.mark.slow
def test_fixed_graph_batch_3_matches_torch_and_takes_only_its_shape(tiny_model, tmp_path):
    result = export_onnx(tiny_model, tmp_path / "m.onnx", lite=True, height=48, width=64,
                         batch=3, text=False)  # fmt: skip
    _check_manifest(result)
    assert not result.text.exists()
    _check_fp32(result.image, tiny_model, torch.randn(3, 3, 48, 64))
    with pytest.raises(Exception, match="dimensions"):
        _run_onnx(result.image, images=torch.randn(1, 3, 48, 64))


@pytest.mark.slow
def test_fp16_graphs_match_torch_fp32(tiny_model, tmp_path):
    result = export_onnx(tiny_model, tmp_path / "h.onnx", lite=True, fp16=True, height=48, width=64)
    manifest = _check_manifest(result)
    assert manifest["dtype"] == "float16" and manifest["image"]["shape"] == [1, 3, 48, 64]
    _check_fp16(result.image, tiny_model, torch.randn(1, 3, 48, 64))
    # the text graph stays float32 (onnxruntime 1.31 crashes on the float16 text tower)
    assert onnx.load(str(result.text)).graph.output[0].type.tensor_type.elem_type == 1
    _check_text(result.text, tiny_model, ["floor", "a chair"])
    assert next(tiny_model.parameters()).dtype == torch.float32  # the caller's model unchanged


def _own_ops(graph, output, inputs):
    """The operator types computing ``output`` from the values ``inputs`` (the nodes above
    ``output`` that are not above any of ``inputs``)."""
    producer = {out: node for node in graph.node for out in node.output}

    def above(names):
        seen, stack = set(), list(names)
        while stack:
            node = producer.get(stack.pop())
            if node is not None and id(node) not in seen:
                seen.add(id(node))
                stack.extend(node.input)
        return seen

    shared = above(inputs)
    return {n.op_type for n in graph.node if id(n) in above([output]) - shared}


@pytest.mark.slow
def test_factorised_lite_graph_equals_torch_within_1e_5(tiny_model, tmp_path):
    """Lite's factorised form exports (dynamic shapes, no MatMul -> Softmax -> MatMul: the
    graph upsamples the Gram matrix with Resize) and its output equals torch's Lite, both forms
    and the formula in float64, within 1e-5 (float32) at two batches and grids."""
    result = export_onnx(tiny_model, tmp_path / "f.onnx", lite=True, attention="factorised",
                         dynamic=True, text=False)  # fmt: skip
    manifest = _check_manifest(result)
    assert manifest["lite"]["attention"] == "factorised"
    ops = _own_ops(onnx.load(str(result.image)).graph, "lite", ["intermediates", "language"])
    assert "Softmax" not in ops and "Resize" in ops and "Exp" in ops, sorted(ops)
    for batch, (h, w) in ((1, (48, 64)), (3, (64, 96))):
        images = torch.randn(batch, 3, h, w, generator=torch.Generator().manual_seed(batch))
        got = torch.from_numpy(_run_onnx(result.image, images=images)["lite"])
        with torch.no_grad():
            out = tiny_model.encode(images)
            for form in ("factorised", "sdpa"):
                ref = ReSiRegLite(attention=form)(out.intermediates, out.language)
                assert got.shape == ref.shape
                assert (got - ref).abs().max() <= 1e-5, form
            ref64 = ReSiRegLite(attention="sdpa")(out.intermediates.double(), out.language.double())
        assert (got.double() - ref64).abs().max() <= 1e-5
    with pytest.raises(ValueError, match="height=50: expected a positive multiple of the patch"):
        export_onnx(tiny_model, tmp_path / "f.onnx", height=50, width=64)
    with pytest.raises(ValueError, match="attention='flash'.*'factorised'"):
        export_onnx(tiny_model, tmp_path / "g.onnx", lite=True, attention="flash")


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


# ------------------------------------- a backbone file outside the export (issue 51, item 12)
def _backbone_outside(export, tmp_path):
    """An export as one trained from a local backbone checkpoint was written before such
    exports embedded it: config.json names the checkpoint by its absolute path (outside the
    export, covered by no digest), frozen.safetensors holds the text tower only (its digest
    recomputed). The checkpoint's values differ from the export's random init."""
    from safetensors.torch import load_file, save_file

    frozen = load_file(export / "frozen.safetensors")
    backbone = {k[len("backbone.model."):]: v + 0.5 for k, v in frozen.items()
                if k.startswith("backbone.model.")}  # fmt: skip
    outside = tmp_path / "ckpt" / "eupe.safetensors"
    outside.parent.mkdir()
    save_file(backbone, str(outside))
    save_file({k: v for k, v in frozen.items() if k.startswith("text.")},
              str(export / "frozen.safetensors"))  # fmt: skip
    cfg_file = export / "config.json"
    cfg = json.loads(cfg_file.read_text())
    cfg["backbone"]["weights"] = str(outside)
    cfg["digests"]["frozen.safetensors"] = _sha256(export / "frozen.safetensors")
    cfg_file.write_text(json.dumps(cfg))
    return outside, backbone


def test_a_backbone_file_outside_the_export_is_taken_only_as_an_argument(export_copy, tmp_path):
    """config.json naming an absolute backbone.weights outside the export: from_pretrained and
    resireg-export refuse it in one line naming the field, reading nothing; passed by the user
    (external=), the file is what the backbone holds, and a re-save embeds it (no outside path,
    its digest recorded); a name inside the export that the digests do not cover is refused."""
    from helpers.run import run

    outside, backbone = _backbone_outside(export_copy, tmp_path)
    before = {p.name: _sha256(p) for p in [*export_copy.iterdir(), outside]}
    field = f"{export_copy / 'config.json'}: backbone.weights={str(outside)!r}: an absolute path"
    with pytest.raises(IntegrityError) as err:
        ResiregVLM.from_pretrained(export_copy)
    assert str(err.value).startswith(field) and "\n" not in str(err.value)
    assert "external={'backbone': {'weights': <path>}}" in str(err.value)
    out = tmp_path / "graphs" / "model.onnx"
    proc = run("resireg-export", "onnx", export_copy, "--out", out, "--no-validate", check=False)
    assert proc.returncode == 2
    assert proc.stderr.splitlines() == [proc.stderr.strip()]  # one line, no traceback
    assert field in proc.stderr and not (tmp_path / "graphs").exists()
    assert {p.name: _sha256(p) for p in [*export_copy.iterdir(), outside]} == before

    model = ResiregVLM.from_pretrained(export_copy, external={"backbone": {"weights": outside}})
    held = model.backbone.model.state_dict()
    assert backbone.keys() == held.keys()
    assert all(torch.equal(held[k], v) for k, v in backbone.items())
    assert model.spec()["external"] == {"backbone": {"weights": outside}}
    saved = model.save_pretrained(tmp_path / "resaved")
    cfg = json.loads((saved / "config.json").read_text())
    assert cfg["backbone"]["weights"] is None and "frozen.safetensors" in cfg["digests"]
    assert _same_weights(model, ResiregVLM.from_pretrained(saved))

    # a file inside the export that no digest covers is refused too
    shutil.copy(outside, export_copy / "eupe.safetensors")
    cfg = json.loads((export_copy / "config.json").read_text())
    cfg["backbone"]["weights"] = "eupe.safetensors"
    (export_copy / "config.json").write_text(json.dumps(cfg))
    with pytest.raises(IntegrityError, match=r"backbone\.weights='eupe\.safetensors': not covered "
                       r"by the export's digests"):  # fmt: skip
        ResiregVLM.from_pretrained(export_copy)


def test_a_backbone_file_given_to_resireg_eval_is_in_the_provenance_with_its_digest(
    export_copy, tmp_path
):
    """resireg-eval's encoder.external.backbone.weights (the user's argument) loads the export
    whose config.json names a file outside it; the run's provenance records that file with
    its SHA-256, beside the export's own files."""
    from helpers.run import evaluate

    outside, _ = _backbone_outside(export_copy, tmp_path)
    out = tmp_path / "eval"
    record = evaluate(f"model_path={export_copy}", "dataset=synthetic", "dataset.size=2",
                      "num_workers=0", "variants=[bb]", f"paths.output_dir={out}",
                      f"encoder.external.backbone.weights={outside}")  # fmt: skip
    assert record["status"] == "completed"
    models = record["provenance"]["models"]
    assert models["external"] == {"backbone.weights": {"path": str(outside.resolve()),
                                                       "sha256": _sha256(outside)}}  # fmt: skip
    assert models["export"]["files"]["config.json"] == _sha256(export_copy / "config.json")
