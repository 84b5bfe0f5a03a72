"""Feature lifting: a window's feature grid placed in 3D, in the two modes of ``points``.

The modes (:data:`~resireg.specs.mapping.POINTS`): ``patch`` (:func:`patch_points`, one point
per patch centre, OTAS's code) and ``pixel`` (:func:`pixel_pairs`, every pixel at its patch's
depth, below). :func:`lift_grid` computes either for a window's depth and poses (a
:class:`LiftedGrid`, shared by maps fed the same frames) and :meth:`LiftedGrid.with_features`
joins a window's features to it: a :class:`LiftedPoints`, what a map's storage adds
(:meth:`LiftedPoints.add_to`).

**The literal reading of the paper**: every pixel with its patch's feature. The paper's sentence: "patch centres are unprojected with the depth camera model; depth is
aggregated per patch by nearest downsampling to feature resolution and back to the depth grid".
OTAS's code (``src/model.py``, ``batch_embed_rgbd``), which the sentence describes, unprojects one
point per patch (:func:`resireg.mapping.patch_points` is that reading). Read literally, the
patch depth brought back to the depth grid puts *every* pixel of a patch on its own ray at the
patch's depth, all carrying the patch's feature (docs/maps.md#the-voxel-map):

- the depth ``[B, H, W]`` is nearest-downsampled to the feature grid ``(h, w)``
  (:func:`resireg.mapping.nearest_downsample`) and nearest-upsampled back (the same rule), so
  pixel ``(v, u)`` belongs to patch ``(rows[v], cols[u])`` with ``rows = nearest_indices(h, H)``;
- pixel ``(u, v)`` of patch ``p`` is the world point ``R (z_p K^-1 [u, v, 1]) + t``; a patch is
  lifted iff its depth ``z_p`` is finite and ``> 0`` and the frame's pose is finite.

Pixels of one patch share one feature, so the map needs only how many pixels of each patch fall
in each voxel: :func:`pixel_pairs` returns those (patch, voxel, count) triples, and
:meth:`resireg.mapping.VoxelMap.add_pairs` adds ``count * feature`` per pair. The feature work is
then proportional to the pairs (a small multiple of the patches), not to the ~550k pixels of a
640 x 864 frame; the per-pixel work is ten float64 operations per pixel (:func:`pixel_pairs`).
"""

from __future__ import annotations

from dataclasses import dataclass, replace
from typing import NamedTuple

import torch
from torch import Tensor

from resireg.mapping.geometry import (
    check_hw,
    check_intrinsics,
    nearest_downsample,
    nearest_indices,
    scale_intrinsics,
    unproject,
)
from resireg.mapping.keys import (
    MAX_INDEX,
    check_lattice,
    check_voxel_size,
    pack_keys,
    unpack_keys,
    voxel_indices,
)
from resireg.specs.mapping import POINTS

__all__ = [
    "LiftedGrid",
    "LiftedPoints",
    "lift_grid",
    "patch_points",
    "pixel_pairs",
    "pixel_points",
]

# Pixels per chunk in pixel_pairs: its two float64 per-pixel buffers (2 x 1 MB) are reused by
# the allocator from chunk to chunk; whole-frame buffers (2 x 4.4 MB at 640 x 864) were
# page-faulted afresh on every call, which cost more than the ~12 passes over them.
_CHUNK_PIXELS = 1 << 17
# Most bincount bins per chunk (the cells of its patches' voxel boxes; 32 MB of int64); a chunk
# of larger boxes (far patches or tiny voxels) is counted by sorting instead.
_MAX_BINS = 1 << 22
_TWO52 = 1 << 52
_TWO52_BITS = int(torch.tensor(float(_TWO52), dtype=torch.float64).view(torch.int64))


def _lattice_op(scaled: Tensor, lattice: str) -> Tensor:
    """``round`` (half to even) or ``floor`` of coordinates in voxel units, still float64 (the
    operations of :func:`resireg.mapping.keys.lattice_index`)."""
    return torch.round(scaled) if lattice == "round" else torch.floor(scaled)


