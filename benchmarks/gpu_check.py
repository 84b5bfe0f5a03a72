"""The GPU check: one command that measures, on one CUDA device in a few minutes, what the CPU
machines cannot (issue 26, item 5). Random weights of the real architectures, no network.

    python benchmarks/gpu_check.py --out gpu_check [--cpu-reference cpu_clustering.json]
    python benchmarks/gpu_check.py --dry-run --out /tmp/gpu_check      # every section, tiny, CPU
    python benchmarks/gpu_check.py --write-cpu-reference cpu_clustering.json   # on a CPU machine

Sections (each row records its status; an out-of-memory or an ineligible kernel is a row,
not a crash):

1. **Peak**: a square matmul (8192^3) in bf16 and fp32, the rates every "of bf16 peak"
   column divides by.
2. **Throughput protocol** (``bench_throughput.main``: 25M VLM alone / + Lite / + Full,
   576 x 768, bf16 autocast, batch 1-32, images/s and the ratio to the model alone; its
   per-stage table with FLOP/s), each stage also as a fraction of the bf16 peak.
3. **Lite's computations** on one batch of the 25M features (batch 8, 576 x 768, fp32 as
   the protocol gives Lite, and the features cast to bf16): SDPA with each CUDA backend forced
   (``torch.nn.attention.sdpa_kernel``: flash, memory-efficient, cuDNN, math; flash and cuDNN
   need q/k/v widths <= 256, so at Lite's padded 512 they are expected to be rejected, see
   docs/method.md#resireg-lite) and the factorised computation; seconds, GFLOP/s, fraction of
   the bf16 peak, max difference from the fp32 factorised output.
4. **Full's clustering** (``ReSiRegFull.assign``, 8 images, 55,296 points) on the GPU, on this
   host's CPU, and (``--cpu-reference``) on the CPU machine that wrote the reference JSON.
5. **One bf16 training step** of the 25M model (EUPE ViT-S/16 + the 2-block head, 512 px
   crops, batch 48, AdamW) without and with the stage-1 teacher of RADSeg's size (a local
   ``torch.hub`` repository exposing ``radseg_encoder``: a ViT-B/16, the size of RADIO v3-B,
   and a 2-layer MLP to SigLIP 2's 1152 channels, random init, through the real
   ``RadSegTeacher``): images/s, peak memory, matrix-product FLOP per step
   (``FlopCounterMode``, one untimed step) and their fraction of the bf16 peak.

Writes ``<out>/gpu_check.json`` (every figure) and ``<out>/gpu_check.md`` (the tables).
``--dry-run`` runs every section at tiny size on the CPU (tiny models, 64 x 96 canvas), so
the script is known to work before a GPU is lent (tests/project/test_gpu_check.py).
"""

from __future__ import annotations

import argparse
import contextlib
import functools
import json
import platform
import sys
import tempfile
import textwrap
import time
from collections.abc import Callable
from pathlib import Path
from typing import Any

import torch
from torch.nn.attention import SDPBackend, sdpa_kernel

import bench_throughput as bt
from _common import CONF, build_model, load_yaml

#: SDPA backends tried for Lite (CUDA; on the CPU only flash and math exist).
SDPA_BACKENDS = {
    "flash": SDPBackend.FLASH_ATTENTION,
    "efficient": SDPBackend.EFFICIENT_ATTENTION,
    "cudnn": SDPBackend.CUDNN_ATTENTION,
    "math": SDPBackend.MATH,
}

