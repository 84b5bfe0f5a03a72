"""A language-queryable 3D map a robot feeds with posed RGB-D windows (docs/method.md#robot-maps-semanticmap).

:class:`SemanticMap` holds one dense encoder, one ReSiReg variant (``bb``, ``lite``,
``full``, ``full@n_prototypes:24``, ``lite+prior``...) and one map storage. :meth:`SemanticMap.add`
encodes a window of consecutive frames in one encoder pass, applies the variant to the
window (ReSiReg Full takes the window as one scene: its prototypes are shared by the window's
frames, as in the 3D task), lifts the features to 3D (:mod:`resireg.mapping.lifting`: :func:`patch_points` or
:func:`pixel_pairs`) and fuses them. :meth:`SemanticMap.fuse` is the lift-and-fuse step alone,
for features computed elsewhere: the 3D task's engine (``resireg_train.evaluation.mapping.engine``) encodes
a batch once, applies every variant to it and fuses each into its own ``SemanticMap``, so
the benchmark and a robot run the same code.

Storage (``storage``, :data:`~resireg.specs.mapping.STORAGES`; :mod:`resireg.mapping.storage`: the map
asks its storage object and never branches on the kind): ``exact`` keeps running feature
sums (:class:`VoxelMap`, ``sum_dtype`` float64 or float32) and a mean colour map; ``compact``
keeps low-precision unit features, optionally projected to ``compact.dim`` channels by a basis
fitted once on the first ``compact.basis_rows`` features (an uncentred PCA, :mod:`resireg.mapping.basis`)
or given (``compact.basis``: a map or run folder, or a ``.safetensors`` file), recorded by its SHA-256
(:class:`~resireg.mapping.compact.CompactVoxelMap`: ~290 bytes per voxel at 128 channels,
against ~4,170 for float64 sums of 512). Until a compact map's basis is fitted its frames wait
(the map reads as empty); a save fits it on what it has.

Queries: :meth:`~SemanticMap.query` (cosine similarity of every voxel to text queries),
:meth:`~SemanticMap.top_k` (the best voxels of a text, exact: scored fast in low precision,
the candidates within the error bound re-scored in float64; optionally in a box or a ball,
looked up without reading the map), :meth:`~SemanticMap.region`,
:meth:`~SemanticMap.classify` (the protocol's class prototypes: 80 templates averaged, cosine
argmax or RayFronts' thresholded rule); text embeddings are cached per text, prototypes per class
list. A compact map with a basis scores in the basis's space (the texts projected and
normalised: RayFronts' compressed query). :meth:`~SemanticMap.merge` adds another mapping run's
map (the same encoder and settings; refused naming what differs), optionally through a rigid
transform. Persistence: :meth:`~SemanticMap.save` / :meth:`SemanticMap.load` (a safetensors file
written from the map's blocks, and ``map.json``, atomic: a crash mid-save leaves the previous save
loadable; :mod:`resireg.mapping.map_file`; the JSON records the tensor file's SHA-256 and its own digest, verified on load; the
tensors are memory-mapped), :meth:`~SemanticMap.to_ply` (:mod:`resireg.mapping.colours`). Maps of the
earlier formats load (:data:`~resireg.mapping.map_file.FORMATS`). :meth:`~SemanticMap.fuse` refuses non-finite or non-floating features,
intrinsics and poses (:func:`resireg.method.checks.check_features`).

Memory bound (``exact``): the map holds, per occupied voxel, ``s D + 8`` bytes of accumulators
(``s`` = 8 for float64 sums, 4 for ``sum_dtype="float32"``), 8 bytes of key and 5.7 to 11.4 of
hash slot, and, with ``colour=True``, ``8 x 3 + 8`` bytes of colour sums and their own key and
slot; the accumulators' last block holds fewer than :data:`~resireg.mapping.blocks.BLOCK_ROWS`
spare rows (:attr:`SemanticMap.nbytes` counts them). ``max_voxels`` caps the occupied voxels:
a window that would exceed it raises :class:`MapFullError` *before* anything of it is added, so
the map stays as it was and can be saved. At 5 cm and D = 512 one million voxels (a large
building floor) take ~4.2 GB with float64 sums, ~2.1 GB with float32 ones and ~0.3 GB
``compact`` (docs/benchmarks.md).
"""

