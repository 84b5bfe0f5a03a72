"""The paper's throughput protocol: the 25M dense VLM alone, + ReSiReg Lite, + ReSiReg Full.

Setting. Random weights of the real architecture: EUPE ViT-S/16 (``weights=None``, built from
``conf/model/backbone/eupe_vit_s16.yaml``) and the language head of ``conf/model/vlm25m.yaml``
(2 blocks at 384, 8 heads, MLP ratio 4, Linear 384 -> 512); weights do not change the cost.
The text tower takes no part in an image pass, so the tiny one (``TINY_TEXT``) is built to save
time. Lite and Full take their parameters from ``conf/resireg/default.yaml`` (Lite: alpha 10,
tau 0, upscale 2; Full: 36 prototypes, components tied to the prototypes, alpha 5, upscale 2,
seed 0, at most 100 Lloyd iterations). Canvas 576 x 768 (the protocol's shorter side 576; sides
multiples of 16 -> a 36 x 48 patch grid), random normalised images. The image path only:
``encode_image(x, variant, normalized=True)`` with the ``bb`` variant (the model alone), Lite
or Full; no text, no metric. CUDA runs under bf16 autocast, CPU in fp32. Each (variant, batch)
is warmed up once, then timed ``--repeats`` times (CUDA synchronised before and after each
call) and the median reported. A batch that runs out of memory is reported as OOM; larger
batches of that variant are then not run (OOM*).

Table 1: images per second per batch size and variant, and the ratio to the model alone at
the same batch size. The plot (``--out``): images per second against batch size, log x.

Table 2, the distance to the machine's limit: per stage, at batch 1 and at the largest batch
of the list where every variant fits, the matrix-product FLOP by arithmetic (below), the
median seconds of that stage's call, its achieved FLOP/s, and the FLOP/s of a plain
``torch.matmul`` of a similar shape timed in the same run at the stage's dtype ("fraction" =
achieved / that), and of a large square matmul ("of peak"). Stages: the backbone
(``model.backbone``), the head (``model.head``), Lite's forward and Full's forward, each under
the same autocast as table 1. Lite computes in its inputs' promoted dtype and Full in fp32 with
autocast off, so their matmuls are timed in those dtypes (the dtype column); under CUDA
autocast the backbone's final LayerNorm returns fp32, so Lite is expected to run in fp32 there.
The similar matmuls: ``[B N, D] x [D, D]`` for backbone and head, one image's score product
``[N, W] x [W, N]`` for Lite, the Lloyd assignment product ``[n, r] x [r, K]`` for Full.

FLOP convention: 1 multiply-add = 2 FLOP; only matrix products (linear layers, convolution,
attention's two products, matmul / einsum) are counted; normalisations, softmax, GELU, RoPE,
interpolation, ``index_add_`` and Full's ``D x D`` float64 ``eigh`` are left out (each is
memory-bound or small). These are the ops ``torch.utils.flop_counter.FlopCounterMode`` counts
(it lacks formulas for ``mv`` and the in-place ``addmm_`` of ``pca.gram``), and ``tests/project/test_bench_throughput.py`` checks
every formula against it, exactly, on the real modules.

- Backbone (ViT, ``P = H*W/p^2`` patches, ``N = P + 1 + R`` tokens with R = 4 registers, width
  D, MLP width M = 4D, depth L):
  ``2 P (3 p^2) D + L (2 N D (4D + 2M) + 4 N^2 D)`` = ``2 P 768 D + L (24 N D^2 + 4 N^2 D)``
  (qkv 6ND^2, projection 2ND^2, MLP 16ND^2; QK^T and AV 2N^2D each).
- Head (same blocks at the backbone width, ``N_h = P + 1`` tokens, registers off, depth 2):
  ``2 (24 N_h D^2 + 4 N_h^2 D) + 2 N_h D D_out`` (final Linear to D_out = 512 on every token).
- Lite at upscale s on an h x w grid: queries AND keys are the upsampled points of the same
  image, ``N = s^2 h w`` each. Its ``sdpa`` computation (the default on CUDA): with tau = 0
  SDPA runs on q, k, v zero-padded to ``W = max(Dv, Dl)``: ``4 B N^2 W``. (tau > 0, the
  chunked explicit path: ``2 B N^2 (Dv + Dl)``.) Its ``factorised`` computation (the default
  elsewhere, docs/method.md#resireg-lite): the coarse Gram rows of each query block (with the
  row above and below) and the per-token weight sums times the coarse tokens, about
  ``B (2 (h w)^2 Dv + 2 N h w Dl)`` (:func:`lite_flops`). The segmentation prior (extra keys)
  is not used here.
- Full (the batch is one scene; ``n = B s^2 h w`` points, K prototypes, r = min(components,
  Dv), ``t = 2 + floor(ln K)`` k-means++ candidates per step), as ``resireg.method.full`` /
  ``resireg.method.pca`` compute it: PCA moments from the small grid, ``U_a^T U_a`` of both axes
  ``2 s (h^3 + w^3)``, first moment ``2 h w Dv``, second moment by ``pca.gram`` (upper
  block triangle of 3 column slabs: 6 of 9 slab products, ``(4/3) B h w Dv^2``, accumulated
  over chunks of images; the Cholesky factors are applied elementwise); projection on the
  small grid ``2 B h w Dv r``; k-means++ ``2 n r (1 + t (K - 1))``; k-means ``2 K r R`` for
  the R point-to-all-centroids distance rows it computed (``KMeansResult.dist_rows``: n for
  the first and for the final assignment, and in between only the points whose distance
  bounds fail; plain Lloyd would compute ``R = n (I + 1)`` for I iterations) plus
  ``2 K^2 r`` per iteration for the centroid separations of the bounds; mixing ``2 n K Dl``.
  I and R are data-dependent: they are recorded from the timed calls; the table reports
  R / n as "distance passes".

Numbers at 576 x 768 (h x w = 36 x 48, s = 2, Dv = 384, Dl = 512), per image: backbone
129.97 GFLOP (N = 1733: blocks 128.95 + patch embedding 1.02), head 22.10 GFLOP, Lite
97.84 GFLOP by SDPA (N = 6912 at W = 512; 85.61 without the padding of the 384-d queries and
keys: the padding costs 14%) and 14.65 GFLOP factorised (Gram rows 2.42, token product
12.23), Full 0.64 GFLOP (moments 0.32, projection 0.05, seeding 0.02,
mixing 0.25) + 0.018 GFLOP per distance pass (at least 2 passes: 0.68 GFLOP; plain Lloyd at
the 100-iteration cap, 101 passes: 2.45 GFLOP); per image nearly independent of the batch
size, as n grows with B. The issue's "4 N^2 D = 98 GFLOP against roughly 130 GFLOP for the
ViT-S forward" is right for this code with N = s^2 h w = 6912 for queries and keys alike and
D = 512, the padded width (at D = 384 it would be 73 GFLOP); the ViT-S figure is 130.0 GFLOP.
Keys are not the h w grid points: Lite attends from every upsampled point to every upsampled
point of its image.

Defaults keep a CPU run to minutes: on CPU ``--batch-sizes 1 2 4 --repeats 3``, on CUDA
``--batch-sizes 1 2 4 8 16 32 --repeats 5``. ``--tiny`` swaps in the tiny models of the tests.

    python benchmarks/bench_throughput.py [--device auto|cpu|cuda] [--batch-sizes 1 2 4 ...]
        [--repeats 5] [--height 576 --width 768] [--out throughput.png] [--tiny]
"""

