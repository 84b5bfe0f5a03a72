"""A compact map's projection basis: fitted on its first features, or read from a saved map or file.

:func:`fit_basis` is an uncentred PCA (:mod:`resireg.method.pca`): the top ``k`` eigenvectors of
the features' second moment, in float64 (the mean direction is kept, as every cosine needs it);
:func:`load_basis` reads the ``basis`` of a saved map (verified as a load verifies it) or of a
``.safetensors`` file (``compact.basis``). A basis is recorded by its SHA-256
(:func:`tensor_sha256`): maps merge only with the same one.
"""

from __future__ import annotations

import hashlib
from pathlib import Path

import torch
from torch import Tensor

from resireg.integrity import IntegrityError, read_json, verify_digests
from resireg.mapping.map_file import MAP_JSON, inside_folder, map_folder
from resireg.mapping.tensor_file import read_tensors

__all__ = ["fit_basis", "load_basis", "tensor_sha256"]


def tensor_sha256(t: Tensor) -> str:
    """SHA-256 of a tensor's bytes (on the CPU, contiguous)."""
    return hashlib.sha256(t.detach().cpu().contiguous().numpy().tobytes()).hexdigest()


def fit_basis(rows: Tensor, dim: int) -> Tensor:
    """The basis ``[D, dim]`` float64 of feature rows ``[N, D]``: the top ``dim`` eigenvectors of
    their uncentred second moment (:func:`resireg.method.pca.pca_from_moments` with a zero first
    moment: the mean direction is kept, as every cosine needs it). A ValueError under 2 rows."""
    from resireg.method.pca import gram, pca_from_moments

    rows = rows.to(torch.float64)
    if rows.shape[0] < 2:
        raise ValueError(f"a compact map fits its basis on >= 2 features; it has "
                         f"{rows.shape[0]}: map more frames first")  # fmt: skip
    fit = pca_from_moments(gram(rows), rows.new_zeros(rows.shape[1]), rows.shape[0], dim)
    return fit.components.T


def load_basis(path: str | Path) -> Tensor:
    """A projection basis ``[D, k]`` float32: the ``basis`` of a saved map (a map folder or a
    run folder, :func:`map_folder`; verified as :meth:`SemanticMap.load` verifies it) or the
    tensor ``basis`` of a ``.safetensors`` file."""
    path = Path(path).expanduser()
    if path.is_dir():
        try:
            path = map_folder(path)
        except FileNotFoundError as err:
            raise ValueError(f"compact.basis={err}") from None
        record = read_json(path / MAP_JSON, "saved map record")
        if not isinstance(record, dict) or not record.get("basis_sha256"):
            raise ValueError(f"compact.basis={str(path)!r}: the map records no basis")
        name = inside_folder(path, record.get("tensors"), "tensors", path / MAP_JSON)
        verify_digests(path, {name.name: (record.get("sha256") or {}).get(name.name, "")},
                       "saved map")  # fmt: skip
        tensors = read_tensors(name, "saved map")
        basis = tensors.get("basis")
        if basis is None or tensor_sha256(basis) != record["basis_sha256"]:
            raise IntegrityError(f"{name}: no basis of the recorded SHA-256")
    elif path.is_file():
        basis = read_tensors(path, "basis file").get("basis")
    else:
        raise ValueError(f"compact.basis={str(path)!r}: no such map folder or file")
    if basis is None or basis.ndim != 2 or not basis.is_floating_point():
        raise ValueError(f"compact.basis={str(path)!r}: expected a [D, k] float tensor 'basis'")
    return basis.to(torch.float32).clone()
