"""Camera geometry for 3D mapping: intrinsics scaling, depth downsampling, unprojection
(the lifting of feature grids that uses them: :mod:`resireg.mapping.lifting`).

Conventions (docs/maps.md#the-voxel-map):

- **Pixel centres at integers.** Pixel ``(u, v)`` (column ``u``, row ``v``) covers
  ``[u - 0.5, u + 0.5] x [v - 0.5, v + 0.5]`` and its centre is the point ``(u, v)``; the image of
  ``H x W`` pixels spans ``[-0.5, W - 0.5] x [-0.5, H - 0.5]``. This is the convention of ScanNet's
  (and OpenCV's) intrinsics: a pinhole ``K`` maps a camera point ``(x, y, z)`` to
  ``u = fx x / z + s y / z + cx``, ``v = fy y / z + cy``.
- **Resizing** an image from ``W`` to ``W'`` columns maps the continuous coordinate
  ``u + 0.5`` (distance from the left edge) to ``(u + 0.5) W' / W``, so
  ``fx' = fx W'/W``, ``s' = s W'/W``, ``cx' = (cx + 0.5) W'/W - 0.5`` (rows alike).
- **Camera frame**: OpenCV's (x right, y down, z forward); ``cam_to_world`` ``[4, 4]`` maps
  homogeneous camera points to world points (ScanNet's ``pose/*.txt``).
"""

from __future__ import annotations

import torch
from torch import Tensor

__all__ = [
    "check_hw",
    "check_intrinsics",
    "scale_intrinsics",
    "nearest_indices",
    "nearest_downsample",
    "unproject",
]


def check_hw(name: str, hw: tuple[int, int]) -> tuple[int, int]:
    """``(height, width)`` as two ints when ``hw`` holds two integers >= 1; else a ValueError
    naming ``name``."""
    try:
        h, w = (int(s) for s in hw)
        ok = len(tuple(hw)) == 2 and h >= 1 and w >= 1 and all(int(s) == s for s in hw)
    except (TypeError, ValueError):
        ok = False
    if not ok:
        raise ValueError(f"{name}={hw!r}: expected (height, width), two integers >= 1")
    return h, w


def check_intrinsics(intrinsics: Tensor, name: str = "intrinsics") -> None:
    """A ValueError naming ``name`` unless ``intrinsics`` is a floating ``[..., 3, 3]`` tensor."""
    if not isinstance(intrinsics, Tensor) or intrinsics.ndim < 2 or intrinsics.shape[-2:] != (3, 3):
        shape = tuple(intrinsics.shape) if isinstance(intrinsics, Tensor) else type(intrinsics)
        raise ValueError(f"{name} of shape {shape}: expected a [..., 3, 3] tensor")
    if not intrinsics.is_floating_point():
        raise ValueError(f"{name} of dtype {intrinsics.dtype}: expected a floating-point tensor")


def scale_intrinsics(
    intrinsics: Tensor, from_hw: tuple[int, int], to_hw: tuple[int, int]
) -> Tensor:
    """Intrinsics of the same camera after resampling its image from ``from_hw`` to ``to_hw``.

    With ``sx = W'/W`` and ``sy = H'/H`` the result is ``A K`` for
    ``A = [[sx, 0, (sx - 1)/2], [0, sy, (sy - 1)/2], [0, 0, 1]]``, i.e.
    ``fx' = fx sx``, ``s' = s sx``, ``cx' = (cx + 0.5) sx - 0.5`` and the same for ``y``
    (pixel centres at integer coordinates, module docstring): the resized image's pixel
    coordinate of every ray is its old coordinate mapped by the resize.

    Args:
        intrinsics: ``[..., 3, 3]`` pinhole matrices (last row ``[0, 0, 1]``) for images of
            ``from_hw``.
        from_hw: ``(H, W)`` of the image the intrinsics belong to.
        to_hw: ``(H', W')`` of the resampled image.

    Returns:
        ``[..., 3, 3]`` intrinsics for ``to_hw``, in the input's dtype and device.
    """
    check_intrinsics(intrinsics)
    h, w = check_hw("from_hw", from_hw)
    h2, w2 = check_hw("to_hw", to_hw)
    sx, sy = w2 / w, h2 / h
    scale = torch.tensor(
        [[sx, 0.0, (sx - 1) / 2], [0.0, sy, (sy - 1) / 2], [0.0, 0.0, 1.0]],
        dtype=torch.float64,
        device=intrinsics.device,
    )
    return (scale @ intrinsics.to(torch.float64)).to(intrinsics.dtype)


def nearest_indices(n_in: int, n_out: int, device: torch.device | str | None = None) -> Tensor:
    """Source indices of a nearest-exact resize of one axis from ``n_in`` to ``n_out`` samples.

    Output sample ``i`` covers ``[i, i + 1) n_in / n_out`` of the input axis; it takes the input
    pixel containing that interval's centre, ``floor((i + 0.5) n_in / n_out)``, computed in
    integers as ``((2 i + 1) n_in) // (2 n_out)`` (no float rounding at exact boundaries). For an
    integer factor ``f = n_in / n_out`` this is pixel ``f i + f // 2``: with ``f = 16`` pixel
    ``16 i + 8``, the one right of / below the patch centre ``16 i + 7.5``. This is the rule of
    ``torch.nn.functional.interpolate(mode="nearest-exact")``, which however evaluates it in
    floating point and can take the lower pixel when a centre lies exactly on a pixel edge
    (640 -> 54 columns: output column 40, centre 480.0, gets pixel 479 from torch, 480 here).

    Returns:
        ``[n_out]`` int64 indices in ``0 .. n_in - 1``.
    """
    i = torch.arange(n_out, dtype=torch.int64, device=device)
    return ((2 * i + 1) * n_in) // (2 * n_out)


