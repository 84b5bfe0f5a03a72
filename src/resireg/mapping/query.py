"""Queries on a map: open-vocabulary classification and nearest-neighbour label transfer.

:func:`classify` is the cosine argmax; with ``threshold`` / ``denoise`` it is RayFronts'
``scripts/eval_utils.py`` ``compute_semseg_preds`` (softmax of 100 x cosine over the classes,
"no prediction" below the threshold, MaskCLIP+'s prompt denoising). :func:`transfer_labels`
is RayFronts' ``align_labels_with_knn`` (scikit-learn's ``BallTree``, the mode of the ``k``
nearest labels; ``k = 1`` is the plain nearest neighbour), :func:`transfer_labels_by_voxel` its
``k = 0`` case (``align_labels_with_vox_grid``: same voxel or nothing).
"""

from __future__ import annotations

import numpy as np
import torch
from scipy.spatial import cKDTree
from torch import Tensor

__all__ = ["classify", "nearest", "transfer_labels", "transfer_labels_by_voxel"]

# Rows of the [rows, K] similarity block in classify.
_CHUNK_ELEMENTS = 1 << 24


def _check_matrix(name: str, x: Tensor, cols: int | None = None) -> None:
    if not isinstance(x, Tensor) or x.ndim != 2:
        shape = tuple(x.shape) if isinstance(x, Tensor) else type(x)
        raise ValueError(f"{name} of shape {shape}: expected a 2-D tensor")
    if cols is not None and x.shape[1] != cols:
        raise ValueError(f"{name} of shape {tuple(x.shape)}: expected {cols} columns")


