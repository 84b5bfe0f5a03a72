"""A map's colours and its point cloud file: PCA colours, a diverging ramp, a class palette, PLY.

What :meth:`resireg.mapping.SemanticMap.colours_by` and :meth:`~resireg.mapping.SemanticMap.to_ply`
colour a map's voxels with (:data:`COLOUR_BY`), also used by the live node's views.
"""

from __future__ import annotations

from collections.abc import Sequence
from pathlib import Path
from typing import Any

import numpy as np
import torch
from torch import Tensor

from resireg.integrity import atomic_write

__all__ = [
    "COLOUR_BY",
    "diverging_ramp",
    "palette",
    "pca_colours",
    "voxel_colours",
    "write_ply",
]

#: What :meth:`SemanticMap.to_ply` colours the voxels by.
COLOUR_BY = ("rgb", "pca", "query", "class")


def pca_colours(features: Tensor, sample: int = 100_000, seed: int = 0) -> Tensor:
    """``[M, D]`` features -> ``[M, 3]`` uint8 colours: their first three principal components
    (the top eigenvectors of the float64 covariance of up to ``sample`` rows, ``torch.linalg.eigh``:
    exact and deterministic, ``D x D`` whatever ``M``), each scaled from its 1st..99th percentile
    to 0..255. Each component's sign is fixed so its largest loading is positive."""
    x = features.float()
    if x.shape[0] == 0:
        return torch.zeros(0, 3, dtype=torch.uint8)
    g = torch.Generator().manual_seed(seed)
    rows = torch.randperm(x.shape[0], generator=g)[:sample] if x.shape[0] > sample else None
    fit = x if rows is None else x[rows.to(x.device)]
    mean = fit.double().mean(0, keepdim=True)
    q = min(3, *fit.shape)
    centred = fit.double() - mean
    _, vectors = torch.linalg.eigh(centred.T @ centred)  # ascending eigenvalues
    v = vectors[:, -q:].flip(1)
    v = v * torch.sign(v.gather(0, v.abs().argmax(0, keepdim=True)))
    proj = ((x.double() - mean) @ v).float()  # [M, q]
    lo = torch.quantile(proj[:sample], 0.01, dim=0)
    hi = torch.quantile(proj[:sample], 0.99, dim=0)
    unit = ((proj - lo) / (hi - lo).clamp_min(1e-12)).clamp(0, 1)
    out = torch.zeros(x.shape[0], 3)
    out[:, :q] = unit.cpu()
    return (out * 255).round().to(torch.uint8)


def diverging_ramp(values: Tensor) -> Tensor:
    """``[M]`` values -> ``[M, 3]`` uint8 from blue (lowest) through white to red (highest), the
    values scaled min..max (a diverging ramp; no matplotlib in ``resireg``)."""
    v = values.float().cpu()
    if v.numel() == 0:
        return torch.zeros(0, 3, dtype=torch.uint8)
    t = (v - v.min()) / (v.max() - v.min()).clamp_min(1e-12)
    up, down = (2 * t).clamp(0, 1), (2 - 2 * t).clamp(0, 1)
    return (torch.stack([up, torch.minimum(up, down), down], 1) * 255).round().to(torch.uint8)


def palette(labels: Tensor) -> Tensor:
    """``[M]`` class ids -> ``[M, 3]`` uint8, a fixed distinct colour per id (golden-ratio hues)."""
    ids = labels.long().cpu().clamp_min(0).double()
    h = (ids * 0.618033988749895) % 1.0
    i = torch.floor(h * 6)
    f = h * 6 - i
    s, v = 0.75, 0.95
    p, q, t = torch.full_like(h, v * (1 - s)), v * (1 - s * f), v * (1 - s * (1 - f))
    vv = torch.full_like(h, v)
    table = [(vv, t, p), (q, vv, p), (p, vv, t), (p, q, vv), (t, p, vv), (vv, p, q)]
    out = torch.zeros(h.shape[0], 3, dtype=torch.float64)
    for k, (r, g, b) in enumerate(table):
        m = i == k
        out[m] = torch.stack([r[m], g[m], b[m]], 1)
    return (out * 255).round().to(torch.uint8)


def write_ply(path: str | Path, points: Tensor, colours: Tensor) -> Path:
    """A binary little-endian PLY of ``[M, 3]`` float32 points with ``[M, 3]`` uint8 colours.

    Written by hand (a 6-line header and one numpy record array): the format is fixed and
    small, and no PLY writer is a core dependency (open3d is a test-only reference)."""
    path = Path(path)
    pts = points.detach().cpu().numpy().astype("<f4")
    rgb = colours.detach().cpu().numpy().astype(np.uint8)
    rec = np.empty(pts.shape[0], dtype=[("x", "<f4"), ("y", "<f4"), ("z", "<f4"),
                                        ("red", "u1"), ("green", "u1"), ("blue", "u1")])  # fmt: skip
    for i, name in enumerate("xyz"):
        rec[name] = pts[:, i]
    for i, name in enumerate(("red", "green", "blue")):
        rec[name] = rgb[:, i]
    header = (
        "ply\nformat binary_little_endian 1.0\n"
        f"element vertex {pts.shape[0]}\n"
        "property float x\nproperty float y\nproperty float z\n"
        "property uchar red\nproperty uchar green\nproperty uchar blue\nend_header\n"
    )

    def write(tmp: Path) -> None:
        with open(tmp, "wb") as f:
            f.write(header.encode("ascii"))
            f.write(rec.tobytes())

    path.parent.mkdir(parents=True, exist_ok=True)
    atomic_write(path, write)
    return path


def voxel_colours(
    smap: Any, colour_by: str = "pca", text: str | None = None, classes: Sequence[str] | None = None
) -> Tensor:
    """``[M, 3]`` uint8 colour per voxel of a :class:`~resireg.mapping.SemanticMap`
    (:data:`COLOUR_BY`): ``rgb`` (mean colour), ``pca`` (:func:`pca_colours`), ``query``
    (similarity to ``text``, blue..red) or ``class`` (the ``classify`` class of ``classes``,
    a fixed colour per class)."""
    if colour_by not in COLOUR_BY:
        raise ValueError(f"colour_by={colour_by!r}: expected one of {COLOUR_BY}")
    if colour_by == "rgb":
        return smap.mean_colours()
    if colour_by == "pca":
        return pca_colours(smap.features()[1])
    if colour_by == "query":
        if not text:
            raise ValueError("colour_by='query' needs text=")
        return diverging_ramp(smap.query(text))
    if not classes:
        raise ValueError("colour_by='class' needs classes=")
    return palette(smap.classify(classes))
