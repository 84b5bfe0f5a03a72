"""A language-queryable 3D map a robot feeds with posed RGB-D windows (docs/method.md#robot-maps-semanticmap).

:class:`SemanticMap` holds one dense encoder, one ReSiReg configuration (``bb``, ``lite``,
``full``, ``full@n_prototypes:24``, ``lite+prior``...) and one sparse :class:`VoxelMap` of
running feature sums. :meth:`SemanticMap.add` encodes a window of consecutive frames in one
encoder pass, applies the configuration to the window (ReSiReg Full takes the window as one
scene: its prototypes are shared by the window's frames, as in the 3D task), lifts the features
to 3D (:func:`patch_points` or :func:`pixel_pairs`) and fuses them. :meth:`SemanticMap.fuse` is
the lift-and-fuse step alone, for features computed elsewhere: the 3D task's engine
(``resireg_train.evaluation.mapping.engine``) encodes a batch once, applies every configuration to it and
fuses each into its own ``SemanticMap``, so the benchmark and a robot run the same code.

Queries: :meth:`~SemanticMap.query` (cosine similarity of every voxel to text queries),
:meth:`~SemanticMap.classify` (the protocol's class prototypes: 80 templates averaged, cosine
argmax or RayFronts' thresholded rule). Persistence: :meth:`~SemanticMap.save` /
:meth:`SemanticMap.load` (safetensors + JSON, atomic: a crash mid-save leaves the previous save
loadable; the JSON records the tensor file's SHA-256 and its own digest, verified on load),
:meth:`~SemanticMap.to_ply`. :meth:`~SemanticMap.fuse` refuses non-finite or non-floating
features, intrinsics and poses (:func:`resireg.method.checks.check_features`).

Memory bound: the map holds, per occupied voxel, ``s D + 8`` bytes of accumulators (``s`` = 8
for float64 sums, 4 for ``sum_dtype="float32"``), 16 bytes of key and row, and, with
``colour=True``, ``8 x 3 + 8 + 16`` bytes of mean colour; the accumulators keep up to 1.5x
their rows in reserve (:attr:`SemanticMap.nbytes` counts it). ``max_voxels`` caps the occupied
voxels: a window that would exceed it raises :class:`MapFullError` *before* anything of it is
added, so the map stays as it was and can be saved. At 5 cm and D = 512 one million voxels
(a large building floor) take ~4.1 GB with float64 sums and ~2.1 GB with float32 ones.
"""

from __future__ import annotations

import hashlib
import json
import uuid
from collections.abc import Callable, Mapping, Sequence
from pathlib import Path
from typing import Any

import numpy as np
import torch
import torch.nn.functional as F
from torch import Tensor, nn

from resireg.errors import MapError
from resireg.integrity import (
    IntegrityError,
    atomic_write,
    digests,
    load_safetensors,
    read_json,
    verify_digests,
)
from resireg.mapping.geometry import patch_points
from resireg.mapping.lifting import pixel_pairs
from resireg.mapping.query import classify as classify_features
from resireg.mapping.voxels import SUM_DTYPES, VoxelMap, check_lattice, voxel_indices
from resireg.method.checks import check_features
from resireg.method.variants import apply_variant, build_variants
from resireg.specs.mapping import POINTS
from resireg.specs.variants import takes_prior, variant_layer

__all__ = [
    "COLOUR_BY",
    "ENCODER_OUTPUT",
    "POINTS",
    "MapFullError",
    "SemanticMap",
    "pca_colours",
    "write_ply",
]

#: What :meth:`SemanticMap.to_ply` colours the voxels by.
COLOUR_BY = ("rgb", "pca", "query", "class")
#: The files of a saved map: the JSON (written last: the commit point) names its tensor file.
MAP_JSON = "map.json"
_FORMAT = "resireg.semantic_map/1"
#: The name :meth:`SemanticMap.add` gives its encoder's output in a
#: :class:`resireg.method.checks.NonFiniteError` (``resireg-map`` skips such a window and counts it).
ENCODER_OUTPUT = "encoder output"


class MapFullError(MapError):
    """A window would take the map past its ``max_voxels`` budget (nothing of it was added)."""