#: The stand-in for RADSeg's ``radseg_encoder`` (RADSeg-OVSS/RADSeg ``hubconf.py``): a plain
#: object (no ``.to()``) that builds its modules on ``device`` like ``RADSegEncoder``; timm's
#: ViT-B/16 (RADIO v3-B's size: 768 wide, 12 blocks) and an MLP to 1152 channels (SigLIP 2).
RADSEG_HUBCONF = """
dependencies = ["torch", "timm"]
import timm
import torch
from torch import nn

WIDTH = {width}
DEPTH = {depth}
HEADS = {heads}
LANG = {lang}


class _Encoder:
    def __init__(self, model_version, lang_model, slide_crop, device=None, **kwargs):
        self.device = torch.device(device or "cpu")
        self.vit = timm.create_model(
            "vit_base_patch16_224", pretrained=False, num_classes=0, global_pool="",
            embed_dim=WIDTH, depth=DEPTH, num_heads=HEADS, dynamic_img_size=True,
        ).to(self.device).eval()
        self.lang = nn.Sequential(
            nn.Linear(WIDTH, 2 * WIDTH), nn.GELU(), nn.Linear(2 * WIDTH, LANG)
        ).to(self.device).eval()

    def get_nearest_size(self, h, w):
        return max(16, (h // 16) * 16), max(16, (w // 16) * 16)

    def encode_image_to_feat_map(self, rgb):
        tokens = self.vit.forward_features(rgb)[:, self.vit.num_prefix_tokens:]
        b, n, c = tokens.shape
        h, w = rgb.shape[-2] // 16, rgb.shape[-1] // 16
        return tokens.transpose(1, 2).reshape(b, c, h, w)

    def align_spatial_features_with_language(self, feat_map):
        return self.lang(feat_map.permute(0, 2, 3, 1)).permute(0, 3, 1, 2)


def radseg_encoder(model_version="c-radio_v3-b", lang_model="siglip2", **kwargs):
    return _Encoder(model_version, lang_model, **kwargs)
"""


def _status(fn: Callable[[], Any]) -> tuple[Any, str]:
    """``(fn(), "ok")``, or ``(None, "OOM")`` / ``(None, "not eligible: ...")`` for an
    out-of-memory error or a kernel that refuses the inputs (other errors propagate)."""
    try:
        return fn(), "ok"
    except (torch.OutOfMemoryError, RuntimeError) as exc:
        if bt.is_oom(exc):
            return None, "OOM"
        text = str(exc).splitlines()[0][:100]
        refused = ("No available kernel", "No viable backend", "not supported")
        if any(r.lower() in str(exc).lower() for r in refused):
            return None, f"not eligible: {text}"
        raise


def _of(value: float | None, peak: float | None) -> float | None:
    return None if value is None or not peak else value / peak


# --------------------------------------------------------------------------- sections
def peaks(device: torch.device, size: int, repeats: int) -> dict[str, float | None]:
    """GFLOP/s of a square matmul in bf16 and fp32."""
    return {
        name: bt.matmul_gflops(size, size, size, dtype, device, repeats)
        for name, dtype in (("bfloat16", torch.bfloat16), ("float32", torch.float32))
    }


def throughput(args: argparse.Namespace, peak_bf16: float | None) -> dict[str, Any]:
    """The throughput protocol of ``bench_throughput`` (its tables are printed as it runs)."""
    argv = ["--device", args.device, "--repeats", str(args.repeats), "--out",
            str(args.out / "throughput.png"), "--batch-sizes", *map(str, args.batch_sizes)]  # fmt: skip
    if args.dry_run:
        argv += ["--tiny", "--height", "64", "--width", "96", "--peak-size", "64"]
    result = bt.main(argv)
    for stage in result["stages"]:
        stage["of_bf16_peak"] = _of(stage["gflops"], peak_bf16)
    return {"throughput": result["throughput"], "stages": result["stages"]}


def _features(args: argparse.Namespace, images: int) -> tuple[torch.Tensor, torch.Tensor]:
    """The 25M architecture's (or the tiny one's) features of ``images`` random images. Weights
    and images are drawn on the CPU, so every device (and the CPU reference) sees the same."""
    torch.manual_seed(0)
    model = build_model(args.dry_run).to(args.device)
    g = torch.Generator().manual_seed(0)
    x = torch.randn(images, 3, args.height, args.width, generator=g).to(args.device)
    with torch.no_grad(), _autocast(args):
        out = model.encode(x)
    return out.intermediates.float(), out.language.float()