from __future__ import annotations

import json
import uuid
import warnings
from collections.abc import Callable, Mapping, Sequence
from pathlib import Path
from typing import Any

import torch
import torch.nn.functional as F
from torch import Tensor, nn

from resireg.errors import MapError
from resireg.mapping.colours import voxel_colours, write_ply
from resireg.mapping.compact import CompactSettings
from resireg.mapping.keys import check_lattice, unpack_keys
from resireg.mapping.lifting import lift_grid
from resireg.mapping.map_file import FORMAT, MapSnapshot, read_map
from resireg.mapping.merging import merge_differences, merge_into
from resireg.mapping.storage import make_storage
from resireg.mapping.storage.base import MapStorage
from resireg.mapping.texts import TextEmbeddings
from resireg.mapping.top_k import TopK, best_voxels, region_rows
from resireg.mapping.voxels import SUM_DTYPES
from resireg.method.checks import check_features
from resireg.method.variants import apply_variant, build_variants
from resireg.specs.mapping import POINTS
from resireg.specs.variants import takes_prior, variant_layer

__all__ = ["ENCODER_OUTPUT", "MapFullError", "SemanticMap"]

#: The name :meth:`SemanticMap.add` gives its encoder's output in a
#: :class:`resireg.method.checks.NonFiniteError` (``resireg-map`` skips such a window and counts it).
ENCODER_OUTPUT = "encoder output"
_EMPTY = "the map is empty: add frames first"


class MapFullError(MapError):
    """A window would take the map past its ``max_voxels`` budget (nothing of it was added)."""


def _variant_argument(variant: Any, configuration: Any) -> Any:
    """The variant given, by ``variant`` or by the keyword it replaces, ``configuration`` (one
    release: a FutureWarning naming ``variant``); both given are refused naming both."""
    if configuration is None:
        if variant is None:
            raise TypeError("SemanticMap() needs variant= (a variant name or module)")
        return variant
    if variant is not None:
        raise TypeError(f"SemanticMap(): variant={_name(variant)!r} and configuration="
                        f"{_name(configuration)!r} both given: give variant= only")  # fmt: skip
    warnings.warn("SemanticMap(configuration=...) is deprecated and will be removed in the next "
                  "release: use variant=", FutureWarning, stacklevel=3)  # fmt: skip
    return configuration


def _name(variant: Any) -> str:
    return type(variant).__name__ if isinstance(variant, nn.Module) else str(variant)


