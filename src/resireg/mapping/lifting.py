"""Feature lifting under the literal reading of the paper: every pixel with its patch's feature.

The paper's sentence: "patch centres are unprojected with the depth camera model; depth is
aggregated per patch by nearest downsampling to feature resolution and back to the depth grid".
OTAS's code (``src/model.py``, ``batch_embed_rgbd``), which the sentence describes, unprojects one
point per patch (:func:`resireg.mapping.patch_points` is that reading). Read literally, the
patch depth brought back to the depth grid puts *every* pixel of a patch on its own ray at the
patch's depth, all carrying the patch's feature (docs/design.md section 10.1):

- the depth ``[B, H, W]`` is nearest-downsampled to the feature grid ``(h, w)``
  (:func:`resireg.mapping.nearest_downsample`) and nearest-upsampled back (the same rule), so
  pixel ``(v, u)`` belongs to patch ``(rows[v], cols[u])`` with ``rows = nearest_indices(h, H)``;
- pixel ``(u, v)`` of patch ``p`` is the world point ``R (z_p K^-1 [u, v, 1]) + t``; a patch is
  lifted iff its depth ``z_p`` is finite and ``> 0`` and the frame's pose is finite.

Pixels of one patch share one feature, so the map needs only how many pixels of each patch fall
in each voxel: :func:`pixel_pairs` returns those (patch, voxel, count) triples, and
:meth:`resireg.mapping.VoxelMap.add_pairs` adds ``count * feature`` per pair. The feature work is
then proportional to the pairs (a small multiple of the patches), not to the ~550k pixels of a
640 x 864 frame; the per-pixel work is a few float64 operations per pixel (below).
"""

from __future__ import annotations

import torch
from torch import Tensor

from resireg.mapping.geometry import (
    _check_hw,
    _check_intrinsics,
    nearest_downsample,
    nearest_indices,
    unproject,
)
from resireg.mapping.voxels import _check_voxel_size, check_lattice, lattice_index

__all__ = ["pixel_pairs", "pixel_points"]

# Patches per chunk in pixel_pairs (a chunk's per-pixel temporaries: ~ 8 bytes x pixels x 3).
_CHUNK_PATCHES = 1 << 13


def _patch_of_pixels(n_in: int, n_out: int, device: torch.device) -> tuple[Tensor, Tensor]:
    """Per patch (one axis) its pixels, padded: ``[n_out, m]`` pixel indices and a mask.

    Pixel ``x`` belongs to patch ``nearest_indices(n_out, n_in)[x]`` (the nearest-upsampling
    rule); ``m`` is the largest number of pixels of a patch (``n_in / n_out`` for an integer
    factor, then nothing is padded)."""
    owner = nearest_indices(n_out, n_in, device)  # [n_in] patch of every pixel
    size = torch.bincount(owner, minlength=n_out)
    m = int(size.max())
    first = torch.cumsum(size, 0) - size  # owner is non-decreasing: a patch's pixels are a run
    step = torch.arange(m, device=device)
    mask = step < size[:, None]
    # padded entries repeat the patch's last pixel, so they change no minimum or maximum
    return first[:, None] + torch.minimum(step[None], (size - 1)[:, None]), mask


def pixel_points(
    depth: Tensor, intrinsics: Tensor, cam_to_world: Tensor, grid: tuple[int, int]
) -> tuple[Tensor, Tensor, Tensor]:
    """World points of every pixel at its patch's depth (module docstring), one per pixel.

    The plain per-pixel form of :func:`pixel_pairs` (one point per pixel, through
    :func:`resireg.mapping.unproject`): for checks and for small images; a 640 x 864 frame has
    552,960 points.

    Returns:
        ``points`` ``[B, H, W, 3]`` float32, ``valid`` ``[B, H, W]`` bool, and ``patch``
        ``[H, W]`` int64: the flat patch index ``i * w + j`` of every pixel.
    """
    b, hh, ww = depth.shape
    h, w = _check_hw("grid", grid)
    small = nearest_downsample(depth, (h, w))
    rows = nearest_indices(h, hh, depth.device)
    cols = nearest_indices(w, ww, depth.device)
    points, valid = unproject(small[:, rows[:, None], cols[None, :]], intrinsics, cam_to_world)
    return points, valid, rows[:, None] * w + cols[None, :]