def nearest_downsample(depth: Tensor, size: tuple[int, int]) -> Tensor:
    """Nearest-exact resize of the last two axes: ``[..., H, W] -> [..., h, w]``.

    Every output value is one input pixel (no mixing of depths across an edge): row
    ``((2 i + 1) H) // (2 h)``, column ``((2 j + 1) W) // (2 w)`` (:func:`nearest_indices`), the
    pixel containing the centre of output cell ``(i, j)``. Any dtype (depth, labels); works for
    upsampling too.

    Args:
        depth: ``[..., H, W]`` tensor (typically ``[B, H, W]`` depth in metres).
        size: ``(h, w)`` output size.

    Returns:
        ``[..., h, w]`` tensor of the input's dtype and device.
    """
    if not isinstance(depth, Tensor) or depth.ndim < 2:
        shape = tuple(depth.shape) if isinstance(depth, Tensor) else type(depth)
        raise ValueError(f"depth of shape {shape}: expected a [..., H, W] tensor")
    h, w = check_hw("size", size)
    rows = nearest_indices(depth.shape[-2], h, depth.device)
    cols = nearest_indices(depth.shape[-1], w, depth.device)
    return depth[..., rows[:, None], cols[None, :]]


def unproject(depth: Tensor, intrinsics: Tensor, cam_to_world: Tensor) -> tuple[Tensor, Tensor]:
    """World coordinates of every pixel of depth maps.

    Pixel ``(u, v)`` with depth ``z`` (distance along the optical axis, metres) is the camera
    point ``z K^-1 [u, v, 1]^T`` (without skew: ``x = (u - cx) z / fx``, ``y = (v - cy) z / fy``),
    then ``cam_to_world`` is applied. Computed in float64, returned in float32.

    Args:
        depth: ``[B, h, w]`` floating-point depth in metres (divide ScanNet's uint16 millimetres
            by 1000 first).
        intrinsics: ``[3, 3]`` or ``[B, 3, 3]`` pinhole matrices for this ``h x w`` grid.
        cam_to_world: ``[B, 4, 4]`` camera-to-world poses.

    Returns:
        ``points`` ``[B, h, w, 3]`` float32 world coordinates (NaN where invalid) and ``valid``
        ``[B, h, w]`` bool: depth finite and ``> 0`` and the frame's pose (all 16 entries)
        finite. ScanNet marks lost tracking with ``-inf`` poses; those frames are all invalid.
    """
    if not isinstance(depth, Tensor) or depth.ndim != 3:
        shape = tuple(depth.shape) if isinstance(depth, Tensor) else type(depth)
        raise ValueError(f"depth of shape {shape}: expected a [B, h, w] tensor")
    if not depth.is_floating_point():
        raise ValueError(
            f"depth of dtype {depth.dtype}: expected floating-point metres "
            "(convert integer millimetres with depth / 1000)"
        )
    b, h, w = depth.shape
    check_intrinsics(intrinsics)
    if intrinsics.shape not in ((3, 3), (b, 3, 3)):
        raise ValueError(
            f"intrinsics of shape {tuple(intrinsics.shape)}: expected [3, 3] or [{b}, 3, 3]"
        )
    if (
        not isinstance(cam_to_world, Tensor)
        or cam_to_world.shape != (b, 4, 4)
        or not cam_to_world.is_floating_point()
    ):
        shape = tuple(cam_to_world.shape) if isinstance(cam_to_world, Tensor) else cam_to_world
        raise ValueError(f"cam_to_world of shape {shape}: expected a floating [{b}, 4, 4] tensor")
    dev = depth.device
    f64 = torch.float64
    z = depth.to(f64)
    pose = cam_to_world.to(device=dev, dtype=f64)
    pose_ok = torch.isfinite(pose).flatten(1).all(1)  # [B]
    valid = torch.isfinite(z) & (z > 0) & pose_ok[:, None, None]
    k_inv = torch.linalg.inv(intrinsics.to(device=dev, dtype=f64)).expand(b, 3, 3)
    v, u = torch.meshgrid(
        torch.arange(h, dtype=f64, device=dev),
        torch.arange(w, dtype=f64, device=dev),
        indexing="ij",
    )
    pix = torch.stack([u, v, torch.ones_like(u)], dim=-1).reshape(1, h * w, 3)  # [1, hw, 3]
    rays = pix @ k_inv.transpose(1, 2)  # [B, hw, 3], z component 1
    cam = rays * torch.where(valid, z, torch.nan).reshape(b, h * w, 1)
    # Rotation and translation only; a finite pose never spreads NaN to valid points.
    world = cam @ pose[:, :3, :3].transpose(1, 2) + pose[:, None, :3, 3]
    return world.reshape(b, h, w, 3).to(torch.float32), valid