class SemanticMap:
    """A voxel map of one encoder's features under one ReSiReg variant (module docstring).

    Args:
        encoder: a :class:`~resireg.models.DenseEncoder` (only :meth:`fuse` works without one).
        variant: a variant name (``"bb"``, ``"full"``, ``"full@n_prototypes:24"``,
            ``"full+prior"``) built by :func:`resireg.method.variants.build_variants` with ``params``,
            or a variant module (``prior_input`` then says whether it takes the prior).
            ``configuration=``, its name until now, works for one release with a FutureWarning
            (a saved map's record keeps its field ``settings.configuration``).
        voxel_size: voxel edge in metres.
        params: per-variant keyword arguments (``{"full": {"n_prototypes": 36}}``; the
            ``conf/resireg/default.yaml`` keys).
        prior: a segmentation-prior provider (:class:`resireg.priors.SamPrior`) for a ``+prior``
            variant: called on each window's resized images (float ``[B, 3, H, W]``).
        points: :data:`POINTS` (:mod:`resireg.mapping.lifting`).
        lattice: ``"round"`` or ``"floor"`` (:mod:`resireg.mapping.keys`).
        sum_dtype: ``"float64"`` or ``"float32"``: an ``exact`` map's feature sums.
        max_voxels: ``None`` (no bound) or the most voxels the map may hold.
        short_side: the encoder's input rule on the images (``None``: keep the size, sides
            rounded to the patch size).
        colour: also keep each voxel's mean colour (for ``to_ply(colour_by="rgb")``, Rerun).
        device: where the map lives (default: the encoder's device, else the CPU).
        storage: ``"exact"`` or ``"compact"`` (:mod:`resireg.mapping.storage`).
        compact: a ``compact`` map's settings (:class:`~resireg.mapping.compact.CompactSettings`
            or the ``compact`` block of ``conf/map.yaml``; ``None``: its defaults).
    """

    def __init__(
        self,
        encoder: Any,
        variant: str | nn.Module | None = None,
        voxel_size: float | None = None,
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
        storage: str = "exact",
        compact: CompactSettings | Mapping[str, Any] | None = None,
        configuration: str | nn.Module | None = None,
    ) -> None:
        variant = _variant_argument(variant, configuration)
        if points not in POINTS:
            raise ValueError(f"points={points!r}: expected one of {POINTS}")
        if sum_dtype not in SUM_DTYPES:
            raise ValueError(f"sum_dtype={sum_dtype!r}: expected one of {sorted(SUM_DTYPES)}")
        if max_voxels is not None and (
            isinstance(max_voxels, bool) or not isinstance(max_voxels, int) or max_voxels < 1
        ):
            raise ValueError(f"max_voxels={max_voxels!r}: expected null or an integer >= 1")
        self.storage = storage
        self.encoder = encoder
        if isinstance(variant, nn.Module):
            self.variant_name = type(variant).__name__
            self.variant = variant
            self.takes_prior = bool(prior_input)
        else:
            name = str(variant)
            if variant_layer(name) is not None:
                raise ValueError(
                    f"variant={name!r}: @layer: is an evaluation sweep setting; a map "
                    "runs on the encoder's own intermediates"
                )
            self.variant_name = name
            self.variant = build_variants([name], params or {})[name]
            self.takes_prior = takes_prior(name)
        if self.takes_prior and prior is None and encoder is not None and not isinstance(variant, nn.Module):
            raise ValueError(f"variant={self.variant_name!r} takes a prior: pass prior=")
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
        self.keeps_colour = bool(colour)
        #: The voxels, in the storage ``storage`` names (:mod:`resireg.mapping.storage`).
        self.store: MapStorage = make_storage(
            storage, voxel_size=self.voxel_size, lattice=self.lattice, device=self.device,
            colour=self.keeps_colour, sum_dtype=sum_dtype, compact=compact)  # fmt: skip
        self.texts = TextEmbeddings()
        self.frames = 0  # frames fused
        self.windows = 0  # add / fuse calls that fused frames
        self.meta: dict[str, Any] = {}  # the caller's record, saved with the map (e.g. the source)
        # What the map is made of: its own id, assigned here and kept through save, load and
        # resume; a merge's is the union of its inputs' (merge refuses maps sharing a part).
        self.parts: list[str] = [uuid.uuid4().hex]

    def __len__(self) -> int:
        """Occupied voxels."""
        return len(self.store)

    def __repr__(self) -> str:
        return (
            f"SemanticMap(variant={self.variant_name!r}, voxel_size={self.voxel_size}, "
            f"points={self.points!r}, storage={self.storage!r}, voxels={len(self)}, "
            f"frames={self.frames})"
        )

    # ------------------------------------------------------------------ the storage's
    compact = property(lambda self: self.store.compact, doc="A compact map's settings, else None.")
    voxels = property(lambda self: self.store.voxels, doc="The feature map (None before features).")
    colours = property(lambda self: self.store.colours, doc="An exact map's colour sums, or None.")
    basis = property(lambda self: self.store.basis, doc="A compact map's basis ``[D, k]``, or None.")
    basis_sha256 = property(lambda self: self.store.basis_sha256, doc="The basis's SHA-256.")
    dim = property(lambda self: self.store.dim, doc="The fused features' dimension (None before).")
    stored_dim = property(lambda self: self.store.stored_dim, doc="The stored features' dimension.")
    nbytes = property(lambda self: self.store.nbytes, doc="Bytes held (spare rows, basis included).")

    def set_basis(self, basis: Tensor) -> None:
        """Project this compact map's features with ``basis`` ``[D, k]`` (before any voxel)."""
        self.store.set_basis(basis)

    def fit_pending(self) -> None:
        """Fit a compact map's basis now on the features its pending windows hold (a save
        does), and fuse them."""
        self.store.fit_pending()

    def bytes_per_voxel(self, dim: int | None = None) -> int:
        """Bytes per occupied voxel without the spare rows (module docstring; 8 for a hash
        slot, its middle)."""
        return self.store.bytes_per_voxel(dim)

    # ------------------------------------------------------------------ building
    @torch.no_grad()
    def encode(self, images: Tensor) -> Tensor:
        """Dense features ``[B, D, h, w]`` of a window of RGB images ``[B, 3, H, W]`` (uint8, or
        float in [0, 1]): the encoder's input rule, one encoder pass, the variant applied to
        the window (with the prior if it takes one). Every module in eval mode for the pass
        (each module's mode restored), autocast off."""
        return self._encode_resized(self.resized(images))

    @torch.no_grad()
    def _encode_resized(self, raw: Tensor) -> Tensor:
        """:meth:`encode` of images already resized by :meth:`resized`."""
        if self.takes_prior and self.prior is None:
            raise ValueError(f"variant={self.variant_name!r} takes a prior: pass prior=")
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
                          raw if self.keeps_colour else None, None, ENCODER_OUTPUT)  # fmt: skip

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
        if self.dim is not None and features.shape[1] != self.dim:
            raise ValueError(f"features of shape {tuple(features.shape)}: the map has "
                             f"dim={self.dim}")  # fmt: skip
        with torch.autocast(self.device.type, enabled=False):
            grid = tuple(features.shape[-2:])
            cache = {} if lifted is None else lifted
            if grid not in cache:
                cache[grid] = lift_grid(self.points, depth.to(self.device),
                                        intrinsics.to(self.device), cam_to_world.to(self.device),
                                        grid, self.voxel_size, self.lattice)  # fmt: skip
            feats = features.permute(0, 2, 3, 1).float().to(self.device)
            if self.voxels is None:
                self.store.start(int(feats.shape[-1]))
            rgb = None
            if self.keeps_colour and colour is not None:
                rgb = F.adaptive_avg_pool2d(colour.float().to(self.device), grid)
                rgb = rgb.permute(0, 2, 3, 1)
            window = cache[grid].with_features(feats, rgb)
            probe = None
            if self.max_voxels is not None or self.store.waiting:  # (the voxels' indices)
                probe = window.voxel_index(self.voxel_size, self.lattice)
            before = len(self)
            if self.max_voxels is not None:
                new = self.store.count_new(probe)
                held = before + self.store.pending_voxels
                if held + new > self.max_voxels:
                    raise MapFullError(
                        f"max_voxels={self.max_voxels}: this window of {features.shape[0]} "
                        f"frames adds {new} voxels to the map's {held}; raise max_voxels "
                        f"(each voxel holds ~{self.bytes_per_voxel(feats.shape[-1])} bytes), "
                        "use a coarser voxel_size, sum_dtype=float32 or storage=compact, or "
                        "save this map and start a new one"
                    )
            self.store.add(window, probe)
        self.frames += int(features.shape[0])
        self.windows += 1
        return len(self) - before

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
        """Voxel centres ``[M, 3]`` and unit mean features ``[M, D]`` (:meth:`VoxelMap.features`;
        a compact map's ``[M, k]`` stored directions, :meth:`CompactVoxelMap.features`)."""
        return self.store.features()

    def mean_colours(self) -> Tensor:
        """``[M, 3]`` uint8 mean colour per voxel, in :attr:`indices` order."""
        if not self.keeps_colour:
            raise ValueError("this map keeps no colour (colour=False)")
        return self.store.mean_colours()

    def subsample(self, stride: int = 1) -> tuple[Tensor, Tensor, Tensor | None]:
        """Every ``stride``-th voxel in :attr:`indices` order: centres ``[m, 3]``, features
        ``[m, D]`` (as :meth:`features`) and mean colours ``[m, 3]`` (``None`` without colour),
        computed for those voxels only (a cloud of a large map)."""
        centres, feats = self.store.subsample(stride)
        colours = self.mean_colours()[::stride] if self.keeps_colour else None
        return centres, feats, colours

    def text_queries(self, texts: Sequence[str]) -> Tensor:
        """``[K, D]`` unit-norm queries of the raw texts (the encoder's text path, no template),
        each text embedded once per map (the last 1,024 kept)."""
        return self.texts.queries(self.encoder, texts)

    def project(self, queries: Tensor) -> Tensor:
        """Queries ``[K, D]`` in the stored features' space: a compact map's basis applied and
        each renormalised (the cosine in the basis's space, as RayFronts queries its
        compressed map); unchanged for a map without basis."""
        return self.store.project(queries)

    def prototypes(
        self, classes: Sequence[str], templates: Sequence[Callable[[str], str]] | None = None
    ) -> Tensor:
        """``[K, D]`` class prototypes as the protocol builds them: every template (default:
        the 80 OpenAI ImageNet templates) per class through ``text_features`` then
        ``dense_text``, averaged (:func:`resireg.ovss.text_prototypes`); kept per class list
        and templates."""
        return self.texts.prototypes(self.encoder, self.device, classes, templates)

    def _queries(self, texts: str | Sequence[str] | Tensor) -> tuple[bool, Tensor]:
        """(one text?, ``[K, D]`` unit queries) of a text, texts, or query embeddings."""
        if isinstance(texts, Tensor):
            q = texts.float()
            single = q.ndim == 1
            q = q[None] if single else q
            if q.ndim != 2 or (self.dim is not None and q.shape[1] != self.dim):
                raise ValueError(f"queries of shape {tuple(texts.shape)}: expected [D] or "
                                 f"[K, D] with D = {self.dim}")  # fmt: skip
            return single, F.normalize(q, dim=-1)
        single = isinstance(texts, str)
        return single, self.text_queries([texts] if single else list(texts))

    @torch.no_grad()
    def query(self, texts: str | Sequence[str] | Tensor) -> Tensor:
        """Cosine similarity of every voxel's feature to text queries: ``[M, K]`` float32 for a
        list of ``K`` texts (or query embeddings ``[K, D]`` in the encoder's text space), ``[M]``
        for one string (or ``[D]``); rows in :attr:`indices` order (a compact map's scores are
        accumulated in float32 from its stored features)."""
        single, queries = self._queries(texts)
        if self.voxels is None:
            raise ValueError(_EMPTY)
        sim = self.store.similarities(self.project(queries))
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
        :meth:`prototypes`: :func:`resireg.mapping.classify` (the 3D task's rule), through
        :meth:`classify_features`."""
        protos = self.prototypes(classes, templates)
        return self.classify_features(self.project(protos), threshold, denoise)

    def classify_features(self, prototypes: Tensor, threshold: float | None = None,
                          denoise: float | None = None, none: int = -1) -> Tensor:  # fmt: skip
        """:func:`resireg.mapping.classify` of the map's features against ``prototypes`` in
        the stored space (:meth:`project`). A compact map's labels are those of the rule in
        float64 over its stored features, from one float32 pass over them
        (:meth:`CompactVoxelMap.classify`): no float32 copy of the whole map."""
        if self.voxels is None:
            raise ValueError(_EMPTY)
        return self.store.classify(prototypes, threshold, denoise, none)

    @torch.no_grad()
    def top_k(
        self,
        texts: str | Sequence[str] | Tensor,
        k: int = 10,
        *,
        box: Any = None,
        centre: Any = None,
        radius: float | None = None,
    ) -> TopK | list[TopK]:
        """The ``k`` voxels most similar to a text (a list of texts, or query embeddings ``[K,
        D]``: one :class:`TopK` each), optionally among those in a ``box`` (``[[x0, y0, z0],
        [x1, y1, z1]]`` metres) or a ball (``centre``, ``radius``) (:meth:`region`).

        Exact: equal to sorting every voxel's float64 score (its :meth:`features` row with the
        text's query) with ties to the lower voxel index. A compact map scores every voxel in
        low precision first (:meth:`CompactVoxelMap.approx_scores`, with its error bound ``e``)
        and re-scores in float64 the voxels within ``2 e`` of the ``k``-th best: no voxel
        outside can be among the best (several texts: scored in one pass). An exact map scores
        in float64 in chunks (:mod:`resireg.mapping.top_k`)."""
        if isinstance(k, bool) or not isinstance(k, int) or k < 1:
            raise ValueError(f"k={k!r}: expected an integer >= 1")
        single, queries = self._queries(texts)
        queries = self.project(queries)
        whole = box is None and centre is None and radius is None
        joint = self.store.joint_scores(queries) if whole and len(queries) > 1 else None
        if joint is not None:
            approx, bound = joint
            out = [best_voxels(self.store, q, k, None, None, None, (approx[:, i], bound[i]))
                   for i, q in enumerate(queries)]  # fmt: skip
        else:
            out = [best_voxels(self.store, q, k, box, centre, radius) for q in queries]
        return out[0] if single else out

    def region(self, box: Any = None, centre: Any = None, radius: float | None = None) -> Tensor:
        """``[R, 3]`` int64 indices (lexicographic order) of the voxels whose centre lies in
        ``box`` (``[[x0, y0, z0], [x1, y1, z1]]`` metres, inclusive) or within ``radius`` of
        ``centre``. A region of at most four times as many cells as the map holds voxels is
        looked up cell by cell in the key index, without reading the map."""
        if self.voxels is None:
            return torch.empty(0, 3, dtype=torch.int64)
        rows = region_rows(self.store, box, centre, radius)
        return unpack_keys(torch.sort(self.voxels.keys[rows]).values).cpu()

    # ------------------------------------------------------------------ merging
    def merge_differences(self, other: SemanticMap) -> list[str]:
        """What keeps ``other`` from merging into this map: settings (but ``max_voxels``),
        the feature dimension, the basis (by SHA-256, not by where it was read from: a map
        fitted its own, the next run read it from that map's folder) and the encoder's weights
        (by the digest ``resireg-map`` and the live node record in
        ``meta["identity"]["weights"]``)."""
        return merge_differences(self, other)

    def merge(self, other: SemanticMap, transform: Any = None) -> SemanticMap:
        """Add another map of the same encoder and settings (another mapping run) to this one,
        in place; returns ``self``.

        ``transform``: ``None`` (the same world frame) or the ``[4, 4]`` rigid transform from
        ``other``'s world to this one's. One that keeps the lattice (a rotation by multiples
        of 90 degrees about the axes, e.g. about the vertical, and a translation by whole
        voxels) re-keys the voxels exactly: the result equals mapping the transformed frames
        (keys and counts exactly, means to float64 / the storage's rounding). Any other
        transform moves each voxel centre and takes the voxel it falls in: an approximation
        of re-mapping the frames (points near a voxel face change voxels; docs/benchmarks.md
        gives its measured error). A map that differs (:meth:`merge_differences`) is refused,
        naming what differs, and so is one that shares a part (:attr:`parts`) with this one
        (a map and a merge that holds it): merged, its points would count twice. The result
        is made of both maps' parts."""
        if not isinstance(other, SemanticMap):
            raise TypeError(f"merge(): expected a SemanticMap, got {type(other).__name__}")
        if other is self:
            raise ValueError("merge(): a map cannot merge itself")
        return merge_into(self, other, transform)

    # ------------------------------------------------------------------ files
    def settings(self) -> dict[str, Any]:
        """What :meth:`load` needs to rebuild the map (its JSON's ``settings``; the variant's
        name under its saved field name, ``configuration``, so maps of before and after the
        keyword's rename load alike)."""
        return {
            "configuration": self.variant_name,
            "params": self.params,
            "voxel_size": self.voxel_size,
            "points": self.points,
            "lattice": self.lattice,
            "sum_dtype": self.sum_dtype,
            "max_voxels": self.max_voxels,
            "short_side": self.short_side,
            "colour": self.keeps_colour,
            "storage": self.storage,
            "compact": None if self.compact is None else self.compact.as_dict(),
        }

    def snapshot(self, copy: bool = True) -> MapSnapshot:
        """What :meth:`save` writes, taken now: with ``copy`` the map's tensors are copied
        (one copy of the map), so the snapshot is written while the map goes on changing
        (the live node copies under its lock and writes outside it)."""
        self.fit_pending()
        tensors = self.store.tensors()
        if copy:
            tensors = {k: [b.clone() for b in v] for k, v in tensors.items()}
        record = {
            "format": FORMAT,
            "settings": self.settings(),
            "dim": self.dim,
            "stored_dim": self.stored_dim,
            "basis_sha256": self.basis_sha256,
            "voxels": len(self),
            "frames": self.frames,
            "windows": self.windows,
            "meta": json.loads(json.dumps(self.meta)),
            "parts": list(self.parts),
        }
        return MapSnapshot(tensors, record)

    def save(self, folder: str | Path) -> Path:
        """Write the map to ``folder`` (created): ``map-<id>.safetensors`` (every tensor in row
        order, written from the map's blocks without a copy, :mod:`resireg.mapping.tensor_file`)
        and then ``map.json`` (format, settings, counts, ``meta``, ``parts``, the name and
        SHA-256 of that tensor file, the basis's SHA-256, and ``record_sha256``, the digest of
        the record itself), each through :func:`resireg.integrity.atomic_write` (a temporary
        file, fsync, the umask's mode, ``os.replace``). ``map.json`` is the commit point: a
        crash before it leaves the previous save in force; older tensor files are removed after
        it, and a save that fails (a full disk) removes its own new tensor file and raises an
        ``OSError`` naming the file it could not write (:mod:`resireg.mapping.map_file`).
        Returns ``folder``."""
        return self.snapshot(copy=False).write(folder)

    @classmethod
    def load(
        cls,
        folder: str | Path,
        encoder: Any = None,
        prior: Callable[[Tensor], Tensor] | None = None,
        device: torch.device | str | None = None,
        **overrides: Any,
    ) -> SemanticMap:
        """A map saved by :meth:`save` (or by an earlier version), with ``encoder`` for queries
        and further windows; ``folder``: the map folder or a run folder holding it in ``map/``.
        Verified before anything is read or built from it; an encoder of another dimension
        refused; ``overrides``: saved settings that do not change the content (``max_voxels``)
        (:func:`resireg.mapping.map_file.read_map`: every check)."""
        return read_map(cls, folder, encoder, prior, device, overrides)

    def colours_by(
        self,
        colour_by: str = "pca",
        text: str | None = None,
        classes: Sequence[str] | None = None,
    ) -> Tensor:
        """``[M, 3]`` uint8 colour per voxel (:func:`resireg.mapping.colours.voxel_colours`):
        ``rgb``, ``pca``, ``query`` (similarity to ``text``) or ``class`` (of ``classes``)."""
        return voxel_colours(self, colour_by, text, classes)

    def to_ply(
        self,
        path: str | Path,
        colour_by: str = "pca",
        text: str | None = None,
        classes: Sequence[str] | None = None,
    ) -> Path:
        """The voxel centres as a coloured point cloud (binary PLY; :meth:`colours_by`)."""
        return write_ply(path, self.centres(), self.colours_by(colour_by, text, classes))
