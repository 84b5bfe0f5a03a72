"""A language-queryable 3D map a robot feeds with posed RGB-D windows (docs/maps.md#robot-maps-semanticmap).

:class:`SemanticMap` holds one dense encoder, one ReSiReg variant (``bb``, ``lite``, ``full``,
``full@n_prototypes:24``, ``lite+prior``...) and one map storage. :meth:`SemanticMap.add`
encodes a window of consecutive frames in one encoder pass, applies the variant to the window
(ReSiReg Full takes the window as one scene: its prototypes are shared by the window's frames,
as in the 3D task), lifts the features to 3D (:mod:`resireg.mapping.lifting`) and fuses them.
:meth:`SemanticMap.fuse` is the lift-and-fuse step alone, for features computed elsewhere: the
3D task's engine (``resireg_train.evaluation.mapping.engine``) encodes a batch once, applies
every variant to it and fuses each into its own ``SemanticMap``, so the benchmark and a robot
run the same code.

The rooms: the voxels live in the storage ``storage`` names (:mod:`resireg.mapping.storage`:
``exact`` running sums or ``compact`` low-precision unit features with their basis,
:mod:`resireg.mapping.basis`; the map asks its storage and never branches on the kind; the
memory bound: :mod:`resireg.mapping.storage.exact`); queries by text
(:meth:`~SemanticMap.query`, :meth:`~SemanticMap.top_k` and :meth:`~SemanticMap.region`:
:mod:`resireg.mapping.top_k`; :meth:`~SemanticMap.classify`; embeddings kept by
:mod:`resireg.mapping.texts`; a compact map with a basis scores in the basis's space, RayFronts'
compressed query); :meth:`~SemanticMap.merge` (another mapping run's map, optionally through a
rigid transform: :mod:`resireg.mapping.merging`); :meth:`~SemanticMap.save` /
:meth:`SemanticMap.load` (atomic, verified, memory-mapped; the earlier formats load:
:mod:`resireg.mapping.map_file`); :meth:`~SemanticMap.to_ply` (:mod:`resireg.mapping.colours`).
:meth:`~SemanticMap.fuse` refuses non-finite or non-floating features, intrinsics and poses
(:func:`resireg.method.checks.check_features`); ``max_voxels`` caps the occupied voxels: a
window that would exceed it raises :class:`MapFullError` *before* anything of it is added, so
the map stays as it was and can be saved.
"""

from __future__ import annotations

import uuid
from collections.abc import Callable, Mapping, Sequence
from pathlib import Path
from typing import Any

import torch
import torch.nn.functional as F
from torch import Tensor, nn

from resireg.mapping.colours import voxel_colours, write_ply
from resireg.mapping.compact import CompactSettings
from resireg.mapping.fusion import MapFullError, encode_resized, fuse_window, resize_images
from resireg.mapping.keys import check_lattice, unpack_keys
from resireg.mapping.map_file import MapSnapshot, read_map
from resireg.mapping.merging import merge_differences, merge_into
from resireg.mapping.storage import make_storage
from resireg.mapping.storage.base import MapStorage
from resireg.mapping.texts import TextEmbeddings
from resireg.mapping.top_k import TopK, best_voxels, region_rows
from resireg.mapping.variant import map_variant, variant_argument
from resireg.mapping.voxels import SUM_DTYPES
from resireg.specs.mapping import POINTS

__all__ = ["ENCODER_OUTPUT", "MapFullError", "SemanticMap"]

#: The name :meth:`SemanticMap.add` gives its encoder's output in a
#: :class:`resireg.method.checks.NonFiniteError` (``resireg-map`` skips such a window and counts it).
ENCODER_OUTPUT = "encoder output"
_EMPTY = "the map is empty: add frames first"


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
        variant = variant_argument(variant, configuration)
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
        chosen = map_variant(variant, params, prior_input)
        self.variant_name, self.variant, self.takes_prior, _ = chosen
        if self.takes_prior and prior is None and encoder is not None and not chosen.given:
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
    basis = property(
        lambda self: self.store.basis, doc="A compact map's basis ``[D, k]``, or None."
    )
    basis_sha256 = property(lambda self: self.store.basis_sha256, doc="The basis's SHA-256.")
    dim = property(lambda self: self.store.dim, doc="The fused features' dimension (None before).")
    stored_dim = property(lambda self: self.store.stored_dim, doc="The stored features' dimension.")
    nbytes = property(
        lambda self: self.store.nbytes, doc="Bytes held (spare rows, basis included)."
    )

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
        return encode_resized(self, self.resized(images))

    def resized(self, images: Tensor) -> Tensor:
        """RGB ``[B, 3, H, W]`` -> float ``[B, 3, H', W']`` in [0, 1] by the encoder's input rule."""
        return resize_images(self, images)

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
        dense = encode_resized(self, raw)
        return fuse_window(self, dense, depth, intrinsics, cam_to_world,
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
        return fuse_window(
            self, features, depth, intrinsics, cam_to_world, colour, lifted, "features"
        )

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
        in place, optionally through a rigid ``transform`` (exact when it keeps the lattice);
        returns ``self``. A map that differs (:meth:`merge_differences`) or shares a part
        (:attr:`parts`) is refused (:func:`resireg.mapping.merging.merge_into`: the details)."""
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
        return MapSnapshot.of(self, copy)

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
