"""benchmarks/bench_throughput.py: tables, plot, OOM rows, and its FLOP formulas against
``torch.utils.flop_counter.FlopCounterMode`` on the real modules.

The formulas count matrix products only, the ops FlopCounterMode counts (with formulas added
for ``mv`` and the in-place ``addmm_``, which it lacks), so they must agree exactly: tolerance 0. FlopCounterMode does not see CPU SDPA's fused kernel
(``_scaled_dot_product_flash_attention_for_cpu`` has no formula), so counts run with the math
backend, whose two batched products are the ones the fused kernel computes.
"""

from __future__ import annotations

import importlib.util
import itertools

import pytest
import torch
from PIL import Image
from torch.nn.attention import SDPBackend, sdpa_kernel
from torch.utils.flop_counter import FlopCounterMode

from helpers.paths import ROOT
from resireg.method.full import ReSiRegFull
from resireg.method.lite import ReSiRegLite
from resireg.models import EUPEBackbone, LanguageHead

_PATH = ROOT / "benchmarks" / "bench_throughput.py"
_spec = importlib.util.spec_from_file_location("bench_throughput", _PATH)
bench = importlib.util.module_from_spec(_spec)
_spec.loader.exec_module(bench)

TINY = ["--tiny", "--device", "cpu", "--height", "64", "--width", "96", "--repeats", "1",
        "--peak-size", "64"]  # fmt: skip


@pytest.fixture(autouse=True)
def _one_thread():
    """One intra-op thread: the tiny runs check structure, not speed, and a shared 2-core
    machine makes two-thread tiny ops wait on each other (8.5 s against 3.2 s for a run)."""
    threads = torch.get_num_threads()
    torch.set_num_threads(1)
    yield
    torch.set_num_threads(threads)


def _mv_flop(a_shape, b_shape, *args, out_shape=None, **kwargs) -> int:
    return 2 * a_shape[0] * a_shape[1]


def _addmm_flop(self_shape, a_shape, b_shape, *args, out_shape=None, **kwargs) -> int:
    return 2 * a_shape[0] * a_shape[1] * b_shape[1]


#: Matrix products FlopCounterMode has no formula for: matrix-vector products and the
#: in-place ``addmm_`` that ``resireg.method.pca.gram`` accumulates with.
_MISSING = {torch.ops.aten.mv: _mv_flop, torch.ops.aten.addmm_: _addmm_flop}


def _count(fn) -> int:
    """Matrix-product FLOP of ``fn()`` (SDPA on its math kernel, see the module docstring)."""
    counter = FlopCounterMode(display=False, custom_mapping=_MISSING)
    with sdpa_kernel(SDPBackend.MATH), counter, torch.no_grad():
        fn()
    return counter.get_total_flops()


def _table_rows(text: str, header: str) -> list[list[str]]:
    lines = text.splitlines()
    start = next(i for i, line in enumerate(lines) if line.startswith(header))
    rows = []
    for line in lines[start + 2 :]:
        if not line.startswith("|"):
            break
        rows.append([c.strip() for c in line.strip("|").split("|")])
    return rows


@pytest.mark.slow
def test_main_prints_tables_and_writes_plot(tmp_path, capsys):
    out = tmp_path / "plots" / "throughput.png"
    result = bench.main([*TINY, "--batch-sizes", "1", "2", "--out", str(out)])
    text = capsys.readouterr().out

    rows = result["throughput"]
    assert [(r["batch"], r["variant"]) for r in rows] == list(
        itertools.product([1, 2], bench.VARIANT_NAMES)
    )
    assert all(r["status"] == "ok" and r["images_per_s"] > 0 for r in rows)
    assert [r["ratio"] for r in rows if r["variant"] == "VLM"] == [1.0, 1.0]
    printed = _table_rows(text, "| batch | variant |")
    assert len(printed) == 6
    assert [r[3] for r in printed if r[1] == "VLM"] == ["1.00", "1.00"]

    stages = result["stages"]
    assert [(s["batch"], s["stage"]) for s in stages] == list(
        itertools.product([1, 2], ["backbone", "head", "lite", "full"])
    )
    for s in stages:
        assert s["seconds"] > 0 and s["gflops"] > 0 and s["matmul_gflops"] > 0
        assert s["fraction"] == pytest.approx(s["gflops"] / s["matmul_gflops"])
        assert s["dtype"] == "float32"
    assert all(s["iterations"] >= 1 for s in stages if s["stage"] == "full")
    assert len(_table_rows(text, "| batch | stage |")) == 8

    assert result["plot"] == out and out.is_file()
    with Image.open(out) as im:
        assert im.format == "PNG"
        assert im.size == (round(bench.FIGSIZE[0] * bench.DPI), round(bench.FIGSIZE[1] * bench.DPI))