from __future__ import annotations

import argparse
import contextlib
import gc
import itertools
import math
import statistics
import time
from collections.abc import Callable, Iterator, Sequence
from pathlib import Path
from typing import Any

import torch
from torch import nn

from _common import build_model, resireg_defaults
from resireg.method import full as reconstruct
from resireg.method import lite
from resireg.method.variants import build_variant

VARIANT_NAMES = ("VLM", "VLM + Lite", "VLM + Full")
CPU_BATCH_SIZES = (1, 2, 4)
CUDA_BATCH_SIZES = (1, 2, 4, 8, 16, 32)
#: The plot's size in inches and its resolution: PNG of 640 x 400 pixels.
FIGSIZE = (6.4, 4.0)
DPI = 100


# ----------------------------------------------------------------------------- FLOP formulas
def vit_blocks_flops(n_tokens: int, dim: int, depth: int, mlp_hidden: int) -> int:
    """Pre-norm transformer blocks on ``n_tokens`` of width ``dim``:
    ``depth * (2 N D (4 D + 2 M) + 4 N^2 D)`` (= ``24 N D^2 + 4 N^2 D`` per block at M = 4D)."""
    n, d = n_tokens, dim
    return depth * (2 * n * d * (4 * d + 2 * mlp_hidden) + 4 * n * n * d)