def _record_digest(record: Mapping[str, Any]) -> str:
    """SHA-256 of a map record's canonical JSON without its ``record_sha256`` field: an edit of
    ``map.json`` (a ``voxel_size``, a count) no longer matches the digest written with it."""
    body = {k: v for k, v in record.items() if k != "record_sha256"}
    return hashlib.sha256(json.dumps(body, sort_keys=True).encode()).hexdigest()


def pca_colours(features: Tensor, sample: int = 100_000, seed: int = 0) -> Tensor:
    """``[M, D]`` features -> ``[M, 3]`` uint8 colours: their first three principal components
    (the top eigenvectors of the float64 covariance of up to ``sample`` rows, ``torch.linalg.eigh``:
    exact and deterministic, ``D x D`` whatever ``M``), each scaled from its 1st..99th percentile
    to 0..255. Each component's sign is fixed so its largest loading is positive."""
    x = features.float()
    if x.shape[0] == 0:
        return torch.zeros(0, 3, dtype=torch.uint8)
    g = torch.Generator().manual_seed(seed)
    rows = torch.randperm(x.shape[0], generator=g)[:sample] if x.shape[0] > sample else None
    fit = x if rows is None else x[rows.to(x.device)]
    mean = fit.double().mean(0, keepdim=True)
    q = min(3, *fit.shape)
    centred = fit.double() - mean
    _, vectors = torch.linalg.eigh(centred.T @ centred)  # ascending eigenvalues
    v = vectors[:, -q:].flip(1)
    v = v * torch.sign(v.gather(0, v.abs().argmax(0, keepdim=True)))
    proj = ((x.double() - mean) @ v).float()  # [M, q]
    lo = torch.quantile(proj[:sample], 0.01, dim=0)
    hi = torch.quantile(proj[:sample], 0.99, dim=0)
    unit = ((proj - lo) / (hi - lo).clamp_min(1e-12)).clamp(0, 1)
    out = torch.zeros(x.shape[0], 3)
    out[:, :q] = unit.cpu()
    return (out * 255).round().to(torch.uint8)


def diverging_ramp(values: Tensor) -> Tensor:
    """``[M]`` values -> ``[M, 3]`` uint8 from blue (lowest) through white to red (highest), the
    values scaled min..max (a diverging ramp; no matplotlib in ``resireg``)."""
    v = values.float().cpu()
    if v.numel() == 0:
        return torch.zeros(0, 3, dtype=torch.uint8)
    t = (v - v.min()) / (v.max() - v.min()).clamp_min(1e-12)
    up, down = (2 * t).clamp(0, 1), (2 - 2 * t).clamp(0, 1)
    return (torch.stack([up, torch.minimum(up, down), down], 1) * 255).round().to(torch.uint8)


def _palette(labels: Tensor) -> Tensor:
    """``[M]`` class ids -> ``[M, 3]`` uint8, a fixed distinct colour per id (golden-ratio hues)."""
    ids = labels.long().cpu().clamp_min(0).double()
    h = (ids * 0.618033988749895) % 1.0
    i = torch.floor(h * 6)
    f = h * 6 - i
    s, v = 0.75, 0.95
    p, q, t = torch.full_like(h, v * (1 - s)), v * (1 - s * f), v * (1 - s * (1 - f))
    vv = torch.full_like(h, v)
    table = [(vv, t, p), (q, vv, p), (p, vv, t), (p, q, vv), (t, p, vv), (vv, p, q)]
    out = torch.zeros(h.shape[0], 3, dtype=torch.float64)
    for k, (r, g, b) in enumerate(table):
        m = i == k
        out[m] = torch.stack([r[m], g[m], b[m]], 1)
    return (out * 255).round().to(torch.uint8)