@pytest.mark.slow
def test_out_of_memory_is_a_row_not_a_crash(tmp_path, capsys, monkeypatch):
    real = ReSiRegLite.forward

    def forward(self, intermediates, language, prior=None):
        if intermediates.shape[0] >= 2:
            raise torch.OutOfMemoryError("CUDA out of memory. Tried to allocate 6.00 GiB")
        return real(self, intermediates, language, prior)

    monkeypatch.setattr(ReSiRegLite, "forward", forward)
    out = tmp_path / "oom.png"
    result = bench.main([*TINY, "--batch-sizes", "1", "2", "4", "--out", str(out)])
    text = capsys.readouterr().out
    status = {(r["batch"], r["variant"]): r["status"] for r in result["throughput"]}
    assert status[(2, "VLM + Lite")] == "OOM"
    assert status[(4, "VLM + Lite")] == "OOM*"  # not run after a smaller batch failed
    assert all(v == "ok" for (b, name), v in status.items() if name != "VLM + Lite" or b == 1)
    lite_rows = [r for r in _table_rows(text, "| batch | variant |") if r[1] == "VLM + Lite"]
    assert [r[2] for r in lite_rows[1:]] == ["OOM", "OOM*"]
    # Stage timings: batch 1, and the largest batch where every variant fits (also 1).
    assert {s["batch"] for s in result["stages"]} == {1}
    assert out.is_file()


def test_median_seconds_returns_none_on_oom_only():
    cpu = torch.device("cpu")

    def cuda_oom():
        raise torch.OutOfMemoryError("CUDA out of memory")

    def cpu_oom():
        raise RuntimeError("[enforce fail at alloc_cpu.cpp:117] DefaultCPUAllocator: "
                           "can't allocate memory: you tried to allocate 1099511627776 bytes")  # fmt: skip

    def bug():
        raise RuntimeError("shape mismatch")

    assert bench.median_seconds(cuda_oom, 1, cpu) is None
    assert bench.median_seconds(cpu_oom, 1, cpu) is None
    with pytest.raises(RuntimeError, match="shape mismatch"):
        bench.median_seconds(bug, 1, cpu)
    assert bench.median_seconds(lambda: None, 3, cpu) >= 0


@pytest.mark.parametrize("attention", ["sdpa", "factorised"])
@pytest.mark.parametrize("tau", [0.0, 0.1])
@pytest.mark.parametrize("batch,h,w", [(1, 3, 4), (2, 4, 6)])
def test_lite_flops_match_flop_counter(batch, h, w, tau, attention, monkeypatch):
    """The SDPA path (tau = 0, padded to max(Dv, Dl)), the chunked explicit path, and the
    factorised path (with blocks small enough that the Gram rows overlap)."""
    from resireg.method import lite as lite_module

    monkeypatch.setattr(lite_module, "_FACTORISED_BLOCK", 2 * 2 * 4 * h * w)  # 2 coarse rows
    inter, lang = torch.randn(batch, 384, h, w), torch.randn(batch, 512, h, w)
    lite = ReSiRegLite(alpha=10.0, tau=tau, upscale=2, attention=attention)
    expected = bench.lite_flops(batch, h, w, dv=384, dl=512, upscale=2, tau=tau,
                                attention=attention)  # fmt: skip
    assert _count(lambda: lite(inter, lang)) == expected


