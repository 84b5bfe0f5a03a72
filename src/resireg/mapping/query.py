"""Queries on a map: open-vocabulary classification and nearest-neighbour label transfer."""

from __future__ import annotations

import numpy as np
import torch
from scipy.spatial import cKDTree
from torch import Tensor

__all__ = ["classify", "nearest", "transfer_labels"]

# Rows of the [rows, K] similarity block in classify.
_CHUNK_ELEMENTS = 1 << 24


def _check_matrix(name: str, x: Tensor, cols: int | None = None) -> None:
    if not isinstance(x, Tensor) or x.ndim != 2:
        shape = tuple(x.shape) if isinstance(x, Tensor) else type(x)
        raise ValueError(f"{name} of shape {shape}: expected a 2-D tensor")
    if cols is not None and x.shape[1] != cols:
        raise ValueError(f"{name} of shape {tuple(x.shape)}: expected {cols} columns")


def classify(features: Tensor, prototypes: Tensor) -> Tensor:
    """Class of each feature: argmax of the cosine similarity to the class prototypes.

    Both sides are L2-normalised (``v / max(||v||, 1e-12)``) in float32; ties go to the lowest
    class id. Computed in row chunks on the features' device.

    Args:
        features: ``[M, D]`` features (e.g. :meth:`VoxelMap.features`).
        prototypes: ``[K, D]`` class text embeddings.

    Returns:
        ``[M]`` int64 class ids.
    """
    _check_matrix("features", features)
    _check_matrix("prototypes", prototypes, features.shape[1])
    if prototypes.shape[0] == 0:
        raise ValueError("prototypes of shape (0, D): expected at least one class")
    protos = prototypes.to(device=features.device, dtype=torch.float32)
    protos = protos / protos.norm(dim=1, keepdim=True).clamp_min(1e-12)
    out = torch.empty(features.shape[0], dtype=torch.int64, device=features.device)
    step = max(1, _CHUNK_ELEMENTS // max(protos.shape[0], features.shape[1]))
    for start in range(0, features.shape[0], step):
        f = features[start : start + step].to(torch.float32)
        f = f / f.norm(dim=1, keepdim=True).clamp_min(1e-12)
        out[start : start + step] = torch.argmax(f @ protos.T, dim=1)
    return out


def nearest(source: Tensor, targets: Tensor, workers: int = 1) -> Tensor:
    """Index of the nearest source point (Euclidean) for every target point.

    A ``scipy.spatial.cKDTree`` over ``source`` (float64 on the host), queried with ``k=1``;
    among equidistant source points the tree returns one of them (not necessarily the lowest
    index).

    Args:
        source: ``[M, C]`` points (``C = 3`` for maps), ``M >= 1``.
        targets: ``[T, C]`` query points.
        workers: query threads for scipy (``-1``: all cores).

    Returns:
        ``[T]`` int64 indices into ``source``, on ``targets``' device.
    """
    _check_matrix("source", source)
    _check_matrix("targets", targets, source.shape[1])
    if source.shape[0] == 0:
        raise ValueError("source of shape (0, C): expected at least one point")
    if targets.shape[0] == 0:
        return torch.empty(0, dtype=torch.int64, device=targets.device)
    src = source.detach().to("cpu", torch.float64).numpy()
    tgt = targets.detach().to("cpu", torch.float64).numpy()
    if not (np.isfinite(src).all() and np.isfinite(tgt).all()):
        raise ValueError("source or targets contain non-finite coordinates")
    _, index = cKDTree(src).query(tgt, k=1, workers=workers)
    return torch.from_numpy(index.astype(np.int64)).to(targets.device)


def transfer_labels(source: Tensor, labels: Tensor, targets: Tensor, workers: int = 1) -> Tensor:
    """Label of the nearest source point for every target point (no smoothing).

    Args:
        source: ``[M, C]`` points carrying labels (e.g. predicted voxel centres).
        labels: ``[M]`` their labels (any dtype).
        targets: ``[T, C]`` points to label (e.g. ground-truth voxel centres).
        workers: query threads for scipy.

    Returns:
        ``[T]`` labels, ``labels``' dtype and device.
    """
    if not isinstance(labels, Tensor) or labels.ndim != 1 or labels.shape[0] != len(source):
        shape = tuple(labels.shape) if isinstance(labels, Tensor) else type(labels)
        raise ValueError(f"labels of shape {shape}: expected [{len(source)}], one per source point")
    return labels[nearest(source, targets, workers).to(labels.device)]
