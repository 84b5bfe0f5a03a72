"""Building-scale semantic maps: 10k, 100k and 1M voxels at D = 512, ``exact`` against ``compact``.

Each (size, storage) is built and measured in a process of its own (its peak memory is its
own): a :class:`resireg.mapping.SemanticMap` fed through :meth:`~SemanticMap.fuse` with posed
frames of 30 x 40 patches of 512-d features, along a corridor of new ground (one new voxel per
patch: a map of N voxels is N / 1200 frames), each feature one of 40 "class" directions plus
noise, so a PCA basis has structure to keep as real language features have. Then, with the map
at its size:

- **bytes / voxel**: ``SemanticMap.nbytes / len`` (keys, hash slots, features, weights,
  colours, spare rows; the compact map's float32 blocks and basis);
- **peak RSS**: the process's peak resident memory over the whole run (``ru_maxrss``) less
  its size after the imports, against the map's ``nbytes``; and its fixed part, named: the
  encoder's first text run when the map is made (before any frame), a window's input (8
  frames of 512-d features) and the first window's peak over the empty map (its fusion; a
  compact map fits its basis on it);
- **fuse ms / frame**: ``fuse`` of 30 frames (one per call) that revisit mapped ground and
  add ~10% new voxels; median and mean (every call, rehashes and new blocks included);
- **query**: the texts are 16 unit vectors near the class directions (the text tower is timed
  apart: ``text_queries`` of a new text with the 25M VLM's text tower, and of a cached one);
  ``top_k(q, 100)`` of 1 text and of 16 (per text), ``query`` (every voxel's score) of 1 and
  16; p50 and p95 of 15 runs;
- **classify**: ``classify_features`` (as the 3D evaluation calls it) of 16 and of 150 class
  prototypes (ADE20K's count; near the class directions), the cosine argmax and the 3D task's
  rule with RayFronts' threshold 0.1 and prompt denoising 0.5; p50 and p95 of 15 runs (the
  whole call, not per class);
- **classify's floor** (``--classify-floor SIZE``): the product of the stored features with
  16 and 150 prototypes alone, in float32 and bfloat16 (operands already in that precision),
  and the widening of the stored float16 features to float32: what any pass that scores every
  class of every voxel pays before it decides anything;
- **top-100 recall**: ``top_k`` against a float64 numpy brute force over the same stored
  features (:meth:`unit_rows`, chunk by chunk), ties to the lower index;
- **save / load**: ``save`` to a temporary folder and ``SemanticMap.load`` (digest verified,
  memory-mapped), with the peak memory each adds; and the copy the live node takes under its
  lock (``snapshot(copy=True)``);
- **merge** (its own process): two maps of N / 2 voxels each (10% shared) merged in place.

``--transform``: an off-lattice merge (10 degrees, a third of a voxel) against mapping the
transformed frames: the share of points in matching voxels, the features' cosine.

``--table2``: the Table 2 delta on the synthetic ScanNet-format room
(``conf/dataset/scannet_synthetic.yaml``, written by ``python -m
resireg_train.data.scannet_room``): ``resireg-eval task=scannet3d`` with
``dataset.storage=exact`` and ``=compact`` on a random-weight 25M VLM export (no weights are
downloaded), mIoU and f-mIoU of each.

    python benchmarks/bench_map_scale.py                      # all sizes (1M: minutes, ~6 GB)
    python benchmarks/bench_map_scale.py --sizes 10000 100000 --threads 1
    python benchmarks/bench_map_scale.py --table2
    python benchmarks/bench_map_scale.py --transform
    python benchmarks/bench_map_scale.py --sizes 1000000 --storages compact --peak-only
    python benchmarks/bench_map_scale.py --classify-cpu 100000   # CPU time per classify call
    python benchmarks/bench_map_scale.py --classify-floor 1000000 --threads 2  # the product alone

Figures: docs/benchmarks.md (one run, ratios against ``exact``).
"""

from __future__ import annotations

