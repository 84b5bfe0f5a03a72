"""The interface of a map's storage (:class:`MapStorage`): what a :class:`~resireg.mapping.SemanticMap`
asks of the voxels it holds, whatever ``storage`` it was given.

A storage holds the feature map (:attr:`MapStorage.voxels`, a
:class:`~resireg.mapping.sparse.SparseVoxels` made once the features' dimension is known), and
answers: fuse a lifted window (:meth:`~MapStorage.add`), count the voxels a window would add,
read the voxels (indices, centres, unit features, colours, a subsample), score queries (every
voxel's similarity, the candidates of a top-k, exact float64 scores of given rows, labels),
merge another storage of its kind, and save and restore its tensors. The basis of a projected
map lives here too (``None`` where the storage keeps the features as fused).
"""

from __future__ import annotations

from abc import ABC, abstractmethod
from collections.abc import Mapping
from typing import Any

import torch
from torch import Tensor

from resireg.mapping.keys import transform_keys, unpack_keys, voxel_centres
from resireg.mapping.lifting import LiftedPoints
from resireg.mapping.sparse import SparseVoxels
from resireg.mapping.voxels import VoxelMap

__all__ = ["MapStorage"]

_EMPTY = "the map is empty: add frames first"


class MapStorage(ABC):
    """The voxels of one map, in one storage kind (module docstring).

    Args:
        voxel_size: voxel edge in metres.
        lattice: ``"round"`` or ``"floor"`` (:mod:`resireg.mapping.keys`).
        device: where the tensors live.
        colour: also keep each voxel's mean colour.
        sum_dtype: an exact storage's feature sums (:data:`~resireg.mapping.voxels.SUM_DTYPES`).
        compact: a compact storage's settings (:class:`~resireg.mapping.compact.CompactSettings`
            or its mapping; ``None``: its defaults).
    """

    #: A compact storage's settings (:class:`~resireg.mapping.compact.CompactSettings`), else ``None``.
    compact: Any = None

    def __init__(
        self,
        voxel_size: float,
        lattice: str,
        device: torch.device,
        colour: bool,
        sum_dtype: str,
        compact: Any,
    ) -> None:
        self.voxel_size, self.lattice, self.device = voxel_size, lattice, torch.device(device)
        self.keeps_colour = bool(colour)
        VoxelMap(self.voxel_size, 1, self.device, self.lattice)  # checks voxel_size now
        self.dim: int | None = None  # the fused features' dimension, known at the first window
        self.voxels: SparseVoxels | None = None  # made when the dimension is known
        self.colours: VoxelMap | None = None  # an exact storage's colour sums
        self.basis: Tensor | None = None  # [D, k]: a compact map's projection
        self.basis_sha256: str | None = None

    # ------------------------------------------------------------------ what a kind gives
    @abstractmethod
    def make_voxels(self) -> SparseVoxels:
        """An empty feature map of :attr:`stored_dim` channels."""

    @abstractmethod
    def add(self, window: LiftedPoints, probe: Tensor | None) -> None:
        """Fuse one lifted window (``probe``: its voxel indices, when the caller computed them)."""

    @abstractmethod
    def bytes_per_voxel(self, dim: int | None = None) -> int:
        """Bytes per occupied voxel without the spare rows (``dim``: default the stored one)."""

    @abstractmethod
    def mean_colours(self) -> Tensor:
        """``[M, 3]`` uint8 mean colour per voxel, in :attr:`indices` order."""

    @abstractmethod
    def similarities(self, queries: Tensor) -> Tensor:
        """``[M, K]`` cosine of every voxel (:attr:`indices` order) to unit ``queries`` ``[K, k]``
        in the stored space."""

    @abstractmethod
    def classify(self, prototypes: Tensor, threshold: float | None, denoise: float | None,
                 none: int) -> Tensor:  # fmt: skip
        """:func:`resireg.mapping.classify` of the voxels' features against ``prototypes``."""

    @abstractmethod
    def candidates(
        self, q: Tensor, k: int, approx: tuple[Tensor, Tensor] | None
    ) -> tuple[Tensor, Tensor]:
        """Rows holding the ``k`` best voxels of one query ``q`` ``[1, k']`` among all, and
        their float64 scores (``approx``: its low-precision scores and bound, when scored
        with others)."""

    def joint_scores(self, queries: Tensor) -> tuple[Tensor, Tensor] | None:
        """Low-precision scores ``[rows, K]`` of several queries in one pass and their bounds,
        for :meth:`candidates`; ``None`` where the storage scores each query alone."""
        return None

    # ------------------------------------------------------------------ the basis
    @property
    def stored_dim(self) -> int | None:
        """The dimension of the stored features (:attr:`dim` unless projected)."""
        return self.dim

    @property
    def waiting(self) -> bool:
        """Whether windows wait (for a basis) instead of being fused."""
        return False

    @property
    def pending_voxels(self) -> int:
        """Distinct voxels of the windows that wait."""
        return 0

    def set_basis(self, basis: Tensor) -> None:
        """Project the features with ``basis`` ``[D, k]`` (a compact map's, before any voxel)."""
        raise ValueError("a basis is for a compact map with compact.dim set")

    def adopt_basis(self, other: MapStorage) -> None:
        """Take ``other``'s basis before a merge into this empty storage (where it has one)."""
        return None

    def fit_pending(self) -> None:
        """Fit the basis on the waiting windows and fuse them (nothing waits here)."""
        return None

    def project(self, queries: Tensor) -> Tensor:
        """Queries ``[K, D]`` in the stored space (unchanged without a basis)."""
        return queries

    # ------------------------------------------------------------------ shared
    def __len__(self) -> int:
        return 0 if self.voxels is None else len(self.voxels)

    def start(self, dim: int) -> None:
        """The first window's feature dimension: the feature map is made (unless windows wait)."""
        self.dim = int(dim)
        if self.voxels is None and not self.waiting:
            self.voxels = self.make_voxels()

    @property
    def nbytes(self) -> int:
        """Bytes held by the tensors (spare rows and the basis included)."""
        held = sum(m.nbytes for m in (self.voxels, self.colours) if m is not None)
        return held + (0 if self.basis is None else self.basis.numel() * 4)

    def count_new(self, probe: Tensor) -> int:
        """Distinct voxels of indices ``probe`` that the storage does not hold."""
        return self.voxels.count_new(probe)

    def features(self) -> tuple[Tensor, Tensor]:
        """Voxel centres ``[M, 3]`` and unit features ``[M, k]``, in :attr:`indices` order."""
        if self.voxels is None:
            raise ValueError(_EMPTY)
        return self.voxels.features()

    def subsample(self, stride: int) -> tuple[Tensor, Tensor]:
        """Centres and unit features of every ``stride``-th voxel in :attr:`indices` order,
        computed for those voxels only."""
        if self.voxels is None:
            raise ValueError(_EMPTY)
        rows = self.voxels.sorted_rows[::stride]
        centres = voxel_centres(unpack_keys(self.voxels.keys[rows]), self.voxel_size, self.lattice)
        return centres, self.voxels.unit_rows(rows)

    def merge_from(self, other: MapStorage, transform: Any) -> None:
        """Add ``other``'s voxels (the same kind and settings), moved by ``transform``."""
        if other.voxels is None or not len(other.voxels):
            return
        if self.voxels is None:
            self.dim = other.dim
            self.voxels = self.make_voxels()
        self.voxels.merge_from(other.voxels, self.moved(other.voxels, transform))
        if self.colours is not None and other.colours is not None and len(other.colours):
            self.colours.merge_from(other.colours, self.moved(other.colours, transform))

    def moved(self, vmap: SparseVoxels, transform: Any) -> Tensor | None:
        """The keys of ``vmap``'s voxels under ``transform`` (``None``: unchanged)."""
        if transform is None:
            return None
        return transform_keys(vmap.keys, transform, self.voxel_size, self.lattice)

    def tensors(self) -> dict[str, list[Tensor]]:
        """What a save writes: the feature map's tensors (``features.*``), the colours'
        (``colour.*``) and the basis, as lists of blocks."""
        out: dict[str, list[Tensor]] = {}
        for prefix, vmap in (("features", self.voxels), ("colour", self.colours)):
            if vmap is not None:
                for name, blocks in vmap.tensors().items():
                    out[f"{prefix}.{name}"] = blocks
        if self.basis is not None:
            out["basis"] = [self.basis]
        return out

    def restore(self, record: Mapping[str, Any], tensors: Mapping[str, Tensor], old: bool) -> None:
        """Fill this fresh storage from a saved map's tensors (``old``: the first format, its
        tensors as ``state``). The record's sizes are checked against the tensors before
        anything is allocated by them (the file's tensors are mapped, not read)."""

        def part(prefix: str) -> dict[str, Tensor]:
            return {k.split(".", 1)[1]: v.to(self.device) for k, v in tensors.items()
                    if k.startswith(f"{prefix}.")}  # fmt: skip

        if record["dim"] is None:
            held = sorted(k for k in tensors if k.startswith("features.") or k == "basis")
            if record["voxels"] or held:
                raise ValueError(f"dim=null (no feature yet), but voxels={record['voxels']} "
                                 f"and tensors {held}")  # fmt: skip
        else:
            self.dim = record["dim"]
            self.restore_basis(record, tensors)
            if record.get("stored_dim", self.stored_dim) != self.stored_dim:
                raise ValueError(f"stored_dim={record['stored_dim']}: the map's settings and "
                                 f"basis store {self.stored_dim}-d features")  # fmt: skip
            self.voxels = self.make_voxels()
            state = part("features")
            if old:
                self.voxels.load_state(state)
            else:
                self.voxels.load_tensors(state)
            if len(self.voxels) != int(record["voxels"]):
                raise ValueError(f"{len(self.voxels)} voxels, the record says {record['voxels']}")
        if self.colours is not None:
            state = part("colour")
            if old:
                self.colours.load_state(state or self.colours.state())
            elif state:
                self.colours.load_tensors(state)

    def restore_basis(self, record: Mapping[str, Any], tensors: Mapping[str, Tensor]) -> None:
        """The saved basis: none here (a file holding one is refused)."""
        if "basis" in tensors:
            raise ValueError(f"basis of shape {list(tensors['basis'].shape)}: expected [dim="
                             f"{self.dim}, settings.compact.dim=None]")  # fmt: skip
        if record.get("basis_sha256"):
            raise ValueError("no basis")