def backbone_flops(
    batch: int,
    height: int,
    width: int,
    *,
    patch: int = 16,
    dim: int = 384,
    depth: int = 12,
    registers: int = 4,
    mlp_hidden: int = 1536,
    in_chans: int = 3,
) -> int:
    """EUPE ViT forward on ``batch`` images of ``height x width``: patch embedding + blocks."""
    patches = (height // patch) * (width // patch)
    embed = 2 * patches * in_chans * patch * patch * dim
    return batch * (embed + vit_blocks_flops(patches + 1 + registers, dim, depth, mlp_hidden))


def head_flops(
    batch: int,
    n_patches: int,
    *,
    dim: int = 384,
    out_dim: int = 512,
    depth: int = 2,
    mlp_hidden: int = 1536,
    registers: int = 0,
) -> int:
    """Language head on ``[CLS, (registers), patches]``: blocks + the final Linear on every token."""
    n = n_patches + 1 + registers
    return batch * (vit_blocks_flops(n, dim, depth, mlp_hidden) + 2 * n * dim * out_dim)


def lite_flops(
    batch: int,
    h: int,
    w: int,
    *,
    dv: int = 384,
    dl: int = 512,
    upscale: int = 2,
    tau: float = 0.0,
    attention: str = "sdpa",
) -> int:
    """ReSiReg Lite's matrix products (no prior), ``N = s^2 h w`` queries and keys per image.

    ``attention="sdpa"``: tau = 0, SDPA at the padded width ``max(dv, dl)``, ``4 B N^2 W``;
    tau > 0, the explicit chunks, ``2 B N^2 (dv + dl)``. ``"factorised"`` (any tau): per
    query block of :func:`resireg.method.lite.factorised_blocks`, the Gram rows of the coarse
    rows it reads, ``2 (c1 - c0) w * h w * dv``, and the product of the per-token weight sums
    with the coarse tokens, ``2 N h w dl`` (the language grid is the intermediates')."""
    n = upscale * upscale * h * w
    if attention == "factorised":
        blocks = lite.factorised_blocks(h, w, upscale)
        gram = sum(2 * (c1 - c0) * w * h * w * dv for _, _, c0, c1 in blocks)
        return batch * (gram + 2 * n * h * w * dl)
    if tau == 0:
        return 4 * batch * n * n * max(dv, dl)
    return 2 * batch * n * n * (dv + dl)


def kmeanspp_candidates(k: int) -> int:
    """Candidates per k-means++ step, as ``resireg.method.kmeans.kmeans_plusplus`` draws them."""
    return 2 + int(math.log(k))


def gram_flops(rows: int, dim: int, blocks: int = 4) -> int:
    """``resireg.method.pca.gram``: ``y^T y`` of ``[rows, dim]`` from the upper block triangle of
    ``blocks`` column slabs (one plain product when ``dim < 32 * blocks``)."""
    if blocks <= 1 or dim < 32 * blocks:
        return 2 * rows * dim * dim
    edges = [dim * i // blocks for i in range(blocks + 1)]
    sizes = [b - a for a, b in itertools.pairwise(edges)]
    return sum(2 * rows * sizes[i] * sizes[j] for i in range(blocks) for j in range(i, blocks))


def full_flops_breakdown(
    batch: int,
    h: int,
    w: int,
    *,
    iterations: float,
    distance_rows: float | None = None,
    dv: int = 384,
    dl: int = 512,
    upscale: int = 2,
    n_prototypes: int = 36,
    n_components: int | None = None,
) -> dict[str, float]:
    """ReSiReg Full's forward (no prior) by part, for a k-means of ``iterations`` Lloyd
    iterations that computed ``distance_rows`` point-to-all-centroids rows
    (``KMeansResult.dist_rows``; ``None``: plain Lloyd, ``n (iterations + 1)`` rows and no
    bound checks)."""
    s, k, hw = upscale, n_prototypes, h * w
    r = min(n_components if n_components is not None else k, dv)
    n = batch * s * s * hw
    moments = gram_flops(batch * hw, dv)
    if s > 1:  # U_a^T U_a of both axes (Cholesky factors applied elementwise), first moment
        moments += 2 * s * (h**3 + w**3) + 2 * hw * dv
    if distance_rows is None:
        kmeans = 2 * n * k * r * (iterations + 1)
    else:  # the rows the bounds could not vouch for, + one centroid separation per iteration
        kmeans = 2 * distance_rows * k * r + 2 * k * k * r * iterations
    return {
        "moments": moments,
        "projection": 2 * batch * hw * dv * r,
        # k-means++ products on the grid, then upsampled (resireg.method.full: the seeding's dots)
        "seeding": 2 * batch * hw * r * (1 + kmeanspp_candidates(k) * (k - 1)),
        "kmeans": kmeans,
        "mixing": 2 * n * k * dl,
    }


def full_flops(batch: int, h: int, w: int, *, iterations: float, **kwargs: Any) -> float:
    """ReSiReg Full's forward (no prior): the sum of :func:`full_flops_breakdown`."""
    return sum(full_flops_breakdown(batch, h, w, iterations=iterations, **kwargs).values())


# ------------------------------------------------------------------------------ measuring
def is_oom(exc: BaseException) -> bool:
    """An out-of-memory error of CUDA (``torch.OutOfMemoryError``) or of the CPU allocator."""
    if isinstance(exc, torch.OutOfMemoryError):
        return True
    text = str(exc).lower()
    return isinstance(exc, RuntimeError) and (
        "out of memory" in text or "can't allocate memory" in text
    )


def _sync(device: torch.device) -> None:
    if device.type == "cuda":
        torch.cuda.synchronize(device)


def _free(device: torch.device) -> None:
    gc.collect()
    if device.type == "cuda":
        torch.cuda.empty_cache()


def median_seconds(fn: Callable[[], Any], repeats: int, device: torch.device) -> float | None:
    """Median seconds of ``repeats`` calls of ``fn`` after one warm-up call, or ``None`` when
    a call runs out of memory (other errors propagate)."""
    try:
        fn()
        times = []
        for _ in range(repeats):
            _sync(device)
            start = time.perf_counter()
            fn()
            _sync(device)
            times.append(time.perf_counter() - start)
    except (torch.OutOfMemoryError, RuntimeError) as exc:
        if not is_oom(exc):
            raise
        _free(device)
        return None
    return statistics.median(times)


def matmul_gflops(
    m: int, k: int, n: int, dtype: torch.dtype, device: torch.device, repeats: int
) -> float | None:
    """GFLOP/s of a plain ``[m, k] @ [k, n]`` matmul (median of ``repeats``), None on OOM."""
    try:
        a = torch.randn(m, k, device=device, dtype=dtype)
        b = torch.randn(k, n, device=device, dtype=dtype)
    except (torch.OutOfMemoryError, RuntimeError) as exc:
        if not is_oom(exc):
            raise
        _free(device)
        return None
    seconds = median_seconds(lambda a=a, b=b: torch.matmul(a, b), repeats, device)
    return None if seconds is None else 2 * m * k * n / seconds / 1e9


@contextlib.contextmanager
def record_kmeans() -> Iterator[list[tuple[int, int | None]]]:
    """Collect ``(Lloyd iterations, distance rows or None)`` of every k-means that ReSiReg Full
    runs inside (``None`` where ``KMeansResult`` reports no rows: plain Lloyd)."""
    record: list[tuple[int, int | None]] = []
    original = reconstruct.kmeans

    def recording(*args: Any, **kwargs: Any) -> Any:
        result = original(*args, **kwargs)
        record.append((int(result.n_iter), getattr(result, "dist_rows", 0) or None))
        return result

    reconstruct.kmeans = recording
    try:
        yield record
    finally:
        reconstruct.kmeans = original


# --------------------------------------------------------------------------- the benchmark
def build_reconstructions() -> dict[str, nn.Module]:
    """Lite and Full with the defaults of ``conf/resireg/default.yaml``."""
    cfg = resireg_defaults()
    return {
        "lite": build_variant("lite", **cfg["lite"]),
        "full": build_variant("full", **cfg["full"]),
    }


def _parse(argv: Sequence[str] | None) -> argparse.Namespace:
    parser = argparse.ArgumentParser(
        description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter
    )
    parser.add_argument("--device", choices=["auto", "cpu", "cuda"], default="auto")
    parser.add_argument(
        "--batch-sizes", type=int, nargs="+", default=None,
        help=f"default {list(CPU_BATCH_SIZES)} on CPU, {list(CUDA_BATCH_SIZES)} on CUDA",
    )  # fmt: skip
    parser.add_argument("--repeats", type=int, default=None, help="default 3 on CPU, 5 on CUDA")
    parser.add_argument("--height", type=int, default=576)
    parser.add_argument("--width", type=int, default=768)
    parser.add_argument("--out", type=Path, default=Path("throughput.png"))
    parser.add_argument(
        "--peak-size", type=int, default=None,
        help="side of the square matmul of the 'of peak' column (default 2048 CPU, 8192 CUDA)",
    )  # fmt: skip
    parser.add_argument("--tiny", action="store_true", help="the tests' tiny models")
    parser.add_argument("--seed", type=int, default=0)
    args = parser.parse_args(argv)
    if args.device == "auto":
        args.device = "cuda" if torch.cuda.is_available() else "cpu"
    if args.device == "cuda" and not torch.cuda.is_available():
        parser.error("--device cuda: CUDA is not available")
    cuda = args.device == "cuda"
    if args.batch_sizes is None:
        args.batch_sizes = list(CUDA_BATCH_SIZES if cuda else CPU_BATCH_SIZES)
    if args.repeats is None:
        args.repeats = 5 if cuda else 3
    if args.peak_size is None:
        args.peak_size = 8192 if cuda else 2048
    if min(args.batch_sizes) < 1 or args.repeats < 1:
        parser.error("batch sizes and --repeats must be >= 1")
    args.batch_sizes = sorted(set(args.batch_sizes))
    return args


def _fmt(value: float | None, spec: str) -> str:
    return "OOM" if value is None else format(value, spec)


def _dtype_name(dtype: torch.dtype) -> str:
    return str(dtype).removeprefix("torch.")


def plot(rows: list[dict], batch_sizes: list[int], out: Path, title: str) -> Path:
    """Images per second against batch size, one line per variant, log-x; a PNG at ``out``."""
    from matplotlib.backends.backend_agg import FigureCanvasAgg
    from matplotlib.figure import Figure
    from matplotlib.ticker import NullLocator

    fig = Figure(figsize=FIGSIZE, dpi=DPI, layout="constrained")
    FigureCanvasAgg(fig)
    ax = fig.add_subplot()
    for name in VARIANT_NAMES:
        fps = {r["batch"]: r["images_per_s"] for r in rows if r["variant"] == name}
        ys = [math.nan if fps.get(b) is None else fps[b] for b in batch_sizes]
        ax.plot(batch_sizes, ys, marker="o", label=name)
    ax.set_xscale("log", base=2)
    ax.set_xticks(batch_sizes, labels=[str(b) for b in batch_sizes])
    ax.xaxis.set_minor_locator(NullLocator())
    ax.set_xlabel("batch size")
    ax.set_ylabel("images / s")
    ax.set_ylim(bottom=0)
    ax.set_title(title, fontsize=9)
    ax.grid(True, alpha=0.3)
    ax.legend()
    out.parent.mkdir(parents=True, exist_ok=True)
    fig.savefig(out, dpi=DPI)
    return out


def main(argv: Sequence[str] | None = None) -> dict[str, Any]:
    """Run the protocol; print both tables, write the plot. Returns ``{"throughput": rows,
    "stages": rows, "plot": path, "flops_per_image": {...}}``."""
    args = _parse(argv)
    device = torch.device(args.device)
    torch.manual_seed(args.seed)
    model = build_model(args.tiny).to(device)
    recon = build_reconstructions()
    variants: dict[str, nn.Module] = {
        VARIANT_NAMES[0]: build_variant("bb"),
        VARIANT_NAMES[1]: recon["lite"],
        VARIANT_NAMES[2]: recon["full"],
    }
    lite, full = recon["lite"], recon["full"]
    bb = model.backbone
    patch, dim, depth = bb.patch_size, bb.embed_dim, bb.depth
    mlp_hidden = bb.model.blocks[0].mlp.fc1.out_features
    head = model.head
    head_hidden = head.blocks[0].mlp.fc1.out_features
    h, w = args.height // patch, args.width // patch
    if h * patch != args.height or w * patch != args.width:
        raise SystemExit(f"--height/--width must be multiples of the patch size {patch}")
    cuda = device.type == "cuda"
    compute_dtype = torch.bfloat16 if cuda else torch.float32
    autocast = (
        (lambda: torch.autocast("cuda", dtype=torch.bfloat16)) if cuda else contextlib.nullcontext
    )
    n_params = sum(p.numel() for p in [*bb.parameters(), *head.parameters()])
    threads = "" if cuda else f", {torch.get_num_threads()} threads"
    where = torch.cuda.get_device_name(device) if cuda else "CPU"
    print(
        f"{where}{threads}; {'tiny models' if args.tiny else 'the 25M VLM, EUPE ViT-S/16 + head'} "
        f"({n_params / 1e6:.2f}M backbone + head), canvas {args.height} x {args.width} "
        f"({h} x {w} patches), {_dtype_name(compute_dtype)}"
        f"{' autocast' if cuda else ''}, median of {args.repeats} after a warm-up"
    )
    print(f"Lite: {lite.extra_repr()}; Full: {full.extra_repr()}\n")

    def flops_of(
        stage: str, batch: int, iterations: float = 0.0, rows: float | None = None
    ) -> float:
        if stage == "backbone":
            return backbone_flops(
                batch, args.height, args.width, patch=patch, dim=dim, depth=depth,
                registers=bb.num_registers, mlp_hidden=mlp_hidden,
            )  # fmt: skip
        if stage == "head":
            return head_flops(
                batch, h * w, dim=dim, out_dim=head.out_dim, depth=len(head.blocks),
                mlp_hidden=head_hidden, registers=bb.num_registers if head.use_registers else 0,
            )  # fmt: skip
        if stage == "lite":
            return lite_flops(
                batch, h, w, dv=dim, dl=head.out_dim, upscale=lite.upscale, tau=lite.tau,
                attention=lite.resolve_attention(device),
            )  # fmt: skip
        return full_flops(
            batch, h, w, iterations=iterations, distance_rows=rows, dv=dim, dl=head.out_dim,
            upscale=full.upscale,
            n_prototypes=full.resolve_prototypes(batch), n_components=full.n_components,
        )  # fmt: skip

    # ---- table 1: throughput
    gen = torch.Generator(device=device).manual_seed(args.seed)
    rows: list[dict] = []
    first_oom: dict[str, int] = {}
    for b in args.batch_sizes:
        fps: dict[str, float | None] = {}
        for name, variant in variants.items():
            if name in first_oom:
                fps[name] = None
                rows.append({"batch": b, "variant": name, "images_per_s": None,
                             "ratio": None, "status": "OOM*"})  # fmt: skip
                continue
            try:
                x = torch.randn(b, 3, args.height, args.width, device=device, generator=gen)
            except (torch.OutOfMemoryError, RuntimeError) as exc:
                if not is_oom(exc):
                    raise
                x = None
            seconds = None
            if x is not None:

                def run(x=x, variant=variant):
                    with torch.no_grad(), autocast():
                        return model.encode_image(x, variant, normalized=True)

                seconds = median_seconds(run, args.repeats, device)
            del x
            _free(device)
            fps[name] = None if seconds is None else b / seconds
            if seconds is None:
                first_oom[name] = b
            alone = fps[VARIANT_NAMES[0]]
            ratio = None if fps[name] is None or alone is None else fps[name] / alone
            rows.append({"batch": b, "variant": name, "images_per_s": fps[name],
                         "ratio": ratio, "status": "OOM" if seconds is None else "ok"})  # fmt: skip
    print("| batch | variant | images/s | vs VLM alone |")
    print("|---:|---|---:|---:|")
    for r in rows:
        ips = r["status"] if r["images_per_s"] is None else f"{r['images_per_s']:.3g}"
        ratio = "-" if r["ratio"] is None else f"{r['ratio']:.2f}"
        print(f"| {r['batch']} | {r['variant']} | {ips} | {ratio} |")
    if any(r["status"] == "OOM*" for r in rows):
        print("\nOOM*: not run, a smaller batch of this variant ran out of memory.")

    # ---- table 2: stages against plain matmuls
    fits = [b for b in args.batch_sizes if all(b < first_oom.get(n, b + 1) for n in VARIANT_NAMES)]
    stage_batches = sorted({1, *fits[-1:]})
    peaks: dict[torch.dtype, float | None] = {}

    def peak(dtype: torch.dtype) -> float | None:
        if dtype not in peaks:
            s = args.peak_size
            peaks[dtype] = matmul_gflops(s, s, s, dtype, device, args.repeats)
        return peaks[dtype]

    def stage_rows(b: int) -> list[dict]:
        """Time the four stages on one batch of ``b`` images (its tensors die on return)."""
        try:
            x = torch.randn(b, 3, args.height, args.width, device=device, generator=gen)
            with torch.no_grad(), autocast():
                feats = model.backbone(x)
                language = model.head(feats).patches
        except (torch.OutOfMemoryError, RuntimeError) as exc:
            if not is_oom(exc):
                raise
            _free(device)
            print(f"\nbatch {b}: the backbone and head ran out of memory; no stage timings")
            return []
        inter = feats.intermediates
        lite_dtype = torch.promote_types(inter.dtype, language.dtype)
        n_tok = h * w + 1 + bb.num_registers
        n_head = h * w + 1 + (bb.num_registers if head.use_registers else 0)
        n_up = lite.upscale**2 * h * w
        lite_path = lite.resolve_attention(device)
        if lite_path == "factorised":  # its main product: weight sums [N, h w] x tokens
            lite_dtype = torch.promote_types(lite_dtype, torch.float32)
            lite_matmul = (n_up, h * w, head.out_dim)
        else:  # one image's scores [N, W] x [W, N]
            lite_matmul = (n_up, max(dim, head.out_dim), n_up)
        k_full = full.resolve_prototypes(b)
        r_full = min(full.n_components or k_full, dim)
        # stage, label, callable, dtype of its products, the similar matmul (m, k, n)
        plan = [
            ("backbone", "backbone (EUPE ViT)", lambda: model.backbone(x), compute_dtype,
             (b * n_tok, dim, dim)),
            ("head", "language head", lambda: model.head(feats), compute_dtype,
             (b * n_head, dim, dim)),
            ("lite", f"ReSiReg Lite ({lite_path})", lambda: lite(inter, language), lite_dtype,
             lite_matmul),
            ("full", "ReSiReg Full (PCA + k-means + mixing)", lambda: full(inter, language),
             torch.float32, (b * full.upscale**2 * h * w, r_full, k_full)),
        ]  # fmt: skip
        out = []
        for stage, label, fn, dtype, (m, k, n) in plan:

            def call(fn=fn):
                with torch.no_grad(), autocast():
                    return fn()

            with record_kmeans() as runs:
                seconds = median_seconds(call, args.repeats, device)
            iterations = statistics.mean(i for i, _ in runs) if runs else 0.0
            rows = None
            if runs and all(r is not None for _, r in runs):
                rows = statistics.mean(r for _, r in runs)
            flops = flops_of(stage, b, iterations, rows)
            achieved = None if seconds is None else flops / seconds / 1e9
            ref = matmul_gflops(m, k, n, dtype, device, args.repeats)
            top = peak(dtype)
            out.append({
                "batch": b, "stage": stage, "label": label, "dtype": _dtype_name(dtype),
                "gflop_per_image": flops / b / 1e9, "seconds": seconds, "gflops": achieved,
                "matmul_shape": (m, k, n), "matmul_gflops": ref,
                "fraction": None if achieved is None or not ref else achieved / ref,
                "peak_gflops": top,
                "of_peak": None if achieved is None or not top else achieved / top,
                "iterations": iterations if stage == "full" else None,
                # k-means distance rows in passes over all n points (plain Lloyd: I + 1)
                "distance_passes": (
                    (iterations + 1 if rows is None else rows / (b * full.upscale**2 * h * w))
                    if stage == "full" else None
                ),
            })  # fmt: skip
        return out

    stages: list[dict] = []
    for b in stage_batches:
        stages.extend(stage_rows(b))
        _free(device)

    print("\n| batch | stage | dtype | GFLOP/image | seconds | GFLOP/s | plain matmul [m,k]x[k,n] "
          "| matmul GFLOP/s | fraction | of peak |")  # fmt: skip
    print("|---:|---|---|---:|---:|---:|---|---:|---:|---:|")
    for s in stages:
        m, k, n = s["matmul_shape"]
        label = s["label"]
        if s["stage"] == "full":
            label += f", {s['iterations']:.0f} iter., {s['distance_passes']:.1f} distance passes"
        print(
            f"| {s['batch']} | {label} | {s['dtype']} | {s['gflop_per_image']:.3g} "
            f"| {_fmt(s['seconds'], '.3g')} | {_fmt(s['gflops'], '.3g')} | [{m},{k}]x[{k},{n}] "
            f"| {_fmt(s['matmul_gflops'], '.3g')} | {_fmt(s['fraction'], '.2f')} "
            f"| {_fmt(s['of_peak'], '.2f')} |"
        )
    for dtype, value in peaks.items():
        print(
            f"\npeak: square matmul {args.peak_size}^3 in {_dtype_name(dtype)}: "
            f"{_fmt(value, '.4g')} GFLOP/s",
            end="",
        )
    print()

    per_image = {
        "backbone": flops_of("backbone", 1) / 1e9,
        "head": flops_of("head", 1) / 1e9,
        "lite": flops_of("lite", 1) / 1e9,
    }
    title = (
        f"{where}, {args.height} x {args.width}, "
        f"{'bf16 autocast' if cuda else 'fp32'}{', tiny models' if args.tiny else ''}"
    )
    out = plot(rows, args.batch_sizes, args.out, title)
    print(f"\nplot: {out}")
    return {"throughput": rows, "stages": stages, "plot": out, "flops_per_image": per_image}


if __name__ == "__main__":
    main()
