"""Speed of ReSiReg's clustering (torch PCA + k-means) against scikit-learn, and of Full/Lite.

Setting of the issue: 8 images of a 36 x 48 patch grid, 384-d intermediates, 512-d
language tokens, upscale 2 -> 55,296 points, 36 components, 36 prototypes. The
intermediates carry region structure (a smooth random field of region codes plus
noise; ``--features regions``) so k-means sees clusters as it does on real ViT features, or
smooth mixtures of directions plus noise (``--features mixture``, soft cluster borders; both
by default, one section each). All timings of one run
are reported as ratios because absolute times on a shared 2-core machine drift; the
timed paths are interleaved (A, B, A, B, ...) and each keeps its fastest call, so a burst
of load elsewhere hits all of them alike.

One run prints:

1. scikit-learn ``PCA`` + ``KMeans(n_init=1)`` on the 55,296 materialised upsampled points,
   the torch ``pca`` + ``kmeans`` on the same points, and ReSiReg Full's clustering
   (``ReSiRegFull.assign``: from the low-resolution grid, upsampling included), with the
   speed-up over scikit-learn;
2. the k-means inertia of Full's clustering and of scikit-learn, mean over ``--seeds``
   seeds (single runs land in different local minima), and their ratio;
3. the per-stage profile of ``ReSiRegFull.assign`` (PCA moments, ``eigh``, projection,
   upsampling, k-means++ seeding, Lloyd with its iteration count, ...), timed with
   ``time.perf_counter`` around the implementation's own functions (the fastest call);
4. ReSiReg Full's and Lite's forward.

``--impl DIR`` runs everything against another copy of ``full.py``, ``lite.py`` and ``grid.py``
(or ``reconstruct.py``, for versions before Full and Lite had files of their own) and of the
clustering they import: ``pca.py``, ``kmeans.py`` and ``elbo.py``, or ``cluster.py`` for
versions before the clustering was split into those three (e.g. the files before a change,
copied to DIR), so before/after figures come from the same script:

    python benchmarks/bench_reconstruct.py [--threads 2] [--repeats 7] [--seeds 20] [--impl DIR]
        [--features regions mixture] [--no-forward]
"""

from __future__ import annotations

import argparse
import contextlib
import importlib.util
import sys
import time
from collections.abc import Callable, Iterator
from pathlib import Path
from types import ModuleType
from typing import Any, NamedTuple

import numpy as np
import torch
import torch.nn.functional as F
from sklearn.cluster import KMeans
from sklearn.decomposition import PCA
from threadpoolctl import threadpool_limits

import resireg.method.full
import resireg.method.kmeans
import resireg.method.lite
import resireg.method.pca