import argparse
import json
import math
import os
import resource
import shutil
import subprocess
import sys
import tempfile
import time
from pathlib import Path

import numpy as np

HERE = Path(__file__).resolve().parent
D = 512
GRID = (30, 40)
VOXEL = 0.05
CLASSES = 40
#: patches per frame: every patch a voxel of its own along the corridor
PER_FRAME = GRID[0] * GRID[1]


def rss_mb() -> float:
    with open("/proc/self/status") as f:
        for line in f:
            if line.startswith("VmRSS:"):
                return int(line.split()[1]) / 1024
    return math.nan


def peak_mb() -> float:
    return resource.getrusage(resource.RUSAGE_SELF).ru_maxrss / 1024


class RssProbe:
    """The largest resident memory a block adds (sampled every 5 ms in a thread)."""

    def __enter__(self):
        import threading

        self.before = self.top = rss_mb()
        self._stop = threading.Event()
        self._thread = threading.Thread(target=self._watch, daemon=True)
        self._thread.start()
        return self

    def _watch(self):
        while not self._stop.wait(0.005):
            self.top = max(self.top, rss_mb())

    def __exit__(self, *exc):
        self._stop.set()
        self._thread.join()
        self.top = max(self.top, rss_mb())
        self.extra = self.top - self.before


def pctl(values, q):
    return float(np.percentile(np.asarray(values) * 1000, q))