def _autocast(args: argparse.Namespace):
    if args.device == "cuda":
        return torch.autocast("cuda", dtype=torch.bfloat16)
    return contextlib.nullcontext()


def lite(args: argparse.Namespace, peak_bf16: float | None) -> list[dict[str, Any]]:
    """Lite by every SDPA backend and factorised, fp32 and bf16 inputs."""
    from resireg.method.lite import ReSiRegLite

    inter, lang = _features(args, args.lite_batch)
    b, dv, h, w = inter.shape
    dl = lang.shape[1]
    device = torch.device(args.device)
    reference = ReSiRegLite(attention="factorised")(inter, lang).float()
    rows = []
    for dtype in (torch.float32, torch.bfloat16):
        q, v = inter.to(dtype), lang.to(dtype)
        plans: list[tuple[str, str, Callable[[], Any]]] = []
        for name, backend in SDPA_BACKENDS.items():
            sdpa = ReSiRegLite(attention="sdpa")

            def call(sdpa=sdpa, backend=backend, q=q, v=v):
                with torch.no_grad(), sdpa_kernel([backend]):
                    return sdpa(q, v)

            plans.append(("sdpa", name, call))
        fact = ReSiRegLite(attention="factorised")
        plans.append(("factorised", "", lambda fact=fact, q=q, v=v: fact(q, v)))
        for path, backend, call in plans:
            out, status = _status(call)
            seconds = None
            if out is not None:
                seconds = bt.median_seconds(call, args.repeats, device)
                status = "ok" if seconds is not None else "OOM"
            flops = bt.lite_flops(b, h, w, dv=dv, dl=dl, attention=path)
            gflops = None if seconds is None else flops / seconds / 1e9
            diff = None if out is None else float((out.float() - reference).abs().max())
            rows.append({
                "dtype": bt._dtype_name(dtype), "path": path, "backend": backend,
                "status": status, "seconds": seconds, "gflop": flops / 1e9, "gflops": gflops,
                "of_bf16_peak": _of(gflops, peak_bf16), "max_abs_diff": diff,
            })  # fmt: skip
            del out
            bt._free(device)
    return rows


def cpu_clustering(features: tuple[torch.Tensor, torch.Tensor], repeats: int) -> dict[str, Any]:
    """Full's clustering of ``features`` on this machine's CPU: median seconds."""
    full = bt.build_reconstructions()["full"]
    inter = features[0].cpu()
    seconds = bt.median_seconds(lambda: full.assign(inter), repeats, torch.device("cpu"))
    return {"host": platform.processor() or platform.machine(), "threads": torch.get_num_threads(),
            "points": int(inter.shape[0] * inter.shape[2] * inter.shape[3] * full.upscale**2),
            "seconds": seconds}  # fmt: skip


def clustering(args: argparse.Namespace) -> dict[str, Any]:
    """Full's clustering on the device, this host's CPU and the reference CPU."""
    features = _features(args, args.cluster_batch)
    full = bt.build_reconstructions()["full"]
    device = torch.device(args.device)
    inter = features[0]
    on_device = bt.median_seconds(lambda: full.assign(inter), args.repeats, device)
    host = cpu_clustering(features, args.repeats)
    result: dict[str, Any] = {"device_seconds": on_device, "host_cpu": host, "reference_cpu": None}
    if args.cpu_reference:
        result["reference_cpu"] = json.loads(Path(args.cpu_reference).read_text())
    return result