def test_backbone_and_head_flops_match_flop_counter():
    """The real EUPE ViT-S/16 and the real head spec (conf/model/vlm25m.yaml), small canvas."""
    model = bench.build_model(tiny=False)
    bb, head = model.backbone, model.head
    assert (bb.embed_dim, bb.depth, bb.num_registers, bb.patch_size) == (384, 12, 4, 16)
    assert bb.model.blocks[0].mlp.fc1.out_features == 1536
    assert (head.out_dim, len(head.blocks), head.use_registers) == (512, 2, False)
    x = torch.randn(2, 3, 32, 48)
    assert _count(lambda: bb(x)) == bench.backbone_flops(2, 32, 48)
    feats = bb(x)
    assert _count(lambda: head(feats)) == bench.head_flops(2, 2 * 3)
    with_registers = LanguageHead(in_dim=64, out_dim=48, depth=1, num_heads=2, use_registers=True)
    small = EUPEBackbone("eupe_vit_s16", weights=None, embed_dim=64, depth=1, num_heads=2)
    f = small(torch.randn(1, 3, 32, 32))
    expected = bench.head_flops(1, 4, dim=64, out_dim=48, depth=1, mlp_hidden=256, registers=4)
    assert _count(lambda: with_registers(f)) == expected


@pytest.mark.parametrize(
    "kwargs",
    [{}, {"n_prototypes": 7, "n_components": 3, "upscale": 1}, {"n_components": 100, "upscale": 3}],
    ids=["default", "s1", "s3"],
)
def test_full_flops_match_flop_counter(kwargs):
    """ReSiReg Full with the recorded k-means iterations and distance rows (default: conf's
    36 prototypes)."""
    cfg = bench.resireg_defaults()["full"]
    full = ReSiRegFull(**{**cfg, **kwargs})
    inter, lang = torch.randn(2, 384, 3, 4), torch.randn(2, 512, 3, 4)
    with bench.record_kmeans() as runs:
        counted = _count(lambda: full(inter, lang))
    ((iterations, rows),) = runs
    assert iterations >= 1
    expected = bench.full_flops(
        2, 3, 4, iterations=iterations, distance_rows=rows, dv=384, dl=512,
        upscale=full.upscale, n_prototypes=full.n_prototypes, n_components=full.n_components,
    )  # fmt: skip
    assert counted == expected


def test_full_flops_at_protocol_size_match_flop_counter():
    """One real-size batch (2 x 36 x 48, s = 2: 13,824 points) of random features."""
    cfg = bench.resireg_defaults()["full"]
    full = ReSiRegFull(**cfg)
    inter, lang = torch.randn(2, 384, 36, 48), torch.randn(2, 512, 36, 48)
    with bench.record_kmeans() as runs:
        counted = _count(lambda: full(inter, lang))
    ((iterations, rows),) = runs
    assert bench.full_flops(2, 36, 48, iterations=iterations, distance_rows=rows) == counted


def test_gram_flops_match_flop_counter():
    from resireg.method.pca import gram

    for d in (64, 95, 96, 384, 385):
        y = torch.randn(10, d)
        assert _count(lambda y=y: gram(y)) == bench.gram_flops(10, d), d


def test_flop_numbers_of_the_docstring():
    """576 x 768, s = 2: the figures the module docstring (and the issue) quote."""
    gflop = 1e9
    assert bench.backbone_flops(1, 576, 768) / gflop == pytest.approx(129.97, abs=0.005)
    assert bench.head_flops(1, 36 * 48) / gflop == pytest.approx(22.10, abs=0.005)
    assert bench.lite_flops(1, 36, 48) / gflop == pytest.approx(97.84, abs=0.005)
    assert bench.lite_flops(1, 36, 48, tau=0.1) / gflop == pytest.approx(85.61, abs=0.005)
    factorised = bench.lite_flops(1, 36, 48, attention="factorised") / gflop
    assert factorised == pytest.approx(14.65, abs=0.005)
    assert 2 * 6912 * 1728 * 512 / gflop == pytest.approx(12.23, abs=0.005)  # token product
    plain = bench.full_flops_breakdown(1, 36, 48, iterations=0)  # one distance pass
    assert {k: round(v / gflop, 2) for k, v in plain.items()} == {
        "moments": 0.32, "projection": 0.05, "seeding": 0.02, "kmeans": 0.02, "mixing": 0.25,
    }  # fmt: skip
    n = 4 * 36 * 48
    per_pass = bench.full_flops(1, 36, 48, iterations=1, distance_rows=2 * n) - bench.full_flops(
        1, 36, 48, iterations=1, distance_rows=n
    )
    assert per_pass / gflop == pytest.approx(0.018, abs=0.0005)
    assert bench.full_flops(1, 36, 48, iterations=1, distance_rows=2 * n) / gflop == (
        pytest.approx(0.68, abs=0.005)
    )
    assert bench.full_flops(1, 36, 48, iterations=100) / gflop == pytest.approx(2.45, abs=0.005)
