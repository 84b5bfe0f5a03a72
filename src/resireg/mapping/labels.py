"""Ground-truth class votes per voxel (:class:`LabelVoxelMap`): the 3D task's labels."""

from __future__ import annotations

import torch
from torch import Tensor

from resireg.mapping.blocks import RowBlocks
from resireg.mapping.sparse import SparseVoxels, check_count

__all__ = ["LabelVoxelMap"]


class LabelVoxelMap(SparseVoxels):
    """Ground-truth class votes per voxel.

    Every point with a label in ``0 .. num_classes - 1`` adds one vote for its class to its voxel;
    points with any other label (``ignore_index``, e.g. 255, or any other id outside the range)
    are dropped and create no voxel. Their numbers are counted in :attr:`ignored` (labels equal
    to ``ignore_index``) and :attr:`out_of_range` (all other dropped labels), so a label mapping
    that leaks unexpected ids can be detected.

    Args:
        voxel_size: voxel edge in metres (> 0).
        num_classes: number of classes ``K``.
        ignore_index: the "no label" id; must lie outside ``0 .. K - 1``.
        device: where the map's tensors live.
        lattice: ``"round"`` or ``"floor"`` (module docstring).
    """

    def __init__(
        self,
        voxel_size: float,
        num_classes: int,
        ignore_index: int = 255,
        device: torch.device | str = "cpu",
        lattice: str = "round",
    ) -> None:
        super().__init__(voxel_size, device, lattice)
        self.num_classes = check_count("num_classes", num_classes)
        if isinstance(ignore_index, bool) or not isinstance(ignore_index, int):
            raise ValueError(f"ignore_index={ignore_index!r}: expected an integer")
        if 0 <= ignore_index < self.num_classes:
            raise ValueError(
                f"ignore_index={ignore_index}: it is a class id (num_classes={self.num_classes})"
            )
        self.ignore_index = ignore_index
        self.ignored = 0
        self.out_of_range = 0
        self._accumulator("votes", (self.num_classes,), torch.int64)

    def __repr__(self) -> str:
        return (
            f"LabelVoxelMap(voxel_size={self.voxel_size}, num_classes={self.num_classes}, "
            f"device={self.device}, lattice={self.lattice!r}, voxels={len(self)})"
        )

    @property
    def _votes(self) -> RowBlocks:  # [capacity, K] int64 class votes
        return self._acc["votes"]

    def add(self, points: Tensor, labels: Tensor) -> None:
        """Add one vote per labelled point.

        Args:
            points: ``[N, 3]`` world coordinates in metres (finite).
            labels: ``[N]`` integer class ids; ids outside ``0 .. K - 1`` are dropped.
        """
        if not isinstance(labels, Tensor) or labels.ndim != 1:
            shape = tuple(labels.shape) if isinstance(labels, Tensor) else type(labels)
            raise ValueError(f"labels of shape {shape}: expected an [N] integer tensor")
        if labels.is_floating_point() or labels.is_complex() or labels.dtype == torch.bool:
            raise ValueError(f"labels of dtype {labels.dtype}: expected an integer tensor")
        points = self._check_points(points, labels.shape[0])
        labels = labels.to(device=self.device, dtype=torch.int64)
        keep = (labels >= 0) & (labels < self.num_classes)
        n_ignored = int((labels == self.ignore_index).sum())
        self.ignored += n_ignored
        self.out_of_range += int((~keep).sum()) - n_ignored
        points, labels = points[keep], labels[keep]
        if points.shape[0] == 0:
            return
        rows = self._rows_of(points)
        self._votes.flat_add_(rows, labels, torch.ones_like(rows))

    @property
    def votes(self) -> Tensor:
        """``[M, K]`` int64 votes per voxel and class, in the order of :attr:`indices`."""
        return self._votes.gather(self._rows)

    @property
    def counts(self) -> Tensor:
        """``[M]`` int64 labelled points per voxel."""
        return self.votes.sum(dim=1)

    def labels(self) -> tuple[Tensor, Tensor]:
        """Voxel centres ``[M, 3]`` float32 and labels ``[M]`` int64, the most-voted class.

        Ties go to the lowest class id (``torch.argmax`` returns the first maximum).
        """
        return self.centres(), torch.argmax(self.votes, dim=1)
