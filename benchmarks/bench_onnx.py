"""onnxruntime (CPU execution provider) against eager torch for the 25M VLM's ONNX graphs.

The 25M architecture with random weights (EUPE ViT-S/16 and the 25M head:
``_common.build_model``) is exported by ``resireg.deploy.onnx_export.export_onnx`` with dynamic
shapes: the VLM's image graph (backbone + head) and the same with ReSiReg Lite in the graph, in
its factorised form (``attention="factorised"``: the coarse Gram matrix upsampled on both
sides) and, with ``--sdpa-graph``, in its SDPA form too (``MatMul -> Softmax -> MatMul`` on
onnxruntime's CPU provider). Each graph runs on ``--short-side`` x 4/3 inputs (576 x 768, the
protocol's) at each ``--batch`` (1 and 4) against eager torch in float32 on the same inputs:
``model.encode`` for the VLM, and for VLM + Lite ``encode`` then ``ReSiRegLite`` in both exact
forms (``factorised``, torch's default on the CPU, and ``sdpa``). Timed in alternating rounds
(one call of each per round, after one warm-up call each); medians, the ratios
time / onnxruntime's (the factorised graph's for VLM + Lite) and, per batch, onnxruntime's
speed over torch's fastest Lite form (>= 1: the graph is at least as fast). Both use
``torch.get_num_threads()`` threads. Also printed: the export time of each graph, its operator
sets and size, and the largest difference of Lite's unit features between the runtimes.

    python benchmarks/bench_onnx.py                                   # 576 x 768, batch 1 and 4
    python benchmarks/bench_onnx.py --sdpa-graph                      # also the SDPA graph
    python benchmarks/bench_onnx.py --short-side 96 --batch 1 --rounds 1   # quick
"""

from __future__ import annotations

import argparse
import statistics
import tempfile
import time
from pathlib import Path

import numpy as np
import onnxruntime as ort
import torch
import torch.nn.functional as F

from _common import build_model
from resireg.deploy import open_graph
from resireg.deploy.onnx_export import export_onnx
from resireg.method.lite import ReSiRegLite


def _session(path: Path, threads: int) -> ort.InferenceSession:
    """The graph as the project opens one: its SHA-256 checked against the manifest."""
    return open_graph(path, threads=threads)


def _unit_diff(a: np.ndarray, b: torch.Tensor) -> float:
    return float((F.normalize(torch.from_numpy(a), dim=1) - F.normalize(b, dim=1)).abs().max())


def _calls(model, sessions, images, lite_f, lite_s) -> dict:
    """``{(graph, runtime): call}`` on one batch of ``images``."""
    feed = {"images": images.numpy()}

    def vlm():
        with torch.no_grad():
            return model.encode(images)

    def with_lite(lite):
        def run():
            with torch.no_grad():
                out = model.encode(images)
                return lite(out.intermediates, out.language)

        return run

    def graph(name):
        return lambda: sessions[name].run(None, feed)

    calls = {
        ("vlm", "torch"): vlm,
        ("vlm", "onnxruntime"): graph("vlm"),
        ("vlm+lite", "torch (factorised)"): with_lite(lite_f),
        ("vlm+lite", "torch (sdpa)"): with_lite(lite_s),
    }
    for name in sessions:
        if name.startswith("vlm+lite"):
            form = name.split(":")[1]
            calls[("vlm+lite", f"onnxruntime ({form} graph)")] = graph(name)
    return calls


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    parser.add_argument("--short-side", type=int, default=576)
    parser.add_argument("--batch", type=int, nargs="+", default=[1, 4])
    parser.add_argument("--rounds", type=int, default=3)
    parser.add_argument("--sdpa-graph", action="store_true", help="also Lite's SDPA graph")
    args = parser.parse_args()
    threads = torch.get_num_threads()
    torch.manual_seed(0)
    model = build_model()
    h, w = args.short_side, args.short_side * 4 // 3
    print(f"25M VLM (random weights), {h} x {w}, torch {torch.__version__}, onnxruntime "
          f"{ort.__version__}, {threads} threads, medians of {args.rounds} alternating rounds")  # fmt: skip
    exports = [("vlm", False, "sdpa"), ("vlm+lite:factorised", True, "factorised")]
    if args.sdpa_graph:
        exports.append(("vlm+lite:sdpa", True, "sdpa"))
    with tempfile.TemporaryDirectory() as tmp:
        graphs = {}
        for name, lite, attention in exports:
            result = export_onnx(model, Path(tmp) / f"{name.replace(':', '-')}.onnx", lite=lite,
                                 attention=attention, dynamic=True, text=False)  # fmt: skip
            graphs[name] = result.image
            size = result.image.stat().st_size / 2**20
            print(f"export {name}: {result.seconds['image']:.1f} s, opsets {result.opsets}, "
                  f"{size:.0f} MiB")  # fmt: skip
        sessions = {name: _session(path, threads) for name, path in graphs.items()}
        lite_f, lite_s = ReSiRegLite(attention="factorised"), ReSiRegLite(attention="sdpa")
        base = ("vlm+lite", "onnxruntime (factorised graph)")

        rows, summary = [], []
        for batch in args.batch:
            images = torch.randn(batch, 3, h, w)
            feed = {"images": images.numpy()}

            calls = _calls(model, sessions, images, lite_f, lite_s)
            # agreement first (also the warm-up call of each)
            refs = {
                "factorised": calls[("vlm+lite", "torch (factorised)")](),
                "sdpa": calls[("vlm+lite", "torch (sdpa)")](),
            }
            for name in sessions:
                if name.startswith("vlm+lite"):
                    got = sessions[name].run(None, feed)[3]
                    diffs = ", ".join(
                        f"torch {form} {_unit_diff(got, ref):.1e}" for form, ref in refs.items()
                    )
                    print(f"batch {batch}: {name} graph's unit features, max |diff| against "
                          f"{diffs}")  # fmt: skip
            for fn in calls.values():
                fn()
            times: dict[tuple[str, str], list[float]] = {k: [] for k in calls}
            for _ in range(args.rounds):
                for key, fn in calls.items():
                    start = time.perf_counter()
                    fn()
                    times[key].append(time.perf_counter() - start)
            med = {k: statistics.median(v) for k, v in times.items()}
            for key in calls:
                graph, runtime = key
                ort_s = med[base if graph == "vlm+lite" else (graph, "onnxruntime")]
                rows.append((graph, batch, runtime, med[key], med[key] / ort_s))
            fastest = min(
                med[("vlm+lite", "torch (factorised)")], med[("vlm+lite", "torch (sdpa)")]
            )
            summary.append((batch, fastest / med[base]))
        print("\n| graph | batch | runtime | median s | / onnxruntime |")
        print("| --- | --- | --- | --- | --- |")
        for graph, batch, runtime, s, ratio in rows:
            print(f"| {graph} | {batch} | {runtime} | {s:.3f} | {ratio:.2f} |")
        for batch, ratio in summary:
            print(f"batch {batch}: VLM + Lite, onnxruntime (factorised graph) / torch's fastest "
                  f"Lite form, speed: {ratio:.2f}")  # fmt: skip


if __name__ == "__main__":
    main()