def _teacher_repo(root: Path, tiny: bool) -> Path:
    """A local torch.hub repository exposing ``radseg_encoder`` (:data:`RADSEG_HUBCONF`).

    The teacher loads through RADSeg's loader, whose offline checks need what the real RADSeg
    reads from torch's hub cache (NVlabs/RADIO's code, RADIO's checkpoint); the stand-in reads
    neither, so ``root / "hub"`` holds an empty copy of each, to be passed to ``torch.hub.set_dir``.
    """
    from resireg.models.hub import PINNED_REFS
    from resireg.models.zoo.radio import RADIO_CHECKPOINTS

    # the folder torch.hub keeps NVlabs/RADIO in at the pinned commit
    (root / "hub" / f"NVlabs_RADIO_{PINNED_REFS['NVlabs/RADIO']}").mkdir(
        parents=True, exist_ok=True
    )
    (root / "hub" / "checkpoints").mkdir(exist_ok=True)
    (root / "hub" / "checkpoints" / RADIO_CHECKPOINTS["c-radio_v3-b"]).touch()
    repo = root / "RADSeg"
    repo.mkdir(parents=True, exist_ok=True)
    size = {"width": 64, "depth": 2, "heads": 2, "lang": 48} if tiny else {
        "width": 768, "depth": 12, "heads": 12, "lang": 1152}  # fmt: skip
    (repo / "hubconf.py").write_text(textwrap.dedent(RADSEG_HUBCONF.format(**size)))
    return repo


def _train_module(args: argparse.Namespace, teacher: dict | None):
    from _common import TINY_BACKBONE, TINY_HEAD, TINY_TEXT
    from resireg_train.training.module import ResiregModule

    if args.dry_run:
        backbone, head = TINY_BACKBONE, TINY_HEAD
    else:
        backbone = {**load_yaml(CONF / "model" / "backbone" / "eupe_vit_s16.yaml"), "weights": None}
        head = dict(load_yaml(CONF / "model" / "vlm25m.yaml")["head"])
    model = load_yaml(CONF / "model" / "vlm25m.yaml")  # the training settings, no warm-up
    loss = {"contrastive": {"scale": model["loss"]["contrastive"]["scale"], "warmup_epochs": 0},
            "distill": {"scale": 0.1 if teacher else 0.0, "warmup_epochs": 0}}  # fmt: skip
    optimizer = functools.partial(torch.optim.AdamW, lr=model["optimizer"]["lr"])
    module = ResiregModule(backbone, head, TINY_TEXT, teacher=teacher, loss=loss,
                           optimizer=optimizer, scheduler=dict(model["scheduler"]),
                           logit_scale=dict(model["logit_scale"]), steps_per_epoch=1000)  # fmt: skip
    module = module.to(args.device)
    module.setup("fit")
    return module


def train_step(args: argparse.Namespace, peak_bf16: float | None) -> list[dict[str, Any]]:
    """One bf16 training step of the 25M model without and with the RADSeg-sized teacher."""
    from torch.utils.flop_counter import FlopCounterMode

    device = torch.device(args.device)
    cuda = device.type == "cuda"
    rows = []
    hub_dir = torch.hub.get_dir()
    with tempfile.TemporaryDirectory() as tmp:
        repo = _teacher_repo(Path(tmp), args.dry_run)
        torch.hub.set_dir(str(Path(tmp) / "hub"))
        for label, teacher in (
            ("without teacher", None),
            ("with RADSeg-sized teacher", {"kind": "radseg", "repo": str(repo), "source": "local"}),
        ):
            torch.manual_seed(0)
            module = _train_module(args, teacher)
            optimizer, scheduler = module.build_optimizer(100)
            module.train()
            g = torch.Generator(device=device).manual_seed(0)
            batch = {
                "image": torch.randn(args.train_batch, 3, args.crop, args.crop, device=device,
                                     generator=g),
                "caption": [f"a photo of thing {i % 7}" for i in range(args.train_batch)],
            }  # fmt: skip

            def step(module=module, optimizer=optimizer, scheduler=scheduler, batch=batch):
                with torch.autocast(device.type, dtype=torch.bfloat16):
                    loss, _ = module.losses(batch, 0)
                optimizer.zero_grad(set_to_none=True)
                loss.backward()
                optimizer.step()
                scheduler.step()

            counter = FlopCounterMode(display=False)
            with counter:
                step()
            if cuda:
                torch.cuda.reset_peak_memory_stats(device)
            seconds = bt.median_seconds(step, args.repeats, device)
            peak_mem = torch.cuda.max_memory_allocated(device) if cuda else None
            flops = counter.get_total_flops()
            gflops = None if seconds is None else flops / seconds / 1e9
            rows.append({
                "step": label, "batch": args.train_batch, "crop": args.crop,
                "status": "ok" if seconds is not None else "OOM", "seconds": seconds,
                "images_per_s": None if seconds is None else args.train_batch / seconds,
                "peak_memory_gib": None if peak_mem is None else peak_mem / 2**30,
                "gflop_per_step": flops / 1e9, "gflops": gflops,
                "of_bf16_peak": _of(gflops, peak_bf16),
            })  # fmt: skip
            del module, optimizer, batch
            bt._free(device)
        torch.hub.set_dir(hub_dir)
    return rows