def write_ply(path: str | Path, points: Tensor, colours: Tensor) -> Path:
    """A binary little-endian PLY of ``[M, 3]`` float32 points with ``[M, 3]`` uint8 colours.

    Written by hand (a 6-line header and one numpy record array): the format is fixed and
    small, and no PLY writer is a core dependency (open3d is a test-only reference)."""
    path = Path(path)
    pts = points.detach().cpu().numpy().astype("<f4")
    rgb = colours.detach().cpu().numpy().astype(np.uint8)
    rec = np.empty(pts.shape[0], dtype=[("x", "<f4"), ("y", "<f4"), ("z", "<f4"),
                                        ("red", "u1"), ("green", "u1"), ("blue", "u1")])  # fmt: skip
    for i, name in enumerate("xyz"):
        rec[name] = pts[:, i]
    for i, name in enumerate(("red", "green", "blue")):
        rec[name] = rgb[:, i]
    header = (
        "ply\nformat binary_little_endian 1.0\n"
        f"element vertex {pts.shape[0]}\n"
        "property float x\nproperty float y\nproperty float z\n"
        "property uchar red\nproperty uchar green\nproperty uchar blue\nend_header\n"
    )

    def write(tmp: Path) -> None:
        with open(tmp, "wb") as f:
            f.write(header.encode("ascii"))
            f.write(rec.tobytes())

    path.parent.mkdir(parents=True, exist_ok=True)
    atomic_write(path, write)
    return path


@torch.no_grad()
def _encoder_dim(encoder: Any) -> int | None:
    """The dimension of ``encoder``'s dense text queries (that of the features it fuses), or
    ``None`` for an encoder without a text path."""
    try:
        return int(encoder.dense_text(encoder.text_features(["a"])).shape[-1])
    except NotImplementedError:
        return None