def classify(
    features: Tensor,
    prototypes: Tensor,
    threshold: float | None = None,
    denoise: float | None = None,
    temperature: float = 100.0,
    none: int = -1,
    denoise_chunk: int = 10_000,
) -> Tensor:
    """Class of each feature: argmax of the cosine similarity to the class prototypes.

    Both sides are L2-normalised (``v / max(||v||, 1e-12)``) in float32; ties go to the lowest
    class id. Computed in row chunks on the features' device.

    With ``threshold`` or ``denoise`` set, the rule of RayFronts' ``compute_semseg_preds``
    (``scripts/eval_utils.py``): the class probabilities are ``softmax(temperature * cosine)``
    over the classes (its ``utils.compute_cos_sim(..., softmax=True)``, temperature 100);
    ``denoise``: a class whose largest probability over a chunk of ``denoise_chunk`` consecutive
    features is below ``denoise`` is removed from that chunk (MaskCLIP+'s prompt denoising,
    applied per chunk of 10,000 rows as RayFronts' ``chunk_size`` does); the class is the
    argmax of the probabilities, and a feature whose largest probability is below
    ``threshold`` gets ``none`` ("no prediction").

    Args:
        features: ``[M, D]`` features (e.g. :meth:`VoxelMap.features`).
        prototypes: ``[K, D]`` class text embeddings.
        threshold: ``None`` or the probability below which nothing is predicted (RayFronts: 0.1).
        denoise: ``None`` or the prompt-denoising probability (RayFronts' configs: 0.5).
        temperature: softmax temperature of the probabilities.
        none: the id of "no prediction".
        denoise_chunk: rows per prompt-denoising chunk.

    Returns:
        ``[M]`` int64 class ids (and ``none``).
    """
    _check_matrix("features", features)
    _check_matrix("prototypes", prototypes, features.shape[1])
    if prototypes.shape[0] == 0:
        raise ValueError("prototypes of shape (0, D): expected at least one class")
    protos = prototypes.to(device=features.device, dtype=torch.float32)
    protos = protos / protos.norm(dim=1, keepdim=True).clamp_min(1e-12)
    out = torch.empty(features.shape[0], dtype=torch.int64, device=features.device)
    rule = threshold is not None or denoise is not None
    step = max(1, _CHUNK_ELEMENTS // max(protos.shape[0], features.shape[1]))
    if denoise is not None:  # the chunks of the denoising rule
        step = denoise_chunk
    for start in range(0, features.shape[0], step):
        f = features[start : start + step].to(torch.float32)
        f = f / f.norm(dim=1, keepdim=True).clamp_min(1e-12)
        sim = f @ protos.T
        if not rule:
            out[start : start + step] = torch.argmax(sim, dim=1)
            continue
        prob = torch.softmax(temperature * sim, dim=1)
        if denoise is not None:
            low = prob.amax(dim=0) < denoise
            prob[:, low] = -torch.inf
        value, cls = torch.max(prob, dim=1)
        if threshold is not None:
            cls = torch.where(value < threshold, none, cls)
        out[start : start + step] = cls
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


def transfer_labels(source: Tensor, labels: Tensor, targets: Tensor, k: int = 1) -> Tensor:
    """Label of every target point from its ``k`` nearest source points (Euclidean).

    RayFronts' ``align_labels_with_knn`` (``scripts/eval_utils.py``): a scikit-learn
    ``BallTree`` over the source points (float64 on the host, default leaf size), queried with
    ``k``; the label is the mode of the ``k`` labels (``torch.mode``: ties to the smallest
    label). ``k = 1`` is the nearest neighbour, no smoothing. Among equidistant source points
    the tree's choice is kept, so the same float32 points give RayFronts' labels.

    Args:
        source: ``[M, C]`` points carrying labels (e.g. predicted voxel centres), ``M >= k``.
        labels: ``[M]`` integer labels.
        targets: ``[T, C]`` points to label (e.g. ground-truth voxel centres).
        k: neighbours (>= 1).

    Returns:
        ``[T]`` labels, ``labels``' dtype and device.
    """
    from sklearn.neighbors import BallTree  # core dependency; imported only where it is used

    _check_matrix("source", source)
    _check_matrix("targets", targets, source.shape[1])
    if not isinstance(labels, Tensor) or labels.ndim != 1 or labels.shape[0] != len(source):
        shape = tuple(labels.shape) if isinstance(labels, Tensor) else type(labels)
        raise ValueError(f"labels of shape {shape}: expected [{len(source)}], one per source point")
    if isinstance(k, bool) or not isinstance(k, int) or k < 1:
        raise ValueError(f"k={k!r}: expected an integer >= 1")
    if source.shape[0] < k:
        raise ValueError(f"source of shape {tuple(source.shape)}: fewer points than k={k}")
    if targets.shape[0] == 0:
        return labels[:0]
    src = source.detach().to("cpu", torch.float64).numpy()
    tgt = targets.detach().to("cpu", torch.float64).numpy()
    if not (np.isfinite(src).all() and np.isfinite(tgt).all()):
        raise ValueError("source or targets contain non-finite coordinates")
    _, index = BallTree(src).query(tgt, k=k)
    near = labels.cpu()[torch.from_numpy(index.astype(np.int64))]  # [T, k]
    out = near[:, 0] if k == 1 else torch.mode(near, dim=1).values
    return out.to(labels.device)


def transfer_labels_by_voxel(source: Tensor, labels: Tensor, targets: Tensor, fill: int) -> Tensor:
    """Label of every target voxel from the source voxel of the same index, else ``fill``.

    RayFronts' ``k = 0`` alignment (``align_labels_with_vox_grid``: the union of both voxel
    sets, a target without a source voxel gets label 0, "no prediction").

    Args:
        source: ``[M, 3]`` int64 voxel indices carrying ``labels`` ``[M]``.
        targets: ``[T, 3]`` int64 voxel indices of the same lattice.
        fill: the label of targets with no source voxel.

    Returns:
        ``[T]`` labels, ``labels``' dtype and device.
    """
    from resireg.mapping.keys import pack_keys

    for name, x in (("source", source), ("targets", targets)):
        if not isinstance(x, Tensor) or x.ndim != 2 or x.shape[1] != 3 or x.is_floating_point():
            shape = tuple(x.shape) if isinstance(x, Tensor) else type(x)
            raise ValueError(f"{name} of shape {shape}: expected [N, 3] integer voxel indices")
    keys = pack_keys(source.long().cpu())
    order = torch.argsort(keys)
    keys = keys[order]
    want = pack_keys(targets.long().cpu())
    pos = torch.searchsorted(keys, want).clamp_max(max(len(keys) - 1, 0))
    out = torch.full((len(want),), fill, dtype=labels.dtype)
    if len(keys):
        hit = keys[pos] == want
        out[hit] = labels.cpu()[order[pos[hit]]]
    return out.to(labels.device)