# ------------------------------------------------------------------------------ report
def _cell(value: Any, spec: str = ".3g") -> str:
    if value is None:
        return "-"
    if isinstance(value, float):
        return format(value, spec)
    return str(value)


def markdown(report: dict[str, Any]) -> str:
    """The report's tables as markdown."""
    lines = [f"# GPU check: {report['device']['name']}", "",
             f"torch {report['device']['torch']}, CUDA {report['device']['cuda']}, "
             f"{'dry run (tiny, CPU)' if report['dry_run'] else 'full size'}; "
             f"peak bf16 {_cell(report['peak']['bfloat16'], '.4g')} GFLOP/s, fp32 "
             f"{_cell(report['peak']['float32'], '.4g')} GFLOP/s", "",
             "## Throughput protocol", "", "| batch | variant | images/s | vs VLM alone |",
             "|---:|---|---:|---:|"]  # fmt: skip
    for r in report["throughput"]["throughput"]:
        lines.append(f"| {r['batch']} | {r['variant']} | {_cell(r['images_per_s'])} | "
                     f"{_cell(r['ratio'], '.2f')} |")  # fmt: skip
    lines += ["", "| batch | stage | dtype | GFLOP/image | seconds | GFLOP/s | of bf16 peak |",
              "|---:|---|---|---:|---:|---:|---:|"]  # fmt: skip
    for s in report["throughput"]["stages"]:
        lines.append(f"| {s['batch']} | {s['label']} | {s['dtype']} | {_cell(s['gflop_per_image'])} "
                     f"| {_cell(s['seconds'])} | {_cell(s['gflops'])} | "
                     f"{_cell(s['of_bf16_peak'], '.3f')} |")  # fmt: skip
    lines += ["", "## Lite: SDPA backends and the factorised computation", "",
              "| dtype | path | status | seconds | GFLOP | GFLOP/s | of bf16 peak | max diff |",
              "|---|---|---|---:|---:|---:|---:|---:|"]  # fmt: skip
    for r in report["lite"]:
        path = f"sdpa ({r['backend']})" if r["path"] == "sdpa" else r["path"]
        lines.append(f"| {r['dtype']} | {path} | {r['status']} | {_cell(r['seconds'])} | "
                     f"{_cell(r['gflop'])} | {_cell(r['gflops'])} | "
                     f"{_cell(r['of_bf16_peak'], '.3f')} | {_cell(r['max_abs_diff'], '.2e')} |")  # fmt: skip
    c = report["clustering"]
    ref = c["reference_cpu"]
    lines += ["", "## Full's clustering (`ReSiRegFull.assign`)", "",
              "| where | seconds | x device |", "|---|---:|---:|",
              f"| device | {_cell(c['device_seconds'])} | 1.00 |",
              f"| this host's CPU ({c['host_cpu']['threads']} threads) | "
              f"{_cell(c['host_cpu']['seconds'])} | "
              f"{_cell(_ratio(c['host_cpu']['seconds'], c['device_seconds']), '.2f')} |"]  # fmt: skip
    if ref:
        lines.append(f"| reference CPU ({ref.get('host')}, {ref.get('threads')} threads) | "
                     f"{_cell(ref.get('seconds'))} | "
                     f"{_cell(_ratio(ref.get('seconds'), c['device_seconds']), '.2f')} |")  # fmt: skip
    lines += ["", "## One bf16 training step", "",
              "| step | batch x crop | images/s | peak memory GiB | GFLOP/step | of bf16 peak |",
              "|---|---|---:|---:|---:|---:|"]  # fmt: skip
    for r in report["train"]:
        lines.append(f"| {r['step']} | {r['batch']} x {r['crop']} | {_cell(r['images_per_s'])} | "
                     f"{_cell(r['peak_memory_gib'])} | {_cell(r['gflop_per_step'])} | "
                     f"{_cell(r['of_bf16_peak'], '.3f')} |")  # fmt: skip
    lines.append(f"\nwall time {report['seconds']:.0f} s")
    return "\n".join(lines) + "\n"


