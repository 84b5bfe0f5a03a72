"""3D semantic mapping with dense vision-language features (torch, numpy, scipy, scikit-learn).

The lattice and the packed voxel keys (:mod:`.keys`), patch points and every pixel at its patch's
depth as (patch, voxel, count) pairs (:mod:`.lifting`, on the camera geometry of :mod:`.geometry`),
sparse voxel maps of running feature sums (:mod:`.voxels`), of low-precision unit features
(:mod:`.compact`) and of ground-truth class votes (:mod:`.labels`), and queries: cosine
classification (optionally with RayFronts' prediction threshold and prompt denoising) and
k-nearest-neighbour label transfer (:mod:`.query`); :class:`SemanticMap` (:mod:`.semantic_map`)
puts them together, over one storage interface (:mod:`.storage`), into the object a robot feeds
with posed RGB-D windows and queries by text (docs/maps.md#robot-maps-semanticmap); its files:
:mod:`.map_file`. Conventions: docs/maps.md#the-voxel-map.

Typical online use, one batch of frames at a time::

    points, valid = patch_points(depth, K_depth, cam_to_world, grid=feats.shape[-2:])
    vmap.add(points[valid], feats.permute(0, 2, 3, 1)[valid])
    centres, voxel_feats = vmap.features()
    classes = classify(voxel_feats, text_prototypes)

or, with the encoding and the text path included::

    smap = SemanticMap(encoder, "full", voxel_size=0.05)
    smap.add(images, depth, K_depth, cam_to_world)   # a window of consecutive frames
    similarity = smap.query("a red chair")           # [M] per voxel
    best = smap.top_k("a red chair", k=10)           # exact: indices, centres, scores
    smap.save("map/"); smap.to_ply("map.ply", colour_by="query", text="a red chair")

May be imported by ``resireg.deploy``, ``resireg.ros2`` and ``resireg_train`` (``resireg-map``,
the 3D task); it imports the method, ``resireg.ovss``, ``resireg.specs`` and
``resireg.integrity`` (the encoder and the prior it is given are built by its callers).
"""

from resireg.mapping.colours import pca_colours, write_ply
from resireg.mapping.compact import CompactSettings, CompactVoxelMap
from resireg.mapping.fusion import MapFullError
from resireg.mapping.geometry import (
    nearest_downsample,
    nearest_indices,
    scale_intrinsics,
    unproject,
)
from resireg.mapping.keys import LATTICES, voxel_centres, voxel_indices
from resireg.mapping.labels import LabelVoxelMap
from resireg.mapping.lifting import LiftedPoints, patch_points, pixel_pairs, pixel_points
from resireg.mapping.map_file import MapFormatWarning, map_folder
from resireg.mapping.query import classify, nearest, transfer_labels, transfer_labels_by_voxel
from resireg.mapping.semantic_map import SemanticMap
from resireg.mapping.top_k import TopK
from resireg.mapping.voxels import VoxelMap

__all__ = [
    "scale_intrinsics",
    "nearest_indices",
    "nearest_downsample",
    "unproject",
    "patch_points",
    "pixel_points",
    "pixel_pairs",
    "LiftedPoints",
    "LATTICES",
    "VoxelMap",
    "LabelVoxelMap",
    "voxel_indices",
    "voxel_centres",
    "classify",
    "nearest",
    "transfer_labels",
    "transfer_labels_by_voxel",
    "SemanticMap",
    "MapFullError",
    "MapFormatWarning",
    "TopK",
    "map_folder",
    "CompactSettings",
    "CompactVoxelMap",
    "pca_colours",
    "write_ply",
]
