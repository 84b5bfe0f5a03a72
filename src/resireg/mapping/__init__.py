"""3D semantic mapping with dense vision-language features (torch, numpy, scipy only).

Patch points from depth, intrinsics and pose (:mod:`.geometry`), sparse voxel maps of running
feature sums and of ground-truth class votes (:mod:`.voxels`), and queries: cosine
classification and nearest-neighbour label transfer (:mod:`.query`). Conventions:
docs/design.md section 10.1.

Typical online use, one batch of frames at a time::

    points, valid = patch_points(depth, K_depth, cam_to_world, grid=feats.shape[-2:])
    vmap.add(points[valid], feats.permute(0, 2, 3, 1)[valid])
    centres, voxel_feats = vmap.features()
    classes = classify(voxel_feats, text_prototypes)
"""

from resireg.mapping.geometry import (
    nearest_downsample,
    nearest_indices,
    patch_points,
    scale_intrinsics,
    unproject,
)
from resireg.mapping.query import classify, nearest, transfer_labels
from resireg.mapping.voxels import LabelVoxelMap, VoxelMap, voxel_indices

__all__ = [
    "scale_intrinsics",
    "nearest_indices",
    "nearest_downsample",
    "unproject",
    "patch_points",
    "VoxelMap",
    "LabelVoxelMap",
    "voxel_indices",
    "classify",
    "nearest",
    "transfer_labels",
]