def _ratio(a: float | None, b: float | None) -> float | None:
    return None if a is None or not b else a / b


def _parse(argv: list[str] | None) -> argparse.Namespace:
    parser = argparse.ArgumentParser(
        description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter
    )
    parser.add_argument("--out", type=Path, default=Path("gpu_check"))
    parser.add_argument("--dry-run", action="store_true", help="every section, tiny, on the CPU")
    parser.add_argument("--cpu-reference", default=None, help="JSON of --write-cpu-reference")
    parser.add_argument(
        "--write-cpu-reference", type=Path, default=None,
        help="only time Full's clustering on this machine's CPU and write it as JSON",
    )  # fmt: skip
    parser.add_argument("--repeats", type=int, default=None, help="default 5 (dry run 1)")
    args = parser.parse_args(argv)
    cuda = torch.cuda.is_available() and not args.dry_run
    args.device = "cuda" if cuda else "cpu"
    if not cuda and not args.dry_run and args.write_cpu_reference is None:
        parser.error("no CUDA device: run with --dry-run (or --write-cpu-reference FILE)")
    tiny = args.dry_run
    args.repeats = args.repeats or (1 if tiny else 5)
    args.height, args.width = (64, 96) if tiny else (576, 768)
    args.batch_sizes = [1] if tiny else list(bt.CUDA_BATCH_SIZES)
    args.lite_batch = 2 if tiny else 8
    args.cluster_batch = 2 if tiny else 8
    args.train_batch, args.crop = (4, 64) if tiny else (48, 512)
    args.peak_size = 64 if tiny else 8192
    return args


def main(argv: list[str] | None = None) -> dict[str, Any]:
    args = _parse(argv)
    start = time.perf_counter()
    if args.write_cpu_reference is not None:
        features = _features(args, args.cluster_batch)
        reference = cpu_clustering(features, args.repeats)
        args.write_cpu_reference.write_text(json.dumps(reference, indent=2))
        print(json.dumps(reference))
        return reference
    args.out.mkdir(parents=True, exist_ok=True)
    device = torch.device(args.device)
    name = torch.cuda.get_device_name(device) if device.type == "cuda" else "CPU"
    report: dict[str, Any] = {
        "device": {"name": name, "torch": torch.__version__, "cuda": torch.version.cuda,
                   "python": sys.version.split()[0]},
        "dry_run": args.dry_run,
    }  # fmt: skip
    report["peak"] = peaks(device, args.peak_size, args.repeats)
    peak_bf16 = report["peak"]["bfloat16"]
    sections: dict[str, Callable[[], Any]] = {
        "throughput": lambda: throughput(args, peak_bf16),
        "lite": lambda: lite(args, peak_bf16),
        "clustering": lambda: clustering(args),
        "train": lambda: train_step(args, peak_bf16),
    }
    timings = {}
    for key, run in sections.items():
        t0 = time.perf_counter()
        report[key] = run()
        timings[key] = time.perf_counter() - t0
        print(f"[gpu_check] {key}: {timings[key]:.1f} s", flush=True)
    report["section_seconds"] = timings
    report["seconds"] = time.perf_counter() - start
    (args.out / "gpu_check.json").write_text(json.dumps(report, indent=2, default=str))
    text = markdown(report)
    (args.out / "gpu_check.md").write_text(text)
    print("\n" + text)
    return report


if __name__ == "__main__":
    main()