class SemanticMap:
    """A voxel map of one encoder's features under one ReSiReg configuration (module docstring).

    Args:
        encoder: a :class:`~resireg.models.DenseEncoder` (only :meth:`fuse` works without one).
        configuration: a configuration name (``"bb"``, ``"full"``, ``"full@n_prototypes:24"``,
            ``"full+prior"``) built by :func:`resireg.method.variants.build_variants` with ``params``,
            or a variant module (``prior_input`` then says whether it takes the prior).
        voxel_size: voxel edge in metres.
        params: per-variant keyword arguments (``{"full": {"n_prototypes": 36}}``; the
            ``conf/resireg/default.yaml`` keys).
        prior: a segmentation-prior provider (:class:`resireg.priors.SamPrior`) for a ``+prior``
            configuration: called on each window's resized images (float ``[B, 3, H, W]``).
        points: :data:`POINTS`.
        lattice: ``"round"`` or ``"floor"`` (:mod:`resireg.mapping.voxels`).
        sum_dtype: ``"float64"`` or ``"float32"``: the feature sums (module docstring).
        max_voxels: ``None`` (no bound) or the most voxels the map may hold.
        short_side: the encoder's input rule on the images (``None``: keep the size, sides
            rounded to the patch size).
        colour: also keep each voxel's mean colour (for ``to_ply(colour_by="rgb")``, Rerun).
        device: where the map lives (default: the encoder's device, else the CPU).
    """

    def __init__(
        self,
        encoder: Any,
        configuration: str | nn.Module,
        voxel_size: float,
        *,
        params: Mapping[str, Mapping[str, Any] | None] | None = None,
        prior: Callable[[Tensor], Tensor] | None = None,
        prior_input: bool = False,
        points: str = "patch",
        lattice: str = "round",
        sum_dtype: str = "float64",
        max_voxels: int | None = None,
        short_side: int | None = None,
        colour: bool = True,
        device: torch.device | str | None = None,
    ) -> None:
        if points not in POINTS:
            raise ValueError(f"points={points!r}: expected one of {POINTS}")
        if sum_dtype not in SUM_DTYPES:
            raise ValueError(f"sum_dtype={sum_dtype!r}: expected one of {sorted(SUM_DTYPES)}")
        if max_voxels is not None and (
            isinstance(max_voxels, bool) or not isinstance(max_voxels, int) or max_voxels < 1
        ):
            raise ValueError(f"max_voxels={max_voxels!r}: expected null or an integer >= 1")
        self.encoder = encoder
        if isinstance(configuration, nn.Module):
            self.configuration = type(configuration).__name__
            self.variant = configuration
            self.takes_prior = bool(prior_input)
        else:
            name = str(configuration)
            if variant_layer(name) is not None:
                raise ValueError(
                    f"configuration={name!r}: @layer: is an evaluation sweep setting; a map "
                    "runs on the encoder's own intermediates"
                )
            self.configuration = name
            self.variant = build_variants([name], params or {})[name]
            self.takes_prior = takes_prior(name)
        if (
            self.takes_prior
            and prior is None
            and encoder is not None
            and not isinstance(configuration, nn.Module)
        ):
            raise ValueError(f"configuration={self.configuration!r} takes a prior: pass prior=")
        self.prior = prior
        self.params = {k: dict(v or {}) for k, v in (params or {}).items()}
        self.voxel_size = float(voxel_size)
        self.lattice = check_lattice(lattice)
        self.points = points
        self.sum_dtype = sum_dtype
        self.max_voxels = max_voxels
        self.short_side = short_side
        if device is None:
            device = encoder.device if encoder is not None else "cpu"
        self.device = torch.device(device)
        self.voxels: VoxelMap | None = None  # made at the first fuse (the dimension is known)
        self.colours = VoxelMap(self.voxel_size, 3, self.device, self.lattice) if colour else None
        VoxelMap(self.voxel_size, 1, self.device, self.lattice)  # checks voxel_size now
        self.frames = 0  # frames fused
        self.windows = 0  # add / fuse calls that fused frames
        self.meta: dict[str, Any] = {}  # the caller's record, saved with the map (e.g. the source)

    def __len__(self) -> int:
        """Occupied voxels."""
        return 0 if self.voxels is None else len(self.voxels)

    def __repr__(self) -> str:
        return (
            f"SemanticMap(configuration={self.configuration!r}, voxel_size={self.voxel_size}, "
            f"points={self.points!r}, voxels={len(self)}, frames={self.frames})"
        )

    # ------------------------------------------------------------------ building
    @property
    def dim(self) -> int | None:
        """The feature dimension (``None`` before the first window)."""
        return None if self.voxels is None else self.voxels.dim

    @property
    def nbytes(self) -> int:
        """Bytes held by the map's tensors (reserve included)."""
        return sum(m.nbytes for m in (self.voxels, self.colours) if m is not None)

    def bytes_per_voxel(self, dim: int | None = None) -> int:
        """Bytes per occupied voxel without the reserve (module docstring)."""
        d = dim or self.dim or 0
        size = 16 + 8 + d * SUM_DTYPES[self.sum_dtype].itemsize
        return size + (16 + 8 + 3 * 8 if self.colours is not None else 0)

    @torch.no_grad()
    def encode(self, images: Tensor) -> Tensor:
        """Dense features ``[B, D, h, w]`` of a window of RGB images ``[B, 3, H, W]`` (uint8, or
        float in [0, 1]): the encoder's input rule, one encoder pass, the configuration applied
        to the window (with the prior if it takes one). Every module in eval mode for the pass
        (each module's mode restored), autocast off."""
        return self._encode_resized(self.resized(images))

    @torch.no_grad()
    def _encode_resized(self, raw: Tensor) -> Tensor:
        """:meth:`encode` of images already resized by :meth:`resized`."""
        if self.takes_prior and self.prior is None:
            raise ValueError(f"configuration={self.configuration!r} takes a prior: pass prior=")
        x = self.encoder.input_rule.normalize(raw)
        modes = {m: m.training for m in self.encoder.modules()}
        self.encoder.eval()
        try:
            with torch.autocast(self.device.type, enabled=False):
                out = self.encoder.encode(x)
                seg = None
                if self.takes_prior:
                    seg = self.prior(raw).to(out.intermediates.device)
                dense = apply_variant(self.variant, out.intermediates, out.language, seg)
        finally:
            for module, mode in modes.items():
                module.training = mode
        return dense

    def resized(self, images: Tensor) -> Tensor:
        """RGB ``[B, 3, H, W]`` -> float ``[B, 3, H', W']`` in [0, 1] by the encoder's input rule."""
        if not isinstance(images, Tensor) or images.ndim != 4 or images.shape[1] != 3:
            shape = tuple(images.shape) if isinstance(images, Tensor) else type(images)
            raise ValueError(f"images of shape {shape}: expected an RGB [B, 3, H, W] tensor")
        if self.encoder is None:
            raise ValueError("this map has no encoder: pass features to fuse() instead")
        rule = self.encoder.input_rule
        return torch.stack([rule.resize(im, self.short_side) for im in images]).to(
            self.encoder.device
        )

    @torch.no_grad()
    def add(self, images: Tensor, depth: Tensor, intrinsics: Tensor, cam_to_world: Tensor) -> int:
        """Encode a window of consecutive frames and fuse it; returns the voxels it added.

        Args:
            images: ``[B, 3, H, W]`` RGB, uint8 or float in [0, 1] (any size: the encoder's
                input rule resizes it; it must show the depth image's field of view).
            depth: ``[B, Hd, Wd]`` depth in metres (0 or non-finite: no depth).
            intrinsics: ``[3, 3]`` or ``[B, 3, 3]`` pinhole intrinsics of the depth image.
            cam_to_world: ``[B, 4, 4]`` camera (OpenCV axes) to world poses.

        Raises :class:`resireg.method.checks.NonFiniteError` naming :data:`ENCODER_OUTPUT` when the
        encoder's features of the window are not finite (nothing is added).
        """
        if depth.ndim != 3 or depth.shape[0] != images.shape[0]:
            raise ValueError(
                f"depth of shape {tuple(depth.shape)}: expected [{images.shape[0]}, H, W], one "
                f"per image of {tuple(images.shape)}"
            )
        raw = self.resized(images)
        dense = self._encode_resized(raw)
        return self._fuse(dense, depth, intrinsics, cam_to_world,
                          raw if self.colours is not None else None, None, ENCODER_OUTPUT)  # fmt: skip

    @torch.no_grad()
    def fuse(
        self,
        features: Tensor,
        depth: Tensor,
        intrinsics: Tensor,
        cam_to_world: Tensor,
        colour: Tensor | None = None,
        lifted: dict | None = None,
    ) -> int:
        """Lift dense features ``[B, D, h, w]`` to 3D and add them; returns the voxels added.

        ``depth``, ``intrinsics``, ``cam_to_world`` as :meth:`add`. ``colour``: optional
        ``[B, 3, H', W']`` RGB in [0, 1] of the same view, area-averaged to the feature grid for
        the mean colour. ``lifted``: a dict shared by maps fed the same frames, which then lift
        each feature grid once (the 3D task's engine). Runs with autocast off (fp32 / fp64).
        Raises :class:`MapFullError` (adding nothing) when the window would take the map past
        ``max_voxels``."""
        return self._fuse(features, depth, intrinsics, cam_to_world, colour, lifted, "features")

    def _fuse(self, features, depth, intrinsics, cam_to_world, colour, lifted, name) -> int:
        """:meth:`fuse`, its features checked under ``name`` (:meth:`add`: the encoder output,
        checked once)."""
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
        with torch.autocast(self.device.type, enabled=False):
            grid = tuple(features.shape[-2:])
            depth = depth.to(self.device)
            pose = cam_to_world.to(self.device)
            k = intrinsics.to(self.device)
            cache = {} if lifted is None else lifted
            if grid not in cache:
                if self.points == "patch":
                    cache[grid] = ("patch", *patch_points(depth, k, pose, grid))
                else:
                    cache[grid] = ("pixel", *pixel_pairs(depth, k, pose, grid, self.voxel_size,
                                                          self.lattice))  # fmt: skip
            kind, *geometry = cache[grid]
            feats = features.permute(0, 2, 3, 1).float().to(self.device)
            if self.voxels is None:
                self.voxels = VoxelMap(self.voxel_size, feats.shape[-1], self.device,
                                       self.lattice, SUM_DTYPES[self.sum_dtype])  # fmt: skip
            vmap = self.voxels
            if kind == "patch":
                pts, valid = geometry
                index = None
                pts = pts[valid]
            else:
                index, patch, count = geometry
            before = len(vmap)
            if self.max_voxels is not None:
                probe = index if index is not None else voxel_indices(pts, self.voxel_size,
                                                                      self.lattice)  # fmt: skip
                new = vmap.count_new(probe)
                if before + new > self.max_voxels:
                    raise MapFullError(
                        f"max_voxels={self.max_voxels}: this window of {features.shape[0]} "
                        f"frames adds {new} voxels to the map's {before}; raise max_voxels "
                        f"(each voxel holds ~{self.bytes_per_voxel(feats.shape[-1])} bytes), "
                        "use a coarser voxel_size or sum_dtype=float32, or save this map and "
                        "start a new one"
                    )
            rgb = None
            if self.colours is not None and colour is not None:
                rgb = F.adaptive_avg_pool2d(colour.float().to(self.device), grid)
                rgb = rgb.permute(0, 2, 3, 1)
            if kind == "patch":
                vmap.add(pts, feats[valid])
                if rgb is not None:
                    self.colours.add(pts, rgb[valid])
            else:
                vmap.add_pairs(index, count, feats.reshape(-1, feats.shape[-1]), patch)
                if rgb is not None:
                    self.colours.add_pairs(index, count, rgb.reshape(-1, 3), patch)
        self.frames += int(features.shape[0])
        self.windows += 1
        return len(vmap) - before

    # ------------------------------------------------------------------ reading
    @property
    def indices(self) -> Tensor:
        """``[M, 3]`` int64 voxel indices in lexicographic order."""
        if self.voxels is None:
            return torch.empty(0, 3, dtype=torch.int64, device=self.device)
        return self.voxels.indices

    def centres(self) -> Tensor:
        """``[M, 3]`` float32 voxel centres, in :attr:`indices` order."""
        if self.voxels is None:
            return torch.empty(0, 3, device=self.device)
        return self.voxels.centres()

    def features(self) -> tuple[Tensor, Tensor]:
        """Voxel centres ``[M, 3]`` and unit mean features ``[M, D]`` (:meth:`VoxelMap.features`)."""
        if self.voxels is None:
            raise ValueError("the map is empty: add frames first")
        return self.voxels.features()

    def mean_colours(self) -> Tensor:
        """``[M, 3]`` uint8 mean colour per voxel, in :attr:`indices` order."""
        if self.colours is None:
            raise ValueError("this map keeps no colour (colour=False)")
        if self.voxels is None or not len(self.colours):
            return torch.zeros(len(self), 3, dtype=torch.uint8)
        at = self.colours.find(self.indices)
        mean = self.colours.means().float()
        out = torch.zeros(len(self), 3, device=mean.device)
        out[at >= 0] = mean[at[at >= 0]]
        return (out.clamp(0, 1) * 255).round().to(torch.uint8).cpu()

    @torch.no_grad()
    def text_queries(self, texts: Sequence[str]) -> Tensor:
        """``[K, D]`` unit-norm queries of the raw texts (the encoder's text path, no template)."""
        if self.encoder is None:
            raise ValueError("this map has no encoder to embed text: pass one to load()")
        feats = self.encoder.text_features(list(texts))
        return F.normalize(self.encoder.dense_text(feats).float(), dim=-1)

    @torch.no_grad()
    def prototypes(
        self, classes: Sequence[str], templates: Sequence[Callable[[str], str]] | None = None
    ) -> Tensor:
        """``[K, D]`` class prototypes as the protocol builds them: every template (default:
        the 80 OpenAI ImageNet templates) per class through ``text_features`` then
        ``dense_text``, averaged (:func:`resireg.ovss.text_prototypes`)."""
        from resireg.ovss import TEMPLATES, text_prototypes

        if self.encoder is None:
            raise ValueError("this map has no encoder to embed text: pass one to load()")
        enc = self.encoder

        def embed(texts: list[str]) -> Tensor:
            return enc.dense_text(enc.text_features(texts))

        with torch.autocast(self.device.type, enabled=False):
            return text_prototypes(embed, list(classes), templates or TEMPLATES)

    @torch.no_grad()
    def query(self, texts: str | Sequence[str]) -> Tensor:
        """Cosine similarity of every voxel's feature to text queries: ``[M, K]`` float32 for a
        list of ``K`` texts, ``[M]`` for one string; rows in :attr:`indices` order."""
        single = isinstance(texts, str)
        queries = self.text_queries([texts] if single else list(texts))
        _, feats = self.features()
        sim = feats @ queries.to(feats.device).T
        return sim[:, 0] if single else sim

    @torch.no_grad()
    def classify(
        self,
        classes: Sequence[str],
        threshold: float | None = None,
        denoise: float | None = None,
        templates: Sequence[Callable[[str], str]] | None = None,
    ) -> Tensor:
        """``[M]`` class id per voxel (``-1``: no prediction under ``threshold``) against
        :meth:`prototypes`: :func:`resireg.mapping.classify` (the 3D task's rule)."""
        protos = self.prototypes(classes, templates)
        _, feats = self.features()
        return classify_features(feats, protos.to(feats.device), threshold, denoise, none=-1)

    # ------------------------------------------------------------------ files
    def settings(self) -> dict[str, Any]:
        """What :meth:`load` needs to rebuild the map (its JSON's ``settings``)."""
        return {
            "configuration": self.configuration,
            "params": self.params,
            "voxel_size": self.voxel_size,
            "points": self.points,
            "lattice": self.lattice,
            "sum_dtype": self.sum_dtype,
            "max_voxels": self.max_voxels,
            "short_side": self.short_side,
            "colour": self.colours is not None,
        }

    def save(self, folder: str | Path) -> Path:
        """Write the map to ``folder`` (created): ``map-<id>.safetensors`` (every accumulator in
        :attr:`indices` order) and then ``map.json`` (settings, counts, ``meta``, the name and
        SHA-256 of that tensor file, and ``record_sha256``, the digest of the record itself),
        each through :func:`resireg.integrity.atomic_write` (a temporary file, fsync, the
        umask's mode, ``os.replace``). ``map.json`` is the commit point: a crash before it
        leaves the previous save in force; older tensor files are removed after it, and a save
        that fails (a full disk) removes its own new tensor file and raises an ``OSError``
        naming the file it could not write. Returns ``folder``."""
        from safetensors.torch import save_file

        folder = Path(folder)
        folder.mkdir(parents=True, exist_ok=True)
        tensors: dict[str, Tensor] = {}
        for prefix, vmap in (("features", self.voxels), ("colour", self.colours)):
            if vmap is not None:
                for name, value in vmap.state().items():
                    tensors[f"{prefix}.{name}"] = value.contiguous()
        name = f"map-{uuid.uuid4().hex[:12]}.safetensors"
        try:
            atomic_write(folder / name, lambda tmp: save_file(tensors, str(tmp)))
            record = {
                "format": _FORMAT,
                "tensors": name,
                "sha256": digests(folder, [name]),
                "settings": self.settings(),
                "dim": self.dim,
                "voxels": len(self),
                "frames": self.frames,
                "windows": self.windows,
                "meta": self.meta,
            }
            record["record_sha256"] = _record_digest(record)
            text = json.dumps(record, indent=2, sort_keys=True)
            atomic_write(folder / MAP_JSON, lambda tmp: tmp.write_text(text))
        except BaseException:
            (folder / name).unlink(missing_ok=True)  # not committed: map.json names the old one
            raise
        for old in folder.glob("map-*.safetensors"):
            if old.name != name:
                old.unlink(missing_ok=True)
        return folder

    @classmethod
    def load(
        cls,
        folder: str | Path,
        encoder: Any = None,
        prior: Callable[[Tensor], Tensor] | None = None,
        device: torch.device | str | None = None,
        **overrides: Any,
    ) -> SemanticMap:
        """A map saved by :meth:`save`, with ``encoder`` for queries and further windows.

        Before any tensor is read, ``map.json``'s own digest and its tensor file's SHA-256 are
        verified: a truncated, edited or damaged file is an
        :class:`~resireg.integrity.IntegrityError` naming it. An ``encoder`` whose text
        features have another dimension than the map's is refused here, not at the first
        query (the weights themselves are the caller's to check: ``resireg-map`` records a
        digest of them in ``meta``). ``overrides`` replace saved settings that do not change
        the content (``max_voxels``)."""
        folder = Path(folder)
        path = folder / MAP_JSON
        if not path.is_file():
            raise FileNotFoundError(f"{folder}: no {MAP_JSON} (not a saved SemanticMap)")
        record = read_json(path, "saved map record")
        if not isinstance(record, dict) or record.get("format") != _FORMAT:
            found = record.get("format") if isinstance(record, dict) else type(record).__name__
            raise IntegrityError(f"{path}: format {found!r}, expected {_FORMAT!r}")
        if "record_sha256" not in record or "sha256" not in record:
            raise IntegrityError(
                f"{path}: no record_sha256 / sha256 (a map saved before maps recorded their "
                "digests, or an edited record): make the map again"
            )
        if record["record_sha256"] != _record_digest(record):
            raise IntegrityError(
                f"{path}: its content does not match the record_sha256 written with it (the "
                "file was edited or damaged; a map's settings cannot change after it is made)"
            )
        verify_digests(folder, record["sha256"], "saved map")
        settings = dict(record["settings"])
        bad = set(overrides) - {"max_voxels"}
        if bad:
            raise ValueError(f"load(): {sorted(bad)} cannot change on a saved map")
        settings.update(overrides)
        config = settings.pop("configuration")
        params = settings.pop("params")
        voxel_size = settings.pop("voxel_size")
        if encoder is not None and record["dim"] is not None:
            enc_dim = _encoder_dim(encoder)
            if enc_dim is not None and enc_dim != int(record["dim"]):
                raise ValueError(
                    f"{path}: the map holds {record['dim']}-d features, the encoder given to "
                    f"load() makes {enc_dim}-d ones (another model: load the map with the "
                    "encoder it was built with)"
                )
        smap = cls(encoder if encoder is not None else None, config, voxel_size, params=params,
                   prior=prior, device=device or (encoder.device if encoder is not None else "cpu"),
                   **settings)  # fmt: skip
        tensors = load_safetensors(folder / record["tensors"], "saved map")
        if record["dim"] is not None:
            smap.voxels = VoxelMap(smap.voxel_size, int(record["dim"]), smap.device,
                                   smap.lattice, SUM_DTYPES[smap.sum_dtype])  # fmt: skip
            smap.voxels.load_state({k.split(".", 1)[1]: v for k, v in tensors.items()
                                    if k.startswith("features.")})  # fmt: skip
        if smap.colours is not None:
            smap.colours.load_state({k.split(".", 1)[1]: v for k, v in tensors.items()
                                     if k.startswith("colour.")} or smap.colours.state())  # fmt: skip
        smap.frames, smap.windows = int(record["frames"]), int(record["windows"])
        smap.meta = dict(record.get("meta") or {})
        return smap

    def colours_by(
        self,
        colour_by: str = "pca",
        text: str | None = None,
        classes: Sequence[str] | None = None,
    ) -> Tensor:
        """``[M, 3]`` uint8 colour per voxel (:data:`COLOUR_BY`): ``rgb`` (mean colour),
        ``pca`` (:func:`pca_colours`), ``query`` (similarity to ``text``, blue..red) or
        ``class`` (the :meth:`classify` class of ``classes``, a fixed colour per class)."""
        if colour_by not in COLOUR_BY:
            raise ValueError(f"colour_by={colour_by!r}: expected one of {COLOUR_BY}")
        if colour_by == "rgb":
            return self.mean_colours()
        if colour_by == "pca":
            return pca_colours(self.features()[1])
        if colour_by == "query":
            if not text:
                raise ValueError("colour_by='query' needs text=")
            return diverging_ramp(self.query(text))
        if not classes:
            raise ValueError("colour_by='class' needs classes=")
        return _palette(self.classify(classes))

    def to_ply(
        self,
        path: str | Path,
        colour_by: str = "pca",
        text: str | None = None,
        classes: Sequence[str] | None = None,
    ) -> Path:
        """The voxel centres as a coloured point cloud (binary PLY; :meth:`colours_by`)."""
        return write_ply(path, self.centres(), self.colours_by(colour_by, text, classes))