def _pairs_by_sorting(
    tables: list[tuple[Tensor, Tensor]], lattice: str, keep: Tensor | None
) -> tuple[Tensor, Tensor, Tensor]:
    """The (voxel, patch, count) triples of a chunk of patches by sorting the pixels' keys.

    The fallback of :func:`pixel_pairs` for boxes too large to count with ``bincount``: the same
    per-pixel indices (the same sums of the same ``[n, mh]`` row and ``[n, mw]`` column tables,
    the same rounding), each pixel's packed key, then a sort by (patch, key), i.e. the same
    triples in the same order (by patch, then voxel), in memory linear in the pixels.

    Returns:
        ``index`` ``[M, 3]``, ``owner`` ``[M]`` (patch within the chunk), ``count`` ``[M]``.
    """
    axes = [_lattice_op(r[:, :, None] + c[:, None, :], lattice).to(torch.int64) for r, c in tables]
    owner = torch.arange(axes[0].shape[0], device=axes[0].device)[:, None, None]
    owner = owner.expand_as(axes[0]).reshape(-1)
    key = pack_keys(torch.stack([a.reshape(-1) for a in axes], 1))
    if keep is not None:
        kept = keep.expand_as(axes[0]).reshape(-1)
        key, owner = key[kept], owner[kept]
    key, order = torch.sort(key, stable=True)
    owner, order2 = torch.sort(owner[order], stable=True)  # by patch, then key
    key = key[order2]
    first = torch.ones_like(key, dtype=torch.bool)
    first[1:] = (key[1:] != key[:-1]) | (owner[1:] != owner[:-1])
    start = first.nonzero().squeeze(1)
    count = torch.diff(start, append=start.new_tensor([key.numel()]))
    return unpack_keys(key[start]), owner[start], count


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
    h, w = check_hw("grid", grid)
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
    voxel units the two small tables are summed per pixel and rounded (``round`` / ``floor``);
    each patch's voxels lie in a box from its lowest voxel (the rounded sum of the two tables'
    minima: rounding is monotone) to its highest, and a pixel's voxel is coded by its place in
    its patch's box, the boxes laid end to end; one ``bincount`` over the codes counts the pairs
    (a chunk whose boxes hold more than 2^22 cells, far patches at a small voxel size, is
    counted by sorting the pixels' keys instead: the same triples). Per pixel that is, per axis,
    one float64 addition, one rounding and one multiply-add of exact integers, in chunks of
    2^17 pixels laid out with the patches innermost (contiguous rows). Indices beyond
    ``VoxelMap``'s packable range (``|index| > 2^20 - 1``) raise a ``ValueError``.

    Args:
        depth: ``[B, H, W]`` depth in metres.
        intrinsics: ``[3, 3]`` or ``[B, 3, 3]`` pinhole intrinsics of the ``H x W`` depth image
            (zero skew).
        cam_to_world: ``[B, 4, 4]`` poses.
        grid: ``(h, w)`` feature grid.
        voxel_size: voxel edge in metres.
        lattice: ``"round"`` or ``"floor"`` (:mod:`resireg.mapping.keys`).

    Returns:
        ``index`` ``[M, 3]`` int64 voxel indices, ``patch`` ``[M]`` int64 flat patch indices
        ``b * h * w + i * w + j`` (rows of the frames' ``[B * h * w, D]`` features), and
        ``count`` ``[M]`` int64 pixels per pair; pairs ordered by patch, then voxel.
    """
    if not isinstance(depth, Tensor) or depth.ndim != 3 or not depth.is_floating_point():
        shape = tuple(depth.shape) if isinstance(depth, Tensor) else type(depth)
        raise ValueError(f"depth of shape {shape}: expected a floating [B, H, W] tensor (metres)")
    b, hh, ww = depth.shape
    h, w = check_hw("grid", grid)
    voxel = check_voxel_size(voxel_size)
    check_lattice(lattice)
    check_intrinsics(intrinsics)
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
    mh, mw = row_px.shape[1], col_px.shape[1]
    padded = not (bool(row_mask.all()) and bool(col_mask.all()))
    x_u = (torch.arange(ww, device=dev, dtype=f64)[None] - k[:, 0, 2:3]) / k[:, 0, 0:1]  # [B, W]
    y_v = (torch.arange(hh, device=dev, dtype=f64)[None] - k[:, 1, 2:3]) / k[:, 1, 1:2]  # [B, H]
    zp = z[frame, pi, pj]  # [n]
    # The pixels' x_u (y_v) of every (frame, patch column (row)), [mw, B * w] ([mh, B * h]), then
    # the lifted patches' columns of it: one index_select each (2-D advanced indexing of the
    # [B, W] table costs ~5x more).
    xs = x_u[:, col_px.T].permute(1, 0, 2).reshape(mw, b * w).index_select(1, frame * w + pj)
    ys = y_v[:, row_px.T].permute(1, 0, 2).reshape(mh, b * h).index_select(1, frame * h + pi)
    # Per axis the two tables in voxel units, laid out [3, m, n] (the patches innermost, so that
    # every per-patch and per-pixel operation below runs over contiguous rows of n values), and
    # each patch's lowest and highest voxel (the rounded sums of the tables' extremes: rounding
    # is monotone), all axes and patches at once.
    # [3, 4, n]: R_a0, R_a1, R_a2, t_a per axis a
    rot = pose[:, :3].reshape(b, 12).T.index_select(1, frame).view(3, 4, -1)
    cols_t = (zp * rot[:, 0])[:, None] * xs[None] / voxel  # [3, mw, n]
    rows_t = (zp * (rot[:, 1, None] * ys[None] + rot[:, 2, None]) + rot[:, 3, None]) / voxel
    lo = _lattice_op(rows_t.amin(1) + cols_t.amin(1), lattice)  # [3, n] float64
    hi = _lattice_op(rows_t.amax(1) + cols_t.amax(1), lattice)
    # Checked here, before any integer conversion: the codes below are exact only for indices
    # in the range that VoxelMap packs (its add_pairs would refuse the others anyway).
    extreme = float(torch.maximum(lo.abs(), hi.abs()).max()) if frame.numel() else 0.0
    if extreme > MAX_INDEX:
        raise ValueError(
            f"voxel indices up to {extreme:g} at voxel_size={voxel:g}: beyond +-{MAX_INDEX} "
            "(keys pack 21 bits per axis; a depth or a pose translation too large)"
        )
    low = lo.to(torch.int64)  # [3, n]
    span = (hi - lo).to(torch.int64) + 1  # [3, n]
    # Each patch's voxels are coded in its own box: code = base_p + (ix - lo_x) r_y r_z +
    # (iy - lo_y) r_z + (iz - lo_z), boxes laid end to end (base_p: the boxes before it), so the
    # bins of a chunk are exactly its boxes' cells, however their sizes vary. Chunks counted by
    # bincount are decoded together (a run of them, flushed before a sorted chunk and at the
    # end), so the decoding's ~20 operations run once per frame, not once per chunk.
    cells = span[0] * span[1] * span[2]  # [n]
    strides = torch.stack([span[1] * span[2], span[2]])  # [2, n] of ix, iy
    flat_patch = frame * (h * w) + pi * w + pj  # [n]
    out_index, out_patch, out_count = [], [], []
    run: list = []  # (codes, counts) of the pending bincount chunks
    run_start, run_bins = 0, 0

    def flush(end: int) -> None:
        if not run:
            return
        sl = slice(run_start, end)
        cell = cells[sl]
        base = torch.cumsum(cell, 0) - cell  # [n]: the run's boxes end to end
        code, count = torch.cat([c for c, _ in run]), torch.cat([c for _, c in run])
        owner = torch.searchsorted(base, code, right=True) - 1  # [M] patch in the run
        local = code - base[owner]
        s0, s1 = strides[0, sl][owner], strides[1, sl][owner]
        ix = low[0, sl][owner] + local // s0
        iy = low[1, sl][owner] + (local // s1) % span[1, sl][owner]
        iz = low[2, sl][owner] + local % s1
        out_index.append(torch.stack([ix, iy, iz], 1))
        out_patch.append(flat_patch[sl][owner])
        out_count.append(count)
        run.clear()

    n_px = mh * mw
    step = max(1, _CHUNK_PIXELS // n_px)
    for start in range(0, frame.numel(), step):
        sl = slice(start, start + step)
        n = frame[sl].numel()
        cell = cells[sl]
        bins = int(cell.sum())
        if bins > _MAX_BINS:  # far patches with huge boxes: count by sorting (bounded memory)
            flush(start)
            index, owner, count = _pairs_by_sorting(
                [(rows_t[a, :, sl].T, cols_t[a, :, sl].T) for a in range(3)], lattice,
                keep=None if not padded else
                row_mask[pi[sl]][:, :, None] & col_mask[pj[sl]][:, None, :],
            )  # fmt: skip
            out_index.append(index)
            out_patch.append(flat_patch[sl][owner])
            out_count.append(count)
            continue
        if not run:
            run_start, run_bins = start, 0
        base = torch.cumsum(cell, 0) - cell  # [n]
        s0, s1 = strides[0, sl].to(f64), strides[1, sl].to(f64)
        # The per-patch offset of the code (the box's place, less its lowest voxel's code), plus
        # 2^52 for the conversion below.
        ones = torch.ones_like(cell)[None]
        offset = base - (low[:, sl] * torch.cat([strides[:, sl], ones])).sum(0) + _TWO52
        # Pixel-major layout [mw, mh, n] (patch innermost): every per-pixel operation runs over
        # contiguous rows of n values (the [n, mh, mw] layout's 8- or 16-wide inner rows of a
        # broadcast addition cost ~3x more). Per pixel and axis: one addition of the two tables
        # (the same float64 sum as ever), one rounding, one multiply-add into the code (the
        # first onto the offset). Every intermediate is an integer below 2^53 in magnitude
        # (|index * stride| < 2^42), so exact in float64.
        code = torch.empty(mw, mh, n, dtype=f64, device=dev)
        buf = torch.empty_like(code)
        for a, stride in enumerate((s0, s1, None)):
            torch.add(rows_t[a, None, :, sl], cols_t[a, :, None, sl], out=buf)
            buf.round_() if lattice == "round" else buf.floor_()
            if a == 0:
                torch.addcmul(offset.to(f64), buf, stride, out=code)
            elif stride is not None:
                code.addcmul_(buf, stride)
            else:
                code.add_(buf)
        # To int64 without a conversion pass (by hand: .to(int64) costs ~6x an addition):
        # x + 2^52 for an integer 0 <= x < 2^52 is exact and its bits are those of 2^52 plus
        # x, so the bits viewed as int64, less 2^52's, are x.
        code = code.view(torch.int64).sub_(_TWO52_BITS)
        if padded:
            keep = row_mask[pi[sl]].T[None] & col_mask[pj[sl]].T[:, None]
            code = torch.where(keep, code, bins)  # a bin past the last: dropped below
        counts = torch.bincount(code.reshape(-1), minlength=bins + 1)[:bins]
        occupied = counts.nonzero().squeeze(1)  # in order
        run.append((occupied + run_bins, counts[occupied]))
        run_bins += bins
    flush(frame.numel())
    if not out_index:
        empty = torch.empty(0, dtype=torch.int64, device=dev)
        return empty.reshape(0, 3), empty, empty
    return torch.cat(out_index), torch.cat(out_patch), torch.cat(out_count)


@dataclass(frozen=True)
class LiftedPoints:
    """One window's features placed in 3D (:meth:`LiftedGrid.with_features`), as a map's
    storage adds them (:meth:`add_to`).

    ``patch`` mode: one world point per feature row (``points``). ``pixel`` mode: the
    (voxel, patch, count) pairs of :func:`pixel_pairs` over the grid's feature rows
    (``index``, ``patch``, ``count``); ``points`` is then ``None``, and the pairs are ``None``
    in ``patch`` mode."""

    mode: str  #: ``"patch"`` or ``"pixel"`` (:data:`~resireg.specs.mapping.POINTS`)
    features: Tensor  #: ``[N, D]`` float32 feature rows
    colours: Tensor | None  #: ``[N, 3]`` the mean colour of each row's patch, or ``None``
    points: Tensor | None = None  #: ``patch``: ``[N, 3]`` float32 world points, one per row
    index: Tensor | None = None  #: ``pixel``: ``[P, 3]`` int64 voxel index of each pair
    patch: Tensor | None = None  #: ``pixel``: ``[P]`` int64 feature row of each pair
    count: Tensor | None = None  #: ``pixel``: ``[P]`` int64 pixels of each pair

    def voxel_index(self, voxel_size: float, lattice: str) -> Tensor:
        """``[P, 3]`` int64 voxel indices the window touches (repeats kept)."""
        if self.points is None:
            return self.index
        return voxel_indices(self.points, voxel_size, lattice)

    def distinct_features(self) -> Tensor:
        """The window's feature rows, each lifted row once (a basis is fitted on them)."""
        if self.patch is None:
            return self.features
        return self.features[torch.unique(self.patch)]

    def projected(self, basis: Tensor | None) -> LiftedPoints:
        """The same points with their features projected by ``basis`` ``[D, k]`` (``None``:
        unchanged)."""
        return self if basis is None else replace(self, features=self.features @ basis)

    def add_to(self, target, values: Tensor, *more: Tensor | None) -> None:
        """Add ``values`` (``[N, C]``: the features, or the colours) to a sparse map:
        ``target.add(points, values, *more)`` (``patch``) or ``target.add_pairs(index, count,
        values, patch, *more)`` (``pixel``)."""
        if self.points is not None:
            target.add(self.points, values, *more)
        else:
            target.add_pairs(self.index, self.count, values, self.patch, *more)


class LiftedGrid(NamedTuple):
    """Where a window's feature grid lands (:func:`lift_grid`), before its features join it."""

    mode: str  #: ``"patch"`` or ``"pixel"``
    points: Tensor | None  #: ``patch``: ``[B, h, w, 3]`` float32 world points of the patch centres
    valid: Tensor | None  #: ``patch``: ``[B, h, w]`` bool, the points with a depth and a pose
    index: Tensor | None  #: ``pixel``: ``[P, 3]`` voxel index of each pair
    patch: Tensor | None  #: ``pixel``: ``[P]`` flat patch ``b h w + i w + j`` of each pair
    count: Tensor | None  #: ``pixel``: ``[P]`` pixels of each pair

    def with_features(self, features: Tensor, colours: Tensor | None) -> LiftedPoints:
        """The window's ``[B, h, w, D]`` features (and ``[B, h, w, 3]`` colours, or ``None``)
        placed on this grid's points."""
        if self.mode == "patch":
            valid = self.valid
            rgb = None if colours is None else colours[valid]
            return LiftedPoints("patch", features[valid], rgb, points=self.points[valid])
        rgb = None if colours is None else colours.reshape(-1, 3)
        return LiftedPoints("pixel", features.reshape(-1, features.shape[-1]), rgb,
                            index=self.index, patch=self.patch, count=self.count)  # fmt: skip


def lift_grid(
    mode: str,
    depth: Tensor,
    intrinsics: Tensor,
    cam_to_world: Tensor,
    grid: tuple[int, int],
    voxel_size: float,
    lattice: str = "round",
) -> LiftedGrid:
    """A window's feature grid ``(h, w)`` in 3D by ``mode`` (:data:`~resireg.specs.mapping.POINTS`):
    :func:`patch_points` or :func:`pixel_pairs` (``voxel_size`` and ``lattice``: the pairs'
    voxels)."""
    if mode not in POINTS:
        raise ValueError(f"points={mode!r}: expected one of {POINTS}")
    if mode == "patch":
        points, valid = patch_points(depth, intrinsics, cam_to_world, grid)
        return LiftedGrid("patch", points, valid, None, None, None)
    index, patch, count = pixel_pairs(depth, intrinsics, cam_to_world, grid, voxel_size, lattice)
    return LiftedGrid("pixel", None, None, index, patch, count)


def patch_points(
    depth: Tensor, intrinsics: Tensor, cam_to_world: Tensor, grid: tuple[int, int]
) -> tuple[Tensor, Tensor]:
    """World points of the patch centres of a feature grid, from full-resolution depth.

    The depth is nearest-downsampled to ``grid`` (:func:`nearest_downsample`: each patch takes
    the depth pixel containing its centre), the intrinsics are scaled from the depth image to
    the grid (:func:`scale_intrinsics`), and the grid is unprojected (:func:`unproject`). The
    depth image must show the same field of view as the image the features came from.

    Args:
        depth: ``[B, H, W]`` depth in metres.
        intrinsics: ``[3, 3]`` or ``[B, 3, 3]`` intrinsics of the ``H x W`` depth image.
        cam_to_world: ``[B, 4, 4]`` poses.
        grid: ``(h, w)`` feature grid.

    Returns:
        ``points`` ``[B, h, w, 3]`` float32 and ``valid`` ``[B, h, w]`` bool, as
        :func:`unproject`.
    """
    if not isinstance(depth, Tensor) or depth.ndim != 3:
        shape = tuple(depth.shape) if isinstance(depth, Tensor) else type(depth)
        raise ValueError(f"depth of shape {shape}: expected a [B, H, W] tensor")
    grid = check_hw("grid", grid)
    small = nearest_downsample(depth, grid)
    check_intrinsics(intrinsics)
    k = scale_intrinsics(intrinsics, tuple(depth.shape[-2:]), grid)
    return unproject(small, k, cam_to_world)
