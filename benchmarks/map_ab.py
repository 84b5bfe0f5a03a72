"""A refactor of the map keeps its results and its speed: one checkout's numbers, to compare
with another's (issue 52 moved ``SemanticMap``'s storage, lifting and files into modules).

``digests``: SHA-256 prefixes of a map's outputs for exact and compact storage with patch and
pixel points (colour kept, a compact basis fitted, a merge of two runs): indices, unit features,
``query``, ``top_k`` (whole map and a ball), ``classify_features``, mean colours, ``region``, the
saved tensors, ``nbytes`` and the settings; two checkouts that keep the results print the same
line. ``time``: CPU seconds (``time.process_time``, one thread) of fusing 40 windows of 2 frames
(16 x 20 grid, D = 256), 20 ``top_k`` and 20 ``query`` calls of 8 texts, per storage and points.

    PYTHONPATH=<checkout>/src python benchmarks/map_ab.py digests > a.json   # then cmp
    PYTHONPATH=<checkout>/src python benchmarks/map_ab.py time              # alternate, min of 3
"""

from __future__ import annotations

import argparse
import glob
import hashlib
import json
import tempfile
import time

import torch


def _digest(t: torch.Tensor) -> str:
    return hashlib.sha256(t.detach().contiguous().cpu().numpy().tobytes()).hexdigest()[:16]


def _windows(
    n: int, size: tuple[int, int], grid: tuple[int, int], dim: int, span: float, focal: float
):
    g = torch.Generator().manual_seed(1 if dim == 32 else 0)
    (hh, ww), out = size, []
    for _ in range(n):
        depth = 1.0 + 3 * torch.rand(2, hh, ww, generator=g)
        k = torch.tensor([[focal, 0, (ww - 1) / 2], [0, focal, (hh - 1) / 2], [0, 0, 1]])
        pose = torch.eye(4).repeat(2, 1, 1)
        pose[:, :3, 3] = torch.rand(2, 3, generator=g) * span
        out.append((torch.randn(2, dim, *grid, generator=g), depth, k, pose,
                    torch.rand(2, 3, hh, ww, generator=g)))  # fmt: skip
    return out, g


def digests() -> dict:
    from safetensors.torch import load_file

    from resireg.mapping import SemanticMap

    wins, g = _windows(12, (48, 64), (12, 16), 32, 2.0, 50.0)
    q = torch.nn.functional.normalize(torch.randn(4, 32, generator=g), dim=-1)
    out = {}
    for storage in ("exact", "compact"):
        for points in ("patch", "pixel"):
            kw = {"compact": {"dim": 8, "basis_rows": 500}} if storage == "compact" else {}
            m = SemanticMap(None, "bb", 0.1, storage=storage, points=points, **kw)
            for win in wins[:6]:
                m.fuse(*win)
            other = SemanticMap(None, "bb", 0.1, storage=storage, points=points, **kw)
            if m.basis is not None:
                other.set_basis(m.basis)
            for win in wins[6:]:
                other.fuse(*win)
            m.merge(other)
            ball = {"centre": [1.0, 1.0, 2.0], "radius": 1.0}
            folder = tempfile.mkdtemp()
            m.save(folder)
            saved = load_file(glob.glob(f"{folder}/map-*.safetensors")[0])
            out[f"{storage}/{points}"] = [
                len(m), _digest(m.indices), _digest(m.features()[1]), _digest(m.query(q)),
                [_digest(t.scores) + _digest(t.indices) for t in m.top_k(q, k=5)],
                _digest(m.top_k(q[0], k=5, **ball).scores),
                _digest(m.classify_features(m.project(q))), _digest(m.mean_colours()),
                _digest(m.region(**ball)), sorted((k, _digest(v)) for k, v in saved.items()),
                m.nbytes, m.settings(),
            ]  # fmt: skip
    return out


def times() -> dict:
    from resireg.mapping import SemanticMap

    wins, g = _windows(40, (60, 80), (16, 20), 256, 3.0, 60.0)
    q = torch.randn(8, 256, generator=g)
    out = {}
    for storage in ("exact", "compact"):
        for points in ("patch", "pixel"):
            kw = {"compact": {"dim": 64, "basis_rows": 2000}} if storage == "compact" else {}
            m = SemanticMap(None, "bb", 0.05, storage=storage, points=points, **kw)
            t = time.process_time()
            for win in wins:
                m.fuse(*win)
            m.fit_pending()
            out[f"{storage}/{points}/fuse_s"] = time.process_time() - t
            t = time.process_time()
            for _ in range(20):
                m.top_k(q, k=10)
            out[f"{storage}/{points}/top_k_s"] = time.process_time() - t
            t = time.process_time()
            for _ in range(20):
                m.query(q)
            out[f"{storage}/{points}/query_s"] = time.process_time() - t
            out[f"{storage}/{points}/voxels"] = len(m)
    return out


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.split("\n")[0])
    parser.add_argument("what", choices=("digests", "time"))
    args = parser.parse_args()
    torch.set_num_threads(1)
    print(json.dumps(digests() if args.what == "digests" else times(), sort_keys=True))


if __name__ == "__main__":
    main()