def make_features(b=8, h=36, w=48, dv=384, dl=512, regions=48, seed=0):
    g = torch.Generator().manual_seed(seed)
    logits = F.interpolate(
        torch.randn(b, regions, h // 6, w // 6, generator=g), size=(h, w), mode="bicubic"
    )
    labels = logits.argmax(1)
    codes = torch.randn(regions, dv, generator=g)
    inter = codes[labels].permute(0, 3, 1, 2) + 0.5 * torch.randn(b, dv, h, w, generator=g)
    lang = torch.randn(b, dl, h, w, generator=g)
    return inter, lang


def make_mixture_features(
    b=8, h=36, w=48, dv=384, dl=512, directions=24, temperature=0.15, noise=0.3, seed=0
):
    """Structured features like ViT tokens: every point a mixture of ``directions`` random
    unit directions (scaled by 4), the mixture weights smooth in space (a softmax of a
    bicubically upsampled random field at ``temperature``), plus Gaussian noise. Unlike
    :func:`make_features`' hard regions, neighbouring points blend, so the clusters have soft
    borders and Lloyd takes tens of iterations."""
    g = torch.Generator().manual_seed(seed)
    logits = F.interpolate(
        torch.randn(b, directions, h // 6, w // 6, generator=g), size=(h, w), mode="bicubic"
    )
    weights = torch.softmax(logits / temperature, dim=1)
    axes = F.normalize(torch.randn(directions, dv, generator=g), dim=1) * 4
    inter = torch.einsum("bkhw,kd->bdhw", weights, axes)
    inter = inter + noise * torch.randn(b, dv, h, w, generator=g)
    return inter, torch.randn(b, dl, h, w, generator=g)


FEATURES = {"regions": make_features, "mixture": make_mixture_features}


class Impl(NamedTuple):
    """An implementation's modules: ``kmeans`` (``impl[0]``: ``kmeans``, ``kmeans_plusplus``,
    ``_lloyd``, ...), ``reconstruct`` (``impl[1]``: ReSiReg Full's module, ``full.py``, or
    ``reconstruct.py`` before Full and Lite had files of their own), ``pca`` and ``lite``
    (ReSiReg Lite's module); for a version from before the clustering was split, ``kmeans``
    and ``pca`` are both its ``cluster.py``."""

    kmeans: ModuleType
    reconstruct: ModuleType
    pca: ModuleType
    lite: ModuleType


def load_impl(directory: str | None) -> Impl:
    """The installed modules, or the copies in ``directory``: its ``pca.py``, ``kmeans.py``,
    ``elbo.py`` (or, from before the split, its ``cluster.py``), ``grid.py``, ``full.py`` and
    ``lite.py`` (or, from before those, ``reconstruct.py``), each bound to the directory's own
    copies of the others."""
    if directory is None:
        return Impl(resireg.method.kmeans, resireg.method.full, resireg.method.pca,
                    resireg.method.lite)  # fmt: skip

    def load(name: str) -> ModuleType:
        spec = importlib.util.spec_from_file_location(
            f"_bench_impl_{name}", Path(directory) / f"{name}.py"
        )
        assert spec is not None and spec.loader is not None
        module = importlib.util.module_from_spec(spec)
        sys.modules[spec.name] = module  # dataclasses look their module up there
        spec.loader.exec_module(module)
        return module

    split = (Path(directory) / "kmeans.py").is_file()
    own = (Path(directory) / "full.py").is_file()  # Full and Lite in files of their own
    names = ["pca", "kmeans", "elbo"] if split else ["cluster"]
    names += ["grid"] if own else []
    # `from resireg.<name> import ...` (before resireg/method/) or `from resireg.method.<name>`
    keys = [f"{package}.{name}" for name in names for package in ("resireg", "resireg.method")]
    installed = {key: sys.modules.get(key) for key in keys}
    loaded: dict[str, ModuleType] = {}
    try:
        for name in names:  # in import order: elbo imports kmeans
            loaded[name] = load(name)
            for package in ("resireg", "resireg.method"):  # the copies import the copy
                sys.modules[f"{package}.{name}"] = loaded[name]
        for name in ("full", "lite") if own else ("reconstruct",):
            loaded[name] = load(name)
    finally:
        for key, module in installed.items():
            if module is None:
                sys.modules.pop(key, None)
            else:
                sys.modules[key] = module
    full = loaded["full"] if own else loaded["reconstruct"]
    lite = loaded["lite"] if own else full
    if split:
        return Impl(loaded["kmeans"], full, loaded["pca"], lite)
    return Impl(loaded["cluster"], full, loaded["cluster"], lite)


def interleaved_best(fns: dict[str, Callable[[], Any]], repeats: int) -> dict[str, float]:
    """Fastest of ``repeats`` calls of every function, calls interleaved across functions."""
    best = dict.fromkeys(fns, float("inf"))
    for _ in range(repeats):
        for name, fn in fns.items():
            start = time.perf_counter()
            fn()
            best[name] = min(best[name], time.perf_counter() - start)
    return best


# Stages of ReSiRegFull.assign, as (module, function) pairs of the implementation that are
# timed when present; functions missing from an implementation are skipped.
_TIMED = [
    ("reconstruct", "upsampled_pca"),  # centring + moments + eigh
    ("reconstruct", "upsampled_spectrum"),  # after FullShared: centring + moments + eigh
    ("reconstruct", "pca_from_moments"),  # eigh
    ("reconstruct", "_project_grid"),  # after the change: the projection
    ("reconstruct", "_upsample"),  # before Full had a file of its own
    ("reconstruct", "upsample"),  # after: resireg.method.grid's, as full.py binds it
    ("reconstruct", "kmeans"),
    ("reconstruct", "sq_distances"),  # before the change: assign's second distance matrix
    ("kmeans", "kmeans_plusplus"),  # before: seeding (called by kmeans)
    ("kmeans", "_kmeans_plusplus"),  # after: seeding
    ("kmeans", "_lloyd"),
]


@contextlib.contextmanager
def timed(modules: dict[str, ModuleType]) -> Iterator[dict[str, float]]:
    """Wrap the functions of ``_TIMED`` so each call adds its seconds to a dict (and the
    Lloyd iteration count under ``"n_iter"``). Times are inclusive; a call made while
    another timed call runs is also recorded under ``"<name>@nested"`` and not under its
    own name, so e.g. the upsampling inside the k-means++ seeding counts as seeding."""
    record: dict[str, float] = {}
    active = [0]
    originals = []
    for mod_name, fn_name in _TIMED:
        module = modules[mod_name]
        original = getattr(module, fn_name, None)
        if original is None:
            continue

        def wrapper(*args: Any, _fn=original, _key=fn_name, **kwargs: Any) -> Any:
            key = _key if active[0] == 0 else f"{_key}@nested"
            active[0] += 1
            start = time.perf_counter()
            try:
                out = _fn(*args, **kwargs)
            finally:
                active[0] -= 1
            record[key] = record.get(key, 0.0) + time.perf_counter() - start
            if _key == "_lloyd":
                record["n_iter"] = record.get("n_iter", 0) + out.n_iter
            return out

        setattr(module, fn_name, wrapper)
        originals.append((module, fn_name, original))
    try:
        yield record
    finally:
        for module, fn_name, original in originals:
            setattr(module, fn_name, original)


def stage_profile(modules: dict[str, ModuleType], full: Any, inter: torch.Tensor, repeats: int):
    """Per-stage seconds of the fastest of ``repeats`` ``full.assign(inter)`` calls."""
    best: dict[str, float] | None = None
    for _ in range(repeats):
        with timed(modules) as rec:
            start = time.perf_counter()
            full.assign(inter)
            rec["total"] = time.perf_counter() - start
        if best is None or rec["total"] < best["total"]:
            best = dict(rec)
    assert best is not None
    get = best.get
    seeding = get("kmeans_plusplus@nested", 0.0) + get("_kmeans_plusplus@nested", 0.0)
    eigh = get("pca_from_moments@nested", 0.0)
    lloyd = get("_lloyd@nested", 0.0)
    rows = [
        (
            "PCA moments (centring, grid products, Gram; + eigh if not below)",
            get("upsampled_pca", 0.0) + get("upsampled_spectrum", 0.0) - eigh,
        ),
        ("PCA eigh (float64, D x D)", eigh),
        ("projection on the grid", get("_project_grid", 0.0)),
        ("bilinear upsampling of the projection", get("_upsample", 0.0)),
        ("normalisation, glue (the rest of assign)", 0.0),  # filled below
        ("k-means setup (|x|^2, tolerance)", get("kmeans", 0.0) - seeding - lloyd),
        ("k-means++ seeding", seeding),
        (f"Lloyd, {int(get('n_iter', 0))} iterations + final assignment", lloyd),
        ("second distance matrix in assign", get("sq_distances", 0.0)),
    ]
    rest = best["total"] - sum(t for _, t in rows)
    rows[4] = (rows[4][0], rest)
    return rows, best["total"], int(get("n_iter", 0))


def main() -> None:
    parser = argparse.ArgumentParser(
        description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter
    )
    parser.add_argument("--repeats", type=int, default=7)
    parser.add_argument("--threads", type=int, default=2, help="torch and scikit-learn threads")
    parser.add_argument("--components", type=int, default=36)
    parser.add_argument("--prototypes", type=int, default=36)
    parser.add_argument(
        "--seeds", type=int, default=20, help="k-means seeds for the inertia comparison"
    )
    parser.add_argument(
        "--features", nargs="+", choices=list(FEATURES), default=list(FEATURES),
        help="regions: hard regions of codes + noise; mixture: smooth mixtures of directions",
    )  # fmt: skip
    parser.add_argument(
        "--impl", default=None, help="directory with the clustering and full.py / lite.py to time"
    )
    parser.add_argument("--no-forward", action="store_true", help="skip the Full/Lite forwards")
    args = parser.parse_args()
    torch.set_num_threads(args.threads)
    impl = load_impl(args.impl)
    for kind in args.features:
        torch.manual_seed(0)
        inter, lang = FEATURES[kind]()
        print(f"\n## features: {kind}")
        compare(args, impl, inter, lang, forward=not args.no_forward)


def compare(args, impl: Impl, inter, lang, forward: bool) -> None:
    """One feature kind: the timing table, the inertia comparison, the stage profile and
    (``forward``) the Full/Lite forwards."""
    reconstruct = impl.reconstruct
    modules = {"kmeans": impl.kmeans, "reconstruct": reconstruct}
    points = F.interpolate(inter, scale_factor=2, mode="bilinear", align_corners=False)
    points = points.permute(0, 2, 3, 1).reshape(-1, inter.shape[1]).contiguous()
    r, n = args.components, args.prototypes
    print(
        f"implementation: {args.impl or 'installed resireg'}; points {points.shape[0]} x "
        f"{points.shape[1]}, components {r}, prototypes {n}, threads {args.threads}"
    )

    full = reconstruct.ReSiRegFull(n_prototypes=n, n_components=r)

    def resireg_path():  # what ReSiReg Full runs: from the low-res grid, upsampling included
        return full.assign(inter)

    def torch_generic():  # the same algorithms on the materialised points
        z = F.normalize(impl.pca.pca(points, r).transform(points), dim=1)
        return impl.kmeans.kmeans(z, n, seed=0).inertia.item()

    x_np = points.numpy()

    def sklearn_fit(seed):
        z = PCA(n_components=r, random_state=0).fit_transform(x_np)
        z = z / np.linalg.norm(z, axis=1, keepdims=True)
        return KMeans(n_clusters=n, n_init=1, random_state=seed).fit(z).inertia_

    with threadpool_limits(args.threads):
        for fn in (resireg_path, torch_generic, lambda: sklearn_fit(0)):
            fn()  # warm-up (allocator, MKL/OpenMP thread pools)
        best = interleaved_best(
            {
                "sklearn": lambda: sklearn_fit(0),
                "generic": torch_generic,
                "resireg": resireg_path,
            },
            args.repeats,
        )
        rows, profile_total, n_iter = stage_profile(modules, full, inter, args.repeats)
        # Inertia over several seeds (single runs land in different local minima).
        seeds = range(args.seeds)
        inertias_torch, iters_torch = [], []
        for seed in seeds:
            m = reconstruct.ReSiRegFull(n_prototypes=n, n_components=r, seed=seed)
            with timed(modules) as rec:
                dist, _ = m.assign(inter)
            iters_torch.append(int(rec.get("n_iter", 0)))
            inertias_torch.append(float((dist.min(dim=1).values ** 2).sum()))
        inertias_sk, iters_sk = [], []
        z_sk = PCA(n_components=r, random_state=0).fit_transform(x_np)
        z_sk = z_sk / np.linalg.norm(z_sk, axis=1, keepdims=True)
        for seed in seeds:
            km = KMeans(n_clusters=n, n_init=1, random_state=seed).fit(z_sk)
            inertias_sk.append(km.inertia_)
            iters_sk.append(km.n_iter_)
        if forward:
            fwd = interleaved_best(
                {
                    "full": lambda: full(inter, lang),
                    "lite": lambda: impl.lite.ReSiRegLite()(inter, lang),
                },
                max(1, args.repeats // 2),
            )

    t_sk, t_generic, t_resireg = best["sklearn"], best["generic"], best["resireg"]
    print("\n| path | time | vs scikit-learn |\n|---|---|---|")
    print(f"| scikit-learn `PCA` + `KMeans(n_init=1)` on the points | {t_sk:.3f} s | 1.0x |")
    print(
        f"| torch `pca` + `kmeans` on the same points | {t_generic:.3f} s | "
        f"{t_sk / t_generic:.1f}x |"
    )
    print(
        f"| ReSiReg Full's clustering (`ReSiRegFull.assign`, upsampling included) | "
        f"{t_resireg:.3f} s | **{t_sk / t_resireg:.1f}x** |"
    )
    ratio = np.mean(inertias_torch) / np.mean(inertias_sk)
    print(
        f"\nk-means inertia, mean of {args.seeds} seeds: ReSiReg Full {np.mean(inertias_torch):.2f}, "
        f"scikit-learn {np.mean(inertias_sk):.2f}, ratio {ratio:.4f}; Lloyd iterations, mean: "
        f"{np.mean(iters_torch):.1f} (ours), {np.mean(iters_sk):.1f} (scikit-learn)"
    )
    print(
        f"\nReSiRegFull.assign by stage (fastest of {args.repeats} calls, {profile_total:.3f} s):\n"
    )
    print("| stage | ms | share |\n|---|---|---|")
    for name, seconds in rows:
        if seconds > 0 or name.startswith("normalisation"):
            print(f"| {name} | {seconds * 1e3:.1f} | {seconds / profile_total:.0%} |")
    if forward:
        print(
            f"\nReSiReg Full forward {fwd['full']:.3f} s ({fwd['full'] / t_resireg:.2f}x its "
            f"clustering); ReSiReg Lite forward {fwd['lite']:.3f} s ({fwd['lite'] / fwd['full']:.2f}x Full)"
        )


if __name__ == "__main__":
    main()
