"""Building a map: a window's images resized and encoded, its features checked, lifted and fused
(the bodies of :meth:`SemanticMap.encode <resireg.mapping.SemanticMap.encode>`,
:meth:`~resireg.mapping.SemanticMap.resized` and :meth:`~resireg.mapping.SemanticMap.fuse`)."""

from __future__ import annotations

from typing import Any

import torch
import torch.nn.functional as F
from torch import Tensor

from resireg.errors import MapError
from resireg.mapping.lifting import lift_grid
from resireg.method.checks import check_features
from resireg.method.variants import apply_variant

#: A :class:`~resireg.mapping.SemanticMap` (not imported: the map sits above this module).
SemanticMap = Any

__all__ = ["MapFullError", "encode_resized", "fuse_window", "resize_images"]


class MapFullError(MapError):
    """A window would take the map past its ``max_voxels`` budget (nothing of it was added)."""


@torch.no_grad()
def encode_resized(smap: SemanticMap, raw: Tensor) -> Tensor:
    """:meth:`SemanticMap.encode` of images already resized by :func:`resize_images`."""
    if smap.takes_prior and smap.prior is None:
        raise ValueError(f"variant={smap.variant_name!r} takes a prior: pass prior=")
    x = smap.encoder.input_rule.normalize(raw)
    modes = {m: m.training for m in smap.encoder.modules()}
    smap.encoder.eval()
    try:
        with torch.autocast(smap.device.type, enabled=False):
            out = smap.encoder.encode(x)
            seg = None
            if smap.takes_prior:
                seg = smap.prior(raw).to(out.intermediates.device)
            dense = apply_variant(smap.variant, out.intermediates, out.language, seg)
    finally:
        for module, mode in modes.items():
            module.training = mode
    return dense


def resize_images(smap: SemanticMap, images: Tensor) -> Tensor:
    """RGB ``[B, 3, H, W]`` -> float ``[B, 3, H', W']`` in [0, 1] by the encoder's input rule."""
    if not isinstance(images, Tensor) or images.ndim != 4 or images.shape[1] != 3:
        shape = tuple(images.shape) if isinstance(images, Tensor) else type(images)
        raise ValueError(f"images of shape {shape}: expected an RGB [B, 3, H, W] tensor")
    if smap.encoder is None:
        raise ValueError("this map has no encoder: pass features to fuse() instead")
    rule = smap.encoder.input_rule
    return torch.stack([rule.resize(im, smap.short_side) for im in images]).to(smap.encoder.device)


@torch.no_grad()
def fuse_window(smap: SemanticMap, features: Tensor, depth: Tensor, intrinsics: Tensor,
                cam_to_world: Tensor, colour: Tensor | None, lifted: dict | None, name: str) -> int:  # fmt: skip
    """:meth:`SemanticMap.fuse`, its features checked under ``name`` (:meth:`SemanticMap.add`:
    the encoder output, checked once): lifted (:func:`~resireg.mapping.lifting.lift_grid`, once
    per grid in ``lifted``), counted against ``max_voxels``, given to the map's storage."""
    if not isinstance(features, Tensor) or features.ndim != 4:
        shape = tuple(features.shape) if isinstance(features, Tensor) else type(features)
        raise ValueError(f"features of shape {shape}: expected [B, D, h, w]")
    # A NaN feature would stay in its voxel's sum for good, and integer features would be
    # fused as they are: refused here (resireg.method.checks, one isfinite reduction per tensor).
    check_features(name, features)
    check_features("intrinsics", intrinsics)
    check_features("cam_to_world", cam_to_world)
    if not isinstance(depth, Tensor) or not depth.is_floating_point():
        raise TypeError(f"depth must be a floating-point tensor of metres, got "
                        f"{depth.dtype if isinstance(depth, Tensor) else type(depth).__name__}")  # fmt: skip
    if colour is not None:
        check_features("colour", colour)
    if smap.dim is not None and features.shape[1] != smap.dim:
        raise ValueError(f"features of shape {tuple(features.shape)}: the map has "
                         f"dim={smap.dim}")  # fmt: skip
    with torch.autocast(smap.device.type, enabled=False):
        grid = tuple(features.shape[-2:])
        cache = {} if lifted is None else lifted
        if grid not in cache:
            cache[grid] = lift_grid(smap.points, depth.to(smap.device),
                                    intrinsics.to(smap.device), cam_to_world.to(smap.device),
                                    grid, smap.voxel_size, smap.lattice)  # fmt: skip
        feats = features.permute(0, 2, 3, 1).float().to(smap.device)
        if smap.voxels is None:
            smap.store.start(int(feats.shape[-1]))
        rgb = None
        if smap.keeps_colour and colour is not None:
            rgb = F.adaptive_avg_pool2d(colour.float().to(smap.device), grid)
            rgb = rgb.permute(0, 2, 3, 1)
        window = cache[grid].with_features(feats, rgb)
        probe = None
        if smap.max_voxels is not None or smap.store.waiting:  # (the voxels' indices)
            probe = window.voxel_index(smap.voxel_size, smap.lattice)
        before = len(smap)
        if smap.max_voxels is not None:
            new = smap.store.count_new(probe)
            held = before + smap.store.pending_voxels
            if held + new > smap.max_voxels:
                raise MapFullError(
                    f"max_voxels={smap.max_voxels}: this window of {features.shape[0]} "
                    f"frames adds {new} voxels to the map's {held}; raise max_voxels "
                    f"(each voxel holds ~{smap.bytes_per_voxel(feats.shape[-1])} bytes), "
                    "use a coarser voxel_size, sum_dtype=float32 or storage=compact, or "
                    "save this map and start a new one"
                )
        smap.store.add(window, probe)
    smap.frames += int(features.shape[0])
    smap.windows += 1
    return len(smap) - before