class Corridor:
    """Frames of 30 x 40 patches looking straight at a wall 1.8 m away (patch spacing ~6 cm
    > 5 cm voxels: one voxel per patch); frame ``i`` is ``2.5 i`` m along x, rows of 400 frames
    2 m apart in y (a building floor). Features: a class direction per 8 x 8 patch block
    (40 classes) plus noise, unit norm."""

    def __init__(self, seed: int = 0):
        import torch

        self.torch = torch
        g = torch.Generator().manual_seed(seed)
        self.dirs = torch.nn.functional.normalize(torch.randn(CLASSES, D, generator=g), dim=1)
        self.g = g
        h, w = GRID
        self.k = torch.tensor([[w * 0.72, 0, (w - 1) / 2], [0, w * 0.72, (h - 1) / 2],
                               [0, 0, 1.0]])  # fmt: skip
        self.depth = torch.full((1, h, w), 1.8)

    def pose(self, i: float):
        p = self.torch.eye(4)
        p[:3, :3] = self.torch.tensor([[1.0, 0, 0], [0, 0, -1], [0, 1, 0]])  # looking along +y
        p[0, 3] = 2.5 * (i % 400)
        p[1, 3] = 2.0 * (i // 400)
        return p

    def features(self, n: int):
        torch = self.torch
        h, w = GRID
        cls = torch.randint(0, CLASSES, (n, h // 8 + 1, w // 8 + 1), generator=self.g)
        cls = cls.repeat_interleave(8, 1).repeat_interleave(8, 2)[:, :h, :w]
        # written into one [n, D, h, w] tensor in place (what an encoder hands over), so the
        # synthesis holds two window-sized tensors at most: its temporaries are no part of
        # the mapping's peak memory
        out = self.dirs.T[:, cls].transpose(0, 1).contiguous()  # [n, D, h, w]
        noise = torch.randn(n, h, w, D, generator=self.g).permute(0, 3, 1, 2)  # the same draws
        out.add_(noise, alpha=0.6 / math.sqrt(D))
        del noise
        return out.div_(torch.linalg.vector_norm(out, dim=1, keepdim=True).clamp_min_(1e-12))

    def window(self, frames):
        torch = self.torch
        poses = torch.stack([self.pose(i) for i in frames])
        n = len(frames)
        colour = torch.rand(n, 3, *GRID, generator=self.g)
        return self.features(n), self.depth.expand(n, -1, -1), self.k, poses, colour


def make_map(storage: str, encoder=None):
    from resireg.mapping import SemanticMap

    return SemanticMap(encoder, "bb", VOXEL, storage=storage)


def build(smap, corridor: Corridor, first: int, frames: int, batch: int = 8) -> None:
    for start in range(first, first + frames, batch):
        idx = list(range(start, min(first + frames, start + batch)))
        smap.fuse(*corridor.window(idx))


def brute_top_k(smap, q, k: int):
    """float64 numpy scores of every voxel's stored features with ``q``, best ``k`` (ties to
    the lower index): the reference of the recall."""
    import torch

    vmap = smap.voxels
    order = vmap.sorted_rows
    qs = smap.project(q[None])[0].double().numpy()
    scores = np.empty(order.numel())
    for s in range(0, order.numel(), 1 << 16):
        rows = order[s : s + (1 << 16)]
        scores[s : s + rows.numel()] = vmap.unit_rows(rows).double().numpy() @ qs
    best = np.lexsort((np.arange(len(scores)), -scores))[:k]
    return set(vmap.keys[order[torch.from_numpy(best)]].tolist())


def one(size: int, storage: str, threads: int, peak_only: bool = False) -> dict:
    import torch

    torch.set_num_threads(threads)
    sys.path.insert(0, str(HERE))
    from _common import build_model

    corridor = Corridor()
    text_model = build_model(tiny=False)  # the text tower, timed apart
    base = rss_mb()
    smap = make_map(storage, text_model)
    # the fixed part of the peak, named: the encoder's first text run (the map asks the
    # dimension of its text queries), a window's input, the first window's fusion (a compact
    # map fits its basis on it: a float64 copy of its features)
    probe = rss_mb() - base
    frames = math.ceil(size / PER_FRAME)
    window = corridor.window(list(range(8)))
    window_mb = sum(t.numel() * t.element_size() for t in window) / 2**20
    del window
    t0 = time.perf_counter()
    before = rss_mb()
    with RssProbe() as first:
        build(smap, corridor, 0, min(8, frames))
    first_peak = max(first.top, peak_mb()) - before
    build(smap, corridor, min(8, frames), frames - min(8, frames))
    out = {
        "size": size,
        "storage": storage,
        "voxels": len(smap),
        "build_s": time.perf_counter() - t0,
    }
    out["bytes_per_voxel"] = smap.nbytes / len(smap)
    out["nbytes_mb"] = smap.nbytes / 2**20
    # fusion at this size: 30 frames revisiting mapped ground, shifted by ~1/10 of a frame
    times = []
    for j in range(30):
        window = corridor.window([(frames // 2 + j) % frames])
        window[3][:, 0, 3] += 0.25  # a quarter frame to the side: ~10% new voxels
        t = time.perf_counter()
        smap.fuse(*window)
        times.append(time.perf_counter() - t)
    out["fuse_ms_p50"] = pctl(times, 50)
    out["fuse_ms_mean"] = float(np.mean(times) * 1000)
    out["peak_mapping_mb"] = peak_mb() - base
    out["probe_mb"], out["window_mb"], out["first_window_peak_mb"] = probe, window_mb, first_peak
    if peak_only:
        return out
    # the text tower apart: a new text, then the cached one
    t = time.perf_counter()
    smap.text_queries(["a red office chair"])
    out["text_new_ms"] = (time.perf_counter() - t) * 1000
    t = time.perf_counter()
    smap.text_queries(["a red office chair"])
    out["text_cached_ms"] = (time.perf_counter() - t) * 1000
    g = torch.Generator().manual_seed(1)
    noise = torch.randn(16, D, generator=g) / math.sqrt(D)
    texts = torch.nn.functional.normalize(corridor.dirs[:16] + noise, dim=1)
    for name, fn in (("top_k_1", lambda: smap.top_k(texts[0], 100)),
                     ("top_k_16", lambda: smap.top_k(texts, 100)),
                     ("query_1", lambda: smap.query(texts[0])),
                     ("query_16", lambda: smap.query(texts))):  # fmt: skip
        fn()
        runs = []
        for _ in range(15):
            t = time.perf_counter()
            fn()
            runs.append(time.perf_counter() - t)
        per = 16 if name.endswith("16") else 1
        out[f"{name}_p50_ms"] = pctl(runs, 50) / per
        out[f"{name}_p95_ms"] = pctl(runs, 95) / per
    # classify: 16 and 150 (ADE20K's count) class prototypes near the class directions, the
    # cosine argmax and the 3D task's rule with RayFronts' settings (threshold 0.1, prompt
    # denoising 0.5), through classify_features as the 3D evaluation calls it
    for n_cls in (16, 150):
        g = torch.Generator().manual_seed(2)
        protos = torch.nn.functional.normalize(
            corridor.dirs[torch.arange(n_cls) % CLASSES]
            + 2 * torch.randn(n_cls, D, generator=g) / math.sqrt(D), dim=1)  # fmt: skip
        stored = smap.project(protos)
        for rule, (threshold, denoise) in (("argmax", (None, None)), ("rule", (0.1, 0.5))):
            smap.classify_features(stored, threshold, denoise)
            runs = []
            for _ in range(15):
                t = time.perf_counter()
                smap.classify_features(stored, threshold, denoise)
                runs.append(time.perf_counter() - t)
            out[f"classify_{n_cls}_{rule}_p50_ms"] = pctl(runs, 50)
            out[f"classify_{n_cls}_{rule}_p95_ms"] = pctl(runs, 95)
    recalls = []
    for q in texts[:4]:
        got = smap.top_k(q, 100)
        from resireg.mapping.keys import pack_keys

        want = brute_top_k(smap, q, 100)
        recalls.append(len(set(pack_keys(got.indices).tolist()) & want) / 100)
    out["recall_at_100"] = min(recalls)
    # the live node's copy under its lock, then save and load
    t = time.perf_counter()
    snap = smap.snapshot(copy=True)
    out["snapshot_s"] = time.perf_counter() - t
    del snap
    folder = Path(tempfile.mkdtemp(prefix="bench_map_scale_"))
    try:
        with RssProbe() as probe:
            t = time.perf_counter()
            smap.save(folder / "map")
            out["save_s"] = time.perf_counter() - t
        out["save_extra_mb"] = probe.extra
        out["file_mb"] = sum(p.stat().st_size for p in (folder / "map").iterdir()) / 2**20
        voxels = len(smap)
        smap.store.voxels = smap.store.colours = None  # the map's memory back before the load
        import gc

        gc.collect()
        from resireg.mapping import SemanticMap

        with RssProbe() as probe:
            t = time.perf_counter()
            loaded = SemanticMap.load(folder / "map")
            out["load_s"] = time.perf_counter() - t
        out["load_rss_mb"] = probe.extra
        assert len(loaded) == voxels
    finally:
        shutil.rmtree(folder, ignore_errors=True)
    out["peak_rss_mb"] = peak_mb() - base
    return out


def classify_cpu(size: int, threads: int, runs: int = 5) -> dict:
    """CPU time (the process's user + system time, less sensitive than the wall clock to a
    loaded machine) and wall-clock p50 per ``classify_features`` call on a compact map of
    ``size`` voxels, against the previous path (``resireg.mapping.classify`` over the stored
    features in chunks of the indices order, float32), calls interleaved; and how many labels
    of the previous path differ from the exact ones."""
    import torch

    from resireg.mapping.query import classify as classify_rows

    torch.set_num_threads(threads)
    corridor = Corridor()
    smap = make_map("compact")
    build(smap, corridor, 0, math.ceil(size / PER_FRAME))
    vmap = smap.voxels

    def previous(stored, threshold, denoise):
        order = vmap.sorted_rows
        step = 10_000 if denoise is not None else 1 << 16
        out = torch.empty(order.numel(), dtype=torch.int64)
        for s in range(0, order.numel(), step):
            feats = vmap.unit_rows(order[s : s + step])
            out[s : s + step] = classify_rows(feats, stored, threshold, denoise, none=-1)
        return out

    def now(stored, threshold, denoise):
        return smap.classify_features(stored, threshold, denoise)

    def cpu():
        r = resource.getrusage(resource.RUSAGE_SELF)
        return r.ru_utime + r.ru_stime

    out = {"size": size, "voxels": len(smap), "threads": threads}
    for n_cls in (16, 150):
        g = torch.Generator().manual_seed(2)
        protos = torch.nn.functional.normalize(
            corridor.dirs[torch.arange(n_cls) % CLASSES]
            + 2 * torch.randn(n_cls, D, generator=g) / math.sqrt(D), dim=1)  # fmt: skip
        stored = smap.project(protos)
        for rule, (threshold, denoise) in (("argmax", (None, None)), ("rule", (0.1, 0.5))):
            spent = {"previous": 0.0, "now": 0.0}
            wall: dict[str, list[float]] = {"previous": [], "now": []}
            labels = {}
            for _ in range(runs):
                for name, fn in (("previous", previous), ("now", now)):
                    t, w = cpu(), time.perf_counter()
                    labels[name] = fn(stored, threshold, denoise)
                    wall[name].append(time.perf_counter() - w)
                    spent[name] += cpu() - t
            key = f"classify_{n_cls}_{rule}"
            for name in ("previous", "now"):
                out[f"{key}_cpu_ms_{name}"] = spent[name] / runs * 1000
                out[f"{key}_wall_p50_ms_{name}"] = pctl(wall[name], 50)
            out[f"{key}_previous_labels_off"] = int((labels["previous"] != labels["now"]).sum())
    return out


def classify_floor(size: int, threads: int, runs: int = 7) -> dict:
    """What any dense classify pass over ``size`` stored voxels must pay on this machine: the
    product of ``[size, 128]`` features with 16 and 150 class prototypes alone, in each
    precision torch multiplies in here, from operands already in that precision (no widening,
    no norms, no decision), wall-clock p50 of ``runs``; and the float16 -> float32 widening of
    the stored features (what the exact float32 pass adds). A classify rule that must look at
    every class of every voxel cannot run faster than the product in its precision."""
    import torch

    from _common import median_seconds

    torch.set_num_threads(threads)
    k = 128
    g = torch.Generator().manual_seed(0)
    stored = torch.nn.functional.normalize(torch.randn(size, k, generator=g), dim=1).half()

    def p50(fn) -> float:
        return median_seconds(fn, runs) * 1000

    out: dict = {"size": size, "channels": k, "threads": threads, "torch": torch.__version__,
                 "cpu_capability": torch.backends.cpu.get_cpu_capability()}  # fmt: skip
    wide = torch.empty(size, k)
    out["widen_float16_to_float32_ms"] = p50(lambda: wide.copy_(stored))
    for dtype in (torch.float32, torch.bfloat16):
        x = stored.to(dtype)
        name = str(dtype).removeprefix("torch.")
        for n_cls in (16, 150):
            protos = torch.randn(n_cls, k, generator=g).to(dtype)
            scores = torch.empty(size, n_cls, dtype=dtype)
            out[f"product_{n_cls}_{name}_ms"] = p50(
                lambda x=x, w=protos.T, y=scores: torch.mm(x, w, out=y)
            )
    return out


def merge(size: int, storage: str, threads: int) -> dict:
    import torch

    torch.set_num_threads(threads)
    corridor = Corridor()
    frames = math.ceil(size / PER_FRAME)
    half = frames // 2
    shared = frames // 20  # 10% of each map's voxels in the other too
    a, b = make_map(storage), make_map(storage)
    build(a, corridor, 0, half + shared // 2)
    if storage == "compact":
        b.set_basis(a.basis)
    build(b, corridor, half - shared // 2, frames - half + shared // 2)
    sizes = (len(a), len(b))
    t = time.perf_counter()
    a.merge(b)
    return {"size": size, "storage": storage, "maps": sizes, "merged": len(a),
            "merge_s": time.perf_counter() - t}  # fmt: skip


def child(kind: str, size: int, storage: str, threads: int, peak_only: bool = False) -> dict:
    cmd = [sys.executable, __file__, "--child", kind, str(size), storage, "--threads", str(threads)]
    cmd += ["--peak-only"] if peak_only else []
    env = {**os.environ, "OMP_NUM_THREADS": str(threads)}
    proc = subprocess.run(cmd, capture_output=True, text=True, env=env)
    if proc.returncode:
        return {"size": size, "storage": storage, "error": proc.stderr[-1500:]}
    return json.loads(proc.stdout.strip().splitlines()[-1])


ROWS = [
    ("voxels", "voxels", "{:,.0f}"),
    ("bytes / voxel", "bytes_per_voxel", "{:,.0f}"),
    ("map (nbytes, MiB)", "nbytes_mb", "{:,.0f}"),
    ("peak RSS over the run (MiB)", "peak_rss_mb", "{:,.0f}"),
    ("peak RSS while mapping / nbytes", "peak_ratio", "{:.2f}"),
    ("fixed: the encoder's first text run, before any frame (MiB)", "probe_mb", "{:,.0f}"),
    ("fixed: a window's input, 8 frames (MiB)", "window_mb", "{:,.0f}"),
    ("fixed: the first window's peak over the empty map (MiB)", "first_window_peak_mb", "{:,.0f}"),
    ("fuse ms / frame (p50)", "fuse_ms_p50", "{:.1f}"),
    ("fuse ms / frame (mean)", "fuse_ms_mean", "{:.1f}"),
    ("top-100 of 1 text, p50 / p95 ms", ("top_k_1_p50_ms", "top_k_1_p95_ms"), "{:.1f} / {:.1f}"),
    (
        "top-100 of 16 texts, per text p50 / p95 ms",
        ("top_k_16_p50_ms", "top_k_16_p95_ms"),
        "{:.1f} / {:.1f}",
    ),  # fmt: skip
    (
        "query (all voxels) 1 text, p50 / p95 ms",
        ("query_1_p50_ms", "query_1_p95_ms"),
        "{:.1f} / {:.1f}",
    ),  # fmt: skip
    (
        "query (all voxels) 16 texts, per text p50 / p95 ms",
        ("query_16_p50_ms", "query_16_p95_ms"),
        "{:.1f} / {:.1f}",
    ),  # fmt: skip
    *(
        (
            f"classify {n} classes, {label}, p50 / p95 ms",
            (f"classify_{n}_{rule}_p50_ms", f"classify_{n}_{rule}_p95_ms"),
            "{:.1f} / {:.1f}",
        )
        for n in (16, 150)
        for rule, label in (("argmax", "argmax"), ("rule", "threshold 0.1 + denoise 0.5"))
    ),  # fmt: skip
    ("top-100 recall vs float64", "recall_at_100", "{:.3f}"),
    ("text tower: new text / cached ms", ("text_new_ms", "text_cached_ms"), "{:.1f} / {:.3f}"),
    ("node's copy under its lock (s)", "snapshot_s", "{:.2f}"),
    ("save s", "save_s", "{:.2f}"),
    ("save: extra peak MiB", "save_extra_mb", "{:,.0f}"),
    ("load s (digest + mmap)", "load_s", "{:.2f}"),
    ("load: RSS added MiB", "load_rss_mb", "{:,.0f}"),
    ("merge of two N/2 maps (s)", "merge_s", "{:.2f}"),
]


def table(results: list[dict]) -> str:
    cols = [(r["size"], r["storage"]) for r in results]
    head = "| | " + " | ".join(f"{s:,} {st}" for s, st in cols) + " |"
    lines = [head, "|---" * (len(cols) + 1) + "|"]
    for label, key, fmt in ROWS:
        cells = []
        for r in results:
            try:
                if isinstance(key, tuple):
                    cells.append(fmt.format(*(r[k] for k in key)))
                else:
                    cells.append(fmt.format(r[key]))
            except (KeyError, TypeError):
                cells.append("—")
        lines.append(f"| {label} | " + " | ".join(cells) + " |")
    return "\n".join(lines)


def table2(threads: int) -> dict:
    """resireg-eval task=scannet3d on the synthetic room, exact and compact."""
    import torch

    sys.path.insert(0, str(HERE))
    from _common import build_model

    work = Path(tempfile.mkdtemp(prefix="bench_table2_"))
    try:
        torch.manual_seed(0)
        build_model().save_pretrained(work / "export")
        subprocess.run([sys.executable, "-m", "resireg_train.data.scannet_room",
                        str(work / "scannet_synthetic")], check=True, capture_output=True)  # fmt: skip
        out = {}
        for storage in ("exact", "compact"):
            proc = subprocess.run(
                ["resireg-eval" if shutil.which("resireg-eval") else sys.executable, *(
                    [] if shutil.which("resireg-eval") else ["-m", "resireg_train.cli.eval"]),
                 "task=scannet3d", "dataset=scannet_synthetic",
                 f"dataset.path={work / 'scannet_synthetic'}", f"model_path={work / 'export'}",
                 f"dataset.storage={storage}", "batch_size=4", "num_workers=0", "device=cpu",
                 f"paths.log_dir={work / 'runs'}", f"hydra.run.dir={work / 'runs' / storage}"],
                capture_output=True, text=True,
                env={**os.environ, "OMP_NUM_THREADS": str(threads), "HF_HUB_OFFLINE": "1"},
            )  # fmt: skip
            if proc.returncode:
                out[storage] = {"error": proc.stderr[-1500:]}
                continue
            record = json.loads((work / "runs" / storage / "results.json").read_text())
            final = record["final"]
            out[storage] = {k.rsplit("/", 1)[1]: v for k, v in final.items()
                            if k.rsplit("/", 1)[1] in ("miou_full", "fmiou_full", "miou_bb",
                                                        "fmiou_bb", "miou_lite", "fmiou_lite")}  # fmt: skip
        return out
    finally:
        shutil.rmtree(work, ignore_errors=True)


def transform_error(threads: int) -> dict:
    """An off-lattice merge against re-mapping: a second run's map (40 frames of random depth)
    merged through a 10-degree turn about the vertical and a third of a voxel, against the map
    of its frames with the transformed poses: the share of points whose voxel matches, and the
    features' cosine on the voxels both hold."""
    import torch

    from resireg.mapping import SemanticMap

    torch.set_num_threads(threads)
    g = torch.Generator().manual_seed(5)
    h, w = 48, 64
    k = torch.tensor([[40.0, 0, (w - 1) / 2], [0, 40.0, (h - 1) / 2], [0, 0, 1]])
    frames = []
    for _ in range(20):
        depth = 1.0 + 3 * torch.rand(2, h, w, generator=g)
        pose = torch.eye(4).repeat(2, 1, 1)
        pose[:, :3, 3] = torch.rand(2, 3, generator=g) * 2
        frames.append((torch.randn(2, 32, 12, 16, generator=g), depth, k, pose))
    angle = math.radians(10)
    t = torch.eye(4, dtype=torch.float64)
    t[:2, :2] = torch.tensor(
        [[math.cos(angle), -math.sin(angle)], [math.sin(angle), math.cos(angle)]]
    )
    t[0, 3] = VOXEL / 3
    out = {}
    for storage in ("exact", "compact"):
        merged = SemanticMap(
            None, "bb", VOXEL, storage=storage, compact={"dim": 16, "basis_rows": 500}
        )
        truth = SemanticMap(
            None, "bb", VOXEL, storage=storage, compact={"dim": 16, "basis_rows": 500}
        )
        run = SemanticMap(
            None, "bb", VOXEL, storage=storage, compact={"dim": 16, "basis_rows": 500}
        )
        for f in frames:
            run.fuse(*f)
            truth.fuse(f[0], f[1], f[2], t.float() @ f[3])
        if storage == "compact":
            merged.set_basis(run.basis)
            truth = SemanticMap(None, "bb", VOXEL, storage=storage, compact={"dim": 16})
            truth.set_basis(run.basis)
            for f in frames:
                truth.fuse(f[0], f[1], f[2], t.float() @ f[3])
        merged.merge(run, t)
        a = {
            tuple(i): n
            for i, n in zip(merged.indices.tolist(), merged.voxels.counts.tolist(), strict=True)
        }
        b = {
            tuple(i): n
            for i, n in zip(truth.indices.tolist(), truth.voxels.counts.tolist(), strict=True)
        }
        common = set(a) & set(b)
        same_points = sum(min(a[v], b[v]) for v in common) / sum(b.values())
        fa = dict(zip(map(tuple, merged.indices.tolist()), merged.features()[1], strict=True))
        fb = dict(zip(map(tuple, truth.indices.tolist()), truth.features()[1], strict=True))
        cos = [float(torch.dot(fa[v], fb[v]) / (fa[v].norm() * fb[v].norm())) for v in common]
        out[storage] = {"voxels_merged": len(a), "voxels_remapped": len(b),
                        "voxels_in_both": len(common), "points_in_matching_voxels": same_points,
                        "cosine_median": float(np.median(cos)), "cosine_p5": float(np.percentile(cos, 5))}  # fmt: skip
    return out


def main() -> None:
    from _common import positive_int

    parser = argparse.ArgumentParser(description=__doc__.split("\n")[0])
    parser.add_argument("--sizes", type=int, nargs="+", default=[10_000, 100_000, 1_000_000])
    parser.add_argument("--storages", nargs="+", default=["exact", "compact"])
    parser.add_argument("--threads", type=int, default=1, help="torch threads per process")
    parser.add_argument("--table2", action="store_true", help="the Table 2 delta only")
    parser.add_argument("--transform", action="store_true",
                        help="an off-lattice merge against re-mapping the frames, only")  # fmt: skip
    parser.add_argument(
        "--child", nargs=3, metavar=("KIND", "SIZE", "STORAGE"), help=argparse.SUPPRESS
    )
    parser.add_argument("--json", type=Path, help="also write the results here")
    parser.add_argument("--classify-cpu", type=positive_int, metavar="SIZE",
                        help="classify's CPU time per call on a compact map of SIZE voxels, "
                        "against the previous path, only")  # fmt: skip
    parser.add_argument("--classify-floor", type=positive_int, metavar="SIZE",
                        help="the product of SIZE stored features with 16 and 150 classes "
                        "alone, in float32 and bfloat16, only")  # fmt: skip
    parser.add_argument("--peak-only", action="store_true",
                        help="build the maps and measure the mapping peak only")  # fmt: skip
    args = parser.parse_args()
    if args.child:
        kind, size, storage = args.child
        if kind == "one":
            print(json.dumps(one(int(size), storage, args.threads, args.peak_only)))
        else:
            print(json.dumps(merge(int(size), storage, args.threads)))
        return
    if args.classify_cpu or args.classify_floor:  # (each >= 1 when given)
        result = (classify_cpu(args.classify_cpu, args.threads) if args.classify_cpu
                  else classify_floor(args.classify_floor, args.threads))  # fmt: skip
        print(json.dumps(result, indent=2))
        if args.json:
            args.json.write_text(json.dumps(result, indent=2))
        return
    if args.table2 or args.transform:
        result = table2(args.threads) if args.table2 else transform_error(args.threads)
        print(json.dumps(result, indent=2))
        if args.json:
            args.json.write_text(json.dumps(result, indent=2))
        return
    results = []
    for size in args.sizes:
        for storage in args.storages:
            r = child("one", size, storage, args.threads, args.peak_only)
            if not args.peak_only:
                r["merge_s"] = child("merge", size, storage, args.threads).get("merge_s")
            if "peak_mapping_mb" in r:
                r["peak_ratio"] = r["peak_mapping_mb"] / r["nbytes_mb"]
            results.append(r)
            print(json.dumps(r), flush=True)
    print(table(results))
    if args.json:
        args.json.write_text(json.dumps(results, indent=2))


if __name__ == "__main__":
    main()