def pixel_pairs(
    depth: Tensor,
    intrinsics: Tensor,
    cam_to_world: Tensor,
    grid: tuple[int, int],
    voxel_size: float,
    lattice: str = "round",
) -> tuple[Tensor, Tensor, Tensor]:
    """The (patch, voxel) pairs of the literal reading, with the number of pixels of each.

    For every lifted patch (module docstring) and every voxel that some of its pixels fall in:
    the voxel index, the patch, and how many of its pixels fall there. Equal to voxelising the
    points of :func:`pixel_points` one by one (``voxel_indices(points, voxel_size, lattice)``),
    except that the coordinates are not rounded to float32 first (a pixel within a float32
    rounding of a voxel face may land on the other side).

    How: without skew, ``K^-1 [u, v, 1] = (x_u, y_v, 1)`` with ``x_u = (u - cx) / fx``, ``y_v =
    (v - cy) / fy``, so world axis ``a`` of pixel ``(u, v)`` of patch ``p`` is ``z_p R_a0 x_u +
    (z_p (R_a1 y_v + R_a2) + t_a)``: a per-(patch, column) term plus a per-(patch, row) term. In
    voxel units the two small tables are summed per pixel and rounded (``round`` / ``floor``),
    then each pixel's voxel is coded relative to the patch's lowest voxel (whose index is the
    rounded sum of the two tables' minima: rounding is monotone, so no pixel is below it); one
    ``bincount`` over (patch, code) counts the pairs. Chunks of 8,192 patches bound the memory.

    Args:
        depth: ``[B, H, W]`` depth in metres.
        intrinsics: ``[3, 3]`` or ``[B, 3, 3]`` pinhole intrinsics of the ``H x W`` depth image
            (zero skew).
        cam_to_world: ``[B, 4, 4]`` poses.
        grid: ``(h, w)`` feature grid.
        voxel_size: voxel edge in metres.
        lattice: ``"round"`` or ``"floor"`` (:mod:`resireg.mapping.voxels`).

    Returns:
        ``index`` ``[M, 3]`` int64 voxel indices, ``patch`` ``[M]`` int64 flat patch indices
        ``b * h * w + i * w + j`` (rows of the frames' ``[B * h * w, D]`` features), and
        ``count`` ``[M]`` int64 pixels per pair; pairs ordered by patch, then voxel.
    """
    if not isinstance(depth, Tensor) or depth.ndim != 3 or not depth.is_floating_point():
        shape = tuple(depth.shape) if isinstance(depth, Tensor) else type(depth)
        raise ValueError(f"depth of shape {shape}: expected a floating [B, H, W] tensor (metres)")
    b, hh, ww = depth.shape
    h, w = _check_hw("grid", grid)
    voxel = _check_voxel_size(voxel_size)
    check_lattice(lattice)
    _check_intrinsics(intrinsics)
    if intrinsics.shape not in ((3, 3), (b, 3, 3)):
        raise ValueError(
            f"intrinsics of shape {tuple(intrinsics.shape)}: expected [3, 3] or [{b}, 3, 3]"
        )
    k = intrinsics.to(device=depth.device, dtype=torch.float64).expand(b, 3, 3)
    if bool((k[:, 0, 1] != 0).any()):
        raise ValueError("intrinsics with skew (K[0, 1] != 0): pixel_pairs assumes zero skew")
    if not isinstance(cam_to_world, Tensor) or cam_to_world.shape != (b, 4, 4):
        shape = tuple(cam_to_world.shape) if isinstance(cam_to_world, Tensor) else cam_to_world
        raise ValueError(f"cam_to_world of shape {shape}: expected a floating [{b}, 4, 4] tensor")
    dev, f64 = depth.device, torch.float64
    pose = cam_to_world.to(device=dev, dtype=f64)
    z = nearest_downsample(depth, (h, w)).to(f64)  # [B, h, w] patch depths
    lifted = torch.isfinite(z) & (z > 0) & torch.isfinite(pose).flatten(1).all(1)[:, None, None]
    frame, pi, pj = lifted.nonzero(as_tuple=True)  # the lifted patches
    row_px, row_mask = _patch_of_pixels(hh, h, dev)  # [h, mh]
    col_px, col_mask = _patch_of_pixels(ww, w, dev)  # [w, mw]
    padded = not (bool(row_mask.all()) and bool(col_mask.all()))
    x_u = (torch.arange(ww, device=dev, dtype=f64)[None] - k[:, 0, 2:3]) / k[:, 0, 0:1]  # [B, W]
    y_v = (torch.arange(hh, device=dev, dtype=f64)[None] - k[:, 1, 2:3]) / k[:, 1, 1:2]  # [B, H]
    out_index, out_patch, out_count = [], [], []
    for start in range(0, frame.numel(), _CHUNK_PATCHES):
        f = frame[start : start + _CHUNK_PATCHES]
        i, j = pi[start : start + _CHUNK_PATCHES], pj[start : start + _CHUNK_PATCHES]
        zp = z[f, i, j][:, None]  # [n, 1]
        xs = x_u[f[:, None], col_px[j]]  # [n, mw]
        ys = y_v[f[:, None], row_px[i]]  # [n, mh]
        n = f.numel()
        code = torch.zeros(n, row_px.shape[1], col_px.shape[1], dtype=f64, device=dev)
        low, span = [], []
        for a in range(3):
            rot = pose[f, a]  # [n, 4]: R_a0, R_a1, R_a2, t_a
            col_term = zp * rot[:, 0:1] * xs / voxel  # [n, mw]
            row_term = (zp * (rot[:, 1:2] * ys + rot[:, 2:3]) + rot[:, 3:4]) / voxel  # [n, mh]
            lo = lattice_index(row_term.amin(1) + col_term.amin(1), lattice)  # [n]
            hi = lattice_index(row_term.amax(1) + col_term.amax(1), lattice)
            cell = torch.add(row_term[:, :, None], col_term[:, None, :])  # [n, mh, mw]
            cell = cell.round_() if lattice == "round" else cell.floor_()
            cell.sub_(lo.to(f64)[:, None, None])  # offset in 0 .. hi - lo
            r = int((hi - lo).max()) + 1
            code.mul_(r).add_(cell)
            low.append(lo)
            span.append(r)
        cells = span[0] * span[1] * span[2]
        code = code.to(torch.int64)
        if padded:
            keep = row_mask[i][:, :, None] & col_mask[j][:, None, :]
            code = torch.where(keep, code, cells)  # a code past the last: dropped below
            stride = cells + 1
        else:
            stride = cells
        code += torch.arange(n, device=dev)[:, None, None] * stride
        counts = torch.bincount(code.reshape(-1), minlength=n * stride)
        pair = counts.nonzero().squeeze(1)
        local, owner = pair % stride, pair // stride
        if padded:
            real = local < cells
            pair, local, owner = pair[real], local[real], owner[real]
        oz = local % span[2]
        oy = (local // span[2]) % span[1]
        ox = local // (span[1] * span[2])
        index = torch.stack([low[0][owner] + ox, low[1][owner] + oy, low[2][owner] + oz], 1)
        out_index.append(index)
        out_patch.append((f * (h * w) + i * w + j)[owner])
        out_count.append(counts[pair])
    if not out_index:
        empty = torch.empty(0, dtype=torch.int64, device=dev)
        return empty.reshape(0, 3), empty, empty
    return torch.cat(out_index), torch.cat(out_patch), torch.cat(out_count)
