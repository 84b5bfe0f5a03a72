"""A language-queryable 3D map a robot feeds with posed RGB-D windows (docs/method.md#robot-maps-semanticmap).

:class:`SemanticMap` holds one dense encoder, one ReSiReg configuration (``bb``, ``lite``,
``full``, ``full@n_prototypes:24``, ``lite+prior``...) and one sparse voxel map. :meth:`SemanticMap.add`
encodes a window of consecutive frames in one encoder pass, applies the configuration to the
window (ReSiReg Full takes the window as one scene: its prototypes are shared by the window's
frames, as in the 3D task), lifts the features to 3D (:func:`patch_points` or
:func:`pixel_pairs`) and fuses them. :meth:`SemanticMap.fuse` is the lift-and-fuse step alone,
for features computed elsewhere: the 3D task's engine (``resireg_train.evaluation.mapping.engine``) encodes
a batch once, applies every configuration to it and fuses each into its own ``SemanticMap``, so
the benchmark and a robot run the same code.

Storage (``storage``, :data:`~resireg.specs.mapping.STORAGES`): ``exact`` keeps running feature
sums (:class:`VoxelMap`, ``sum_dtype`` float64 or float32) and a mean colour map; ``compact``
keeps low-precision unit features, optionally projected to ``compact.dim`` channels by a basis
fitted once on the first ``compact.basis_rows`` features (an uncentred PCA, :mod:`resireg.method.pca`)
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
loadable; the JSON records the tensor file's SHA-256 and its own digest, verified on load; the
tensors are memory-mapped), :meth:`~SemanticMap.to_ply`. Maps of the earlier formats load
(:data:`FORMATS`). :meth:`~SemanticMap.fuse` refuses non-finite or non-floating features,
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

import hashlib
import json
import math
import os
import uuid
import warnings
from collections import OrderedDict
from collections.abc import Callable, Mapping, Sequence
from pathlib import Path
from typing import Any, NamedTuple

import numpy as np
import torch
import torch.nn.functional as F
from torch import Tensor, nn

from resireg.errors import MapError, parameters
from resireg.integrity import IntegrityError, atomic_write, read_json, sha256_file, verify_digests
from resireg.mapping.compact import STORED_DTYPES, CompactSettings, CompactVoxelMap
from resireg.mapping.geometry import patch_points
from resireg.mapping.keys import (
    check_lattice,
    pack_keys,
    transform_keys,
    unpack_keys,
    voxel_centres,
    voxel_indices,
)
from resireg.mapping.lifting import pixel_pairs
from resireg.mapping.query import classify as classify_features
from resireg.mapping.tensor_file import read_tensors, write_tensors
from resireg.mapping.voxels import SUM_DTYPES, VoxelMap
from resireg.method.checks import check_features
from resireg.method.variants import apply_variant, build_variants
from resireg.specs.mapping import POINTS, STORAGES, map_errors
from resireg.specs.variants import takes_prior, variant_layer

__all__ = [
    "COLOUR_BY",
    "ENCODER_OUTPUT",
    "FORMAT",
    "FORMATS",
    "POINTS",
    "MapFullError",
    "MapFormatWarning",
    "SemanticMap",
    "TopK",
    "load_basis",
    "map_folder",
    "pca_colours",
    "remove_partial_saves",
    "write_ply",
]

#: What :meth:`SemanticMap.to_ply` colours the voxels by.
COLOUR_BY = ("rgb", "pca", "query", "class")
#: The files of a saved map: the JSON (written last: the commit point) names its tensor file.
MAP_JSON = "map.json"
#: The format :meth:`SemanticMap.save` writes. It changes whenever what a reader needs changes:
#: ``/2`` holds each map's keys in row order with its hash table, its storage and basis.
FORMAT = "resireg.semantic_map/2"
#: The formats :meth:`SemanticMap.load` reads: ``/1`` (indices in lexicographic order; maps
#: saved before the digests were recorded load with a :class:`MapFormatWarning`) and ``/2``.
FORMATS = ("resireg.semantic_map/1", FORMAT)
#: Texts (and class lists) whose embeddings a map keeps.
_TEXT_CACHE = 1024
#: The name :meth:`SemanticMap.add` gives its encoder's output in a
#: :class:`resireg.method.checks.NonFiniteError` (``resireg-map`` skips such a window and counts it).
ENCODER_OUTPUT = "encoder output"


class MapFullError(MapError):
    """A window would take the map past its ``max_voxels`` budget (nothing of it was added)."""


class MapFormatWarning(UserWarning):
    """A saved map of an earlier format was loaded without what the current one proves."""


class TopK(NamedTuple):
    """The best voxels of a text (:meth:`SemanticMap.top_k`), best first (ties: the lower
    voxel index, in lexicographic order)."""

    indices: Tensor  #: ``[k, 3]`` int64 voxel indices
    centres: Tensor  #: ``[k, 3]`` float32 voxel centres
    scores: Tensor  #: ``[k]`` float64 cosine scores (the voxels' features as :meth:`features` gives them)


def _sha256(t: Tensor) -> str:
    return hashlib.sha256(t.detach().cpu().contiguous().numpy().tobytes()).hexdigest()


def _inside(folder: Path, name: Any, field: str, record: Path) -> Path:
    """``folder / name`` when ``name`` (read from ``record``'s ``field``) is a file name that
    stays inside ``folder``; else an :class:`IntegrityError` naming the field and the path
    (a record names its own files; it never points elsewhere)."""
    if not isinstance(name, str) or not name:
        raise IntegrityError(f"{record}: {field}={name!r}: expected a file name")
    path = folder / name
    inside = Path(name).name == name and not Path(name).is_absolute() and name not in (".", "..")
    if not inside or path.resolve().parent != folder.resolve():
        raise IntegrityError(
            f"{record}: {field}={name!r} names a file outside the map folder {folder} "
            "(a map's files stay in its folder)"
        )
    return path


def map_folder(path: str | Path) -> Path:
    """The saved map a "map" argument names: ``path`` itself when it holds ``map.json`` (a map
    folder), else its ``map`` folder (a ``resireg-map`` or ``resireg-map-merge`` run folder).
    The one rule for every argument that names a map (:meth:`SemanticMap.load`,
    ``compact.basis``, ``resireg-map-merge``'s maps); a :class:`FileNotFoundError` naming
    ``path`` when it is neither."""
    path = Path(path).expanduser()
    for folder in (path, path / "map"):
        if (folder / MAP_JSON).is_file():
            return folder
    raise FileNotFoundError(f"{str(path)!r} is neither a saved map (no {MAP_JSON}) nor a run "
                            f"folder holding one (no map/{MAP_JSON})")  # fmt: skip


def load_basis(path: str | Path) -> Tensor:
    """A projection basis ``[D, k]`` float32: the ``basis`` of a saved map (a map folder or a
    run folder, :func:`map_folder`; verified as :meth:`SemanticMap.load` verifies it) or the
    tensor ``basis`` of a ``.safetensors`` file."""
    path = Path(path).expanduser()
    if path.is_dir():
        try:
            path = map_folder(path)
        except FileNotFoundError as err:
            raise ValueError(f"compact.basis={err}") from None
        record = read_json(path / MAP_JSON, "saved map record")
        if not isinstance(record, dict) or not record.get("basis_sha256"):
            raise ValueError(f"compact.basis={str(path)!r}: the map records no basis")
        name = _inside(path, record.get("tensors"), "tensors", path / MAP_JSON)
        verify_digests(path, {name.name: (record.get("sha256") or {}).get(name.name, "")},
                       "saved map")  # fmt: skip
        tensors = read_tensors(name, "saved map")
        basis = tensors.get("basis")
        if basis is None or _sha256(basis) != record["basis_sha256"]:
            raise IntegrityError(f"{name}: no basis of the recorded SHA-256")
    elif path.is_file():
        basis = read_tensors(path, "basis file").get("basis")
    else:
        raise ValueError(f"compact.basis={str(path)!r}: no such map folder or file")
    if basis is None or basis.ndim != 2 or not basis.is_floating_point():
        raise ValueError(f"compact.basis={str(path)!r}: expected a [D, k] float tensor 'basis'")
    return basis.to(torch.float32).clone()


def _integer(value: Any, least: int) -> bool:
    return isinstance(value, int) and not isinstance(value, bool) and value >= least


def _sha256_text(value: Any) -> bool:
    """``None`` or a SHA-256 as ``hexdigest`` writes it."""
    hexdigits = "0123456789abcdef"
    return value is None or (isinstance(value, str) and len(value) == 64
                             and all(c in hexdigits for c in value))  # fmt: skip


#: The most parts (:attr:`SemanticMap.parts`) a map may be made of (a merge of more is refused;
#: a record naming more is refused before it is read further).
MAX_PARTS = 4096


def _parts_ok(value: Any) -> bool:
    """A map's ``parts``: 1 to :data:`MAX_PARTS` distinct ids, each 32 (a uuid4's hex) or 64
    (a SHA-256) lowercase hex digits."""
    hexdigits = "0123456789abcdef"
    return (isinstance(value, list) and 0 < len(value) <= MAX_PARTS
            and all(isinstance(x, str) and len(x) in (32, 64) and all(c in hexdigits for c in x)
                    for x in value)
            and len(set(value)) == len(value))  # fmt: skip


def _params_ok(value: Any) -> bool:
    """A map's ``params``: variant name -> ``None`` or its keyword arguments."""
    return isinstance(value, dict) and all(
        isinstance(k, str) and (x is None or isinstance(x, dict)) for k, x in value.items()
    )


#: The fields of ``map.json`` that :meth:`SemanticMap.load` reads beside the digests and the
#: tensor file's name: (required, rule, what the rule expects).
_RECORD_FIELDS: dict[str, tuple[bool, Callable[[Any], bool], str]] = {
    "settings": (True, lambda v: isinstance(v, dict), "a mapping of the map's settings"),
    "dim": (True, lambda v: v is None or _integer(v, 1), "null or an integer >= 1"),
    "stored_dim": (False, lambda v: v is None or _integer(v, 1), "null or an integer >= 1"),
    "basis_sha256": (False, _sha256_text, "null or a SHA-256 (64 lowercase hex digits)"),
    "voxels": (True, lambda v: _integer(v, 0), "an integer >= 0"),
    "frames": (True, lambda v: _integer(v, 0), "an integer >= 0"),
    "windows": (True, lambda v: _integer(v, 0), "an integer >= 0"),
    "meta": (False, lambda v: v is None or isinstance(v, dict), "null or a mapping"),
    "parts": (
        False,
        _parts_ok,
        f"a list of 1 to {MAX_PARTS} distinct ids of 32 or 64 lowercase hex digits",
    ),
}
#: The keys of a record's ``settings`` that are not rules of MAP_RULES: their rule here.
_SETTING_TYPES: dict[str, tuple[Callable[[Any], bool], str]] = {
    "configuration": (lambda v: isinstance(v, str) and bool(v), "a configuration name"),
    "params": (_params_ok, "a mapping of variant name -> null or a mapping of its arguments"),
    "colour": (lambda v: isinstance(v, bool), "true or false"),
    "compact": (lambda v: v is None or isinstance(v, dict), "null or a mapping"),
}


def _record_errors(record: Mapping[str, Any], names: Sequence[str]) -> list[str]:
    """``field=value: expected ...`` for each field of a map record that :meth:`SemanticMap.load`
    cannot take (:data:`_RECORD_FIELDS`; ``settings.<key>`` by the map settings' own rules,
    :data:`~resireg.specs.mapping.MAP_RULES`, and :data:`_SETTING_TYPES`; ``names``: the
    setting keys a map has), so a record is refused whole before anything is built from it."""
    errors = []
    for name, (required, ok, expected) in _RECORD_FIELDS.items():
        if name not in record:
            if required:
                errors.append(f"{name}: missing")
        elif not ok(record[name]):
            errors.append(f"{name}={_shown(record[name])}: expected {expected}")
    settings = record.get("settings")
    if not isinstance(settings, dict):
        return errors
    errors += [f"settings.{k}: no such setting (expected one of {sorted(names)})"
               for k in settings if k not in names]  # fmt: skip
    errors += [f"settings.{k}: missing" for k in ("configuration", "params", "voxel_size")
               if k not in settings]  # fmt: skip
    for key, (ok, expected) in _SETTING_TYPES.items():
        if key in settings and not ok(settings[key]):
            errors.append(f"settings.{key}={_shown(settings[key])}: expected {expected}")
    ruled = {k: v for k, v in settings.items() if k != "compact" or isinstance(v, dict)}
    return errors + map_errors(ruled, prefix="settings.")


def _shown(value: Any) -> str:
    """A value as an error names it: its repr, cut to 80 characters."""
    text = repr(value)
    return text if len(text) <= 80 else text[:77] + "..."


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


def _running(pid: int) -> bool:
    """Whether a process ``pid`` runs on this machine (signal 0 probes it)."""
    try:
        os.kill(pid, 0)
    except ProcessLookupError:
        return False
    except (PermissionError, OverflowError):
        return True  # another user's (or an id no process can have: kept, to be safe)
    return True


def remove_partial_saves(folder: str | Path) -> list[Path]:
    """Remove from a map folder the temporary files of saves whose process no longer runs:
    :func:`~resireg.integrity.atomic_write` names them ``.<file>.<pid>.<id>.tmp``, and one
    killed mid-save (SIGKILL, a power cut) leaves its file behind (the committed map is
    untouched). A save of this or another running process is left alone. Returns the files
    removed; :meth:`SemanticMap.save` calls it, and the commands that write a map folder at
    their start."""
    removed = []
    for tmp in Path(folder).glob(".map*.tmp"):
        parts = tmp.name.split(".")
        if len(parts) >= 5 and parts[-3].isdigit() and not _running(int(parts[-3])):
            tmp.unlink(missing_ok=True)
            removed.append(tmp)
    return removed


class MapSnapshot:
    """A map's tensors (lists of blocks, by file name) and record, as :meth:`SemanticMap.save`
    writes them (:meth:`SemanticMap.snapshot`)."""

    def __init__(self, tensors: dict[str, list[Tensor]], record: dict[str, Any]) -> None:
        self.tensors, self.record = tensors, record

    def write(self, folder: str | Path) -> Path:
        """Write the tensor file, then ``map.json`` (the commit point), then remove older
        tensor files (:meth:`SemanticMap.save`)."""
        folder = Path(folder)
        folder.mkdir(parents=True, exist_ok=True)
        remove_partial_saves(folder)
        name = f"map-{uuid.uuid4().hex[:12]}.safetensors"
        digest: dict[str, str] = {}
        try:
            atomic_write(
                folder / name, lambda tmp: digest.update({name: write_tensors(tmp, self.tensors)})
            )
            record = {**self.record, "tensors": name, "sha256": digest}
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
        lattice: ``"round"`` or ``"floor"`` (:mod:`resireg.mapping.keys`).
        sum_dtype: ``"float64"`` or ``"float32"``: an ``exact`` map's feature sums.
        max_voxels: ``None`` (no bound) or the most voxels the map may hold.
        short_side: the encoder's input rule on the images (``None``: keep the size, sides
            rounded to the patch size).
        colour: also keep each voxel's mean colour (for ``to_ply(colour_by="rgb")``, Rerun).
        device: where the map lives (default: the encoder's device, else the CPU).
        storage: ``"exact"`` or ``"compact"`` (module docstring).
        compact: a ``compact`` map's settings (:class:`~resireg.mapping.compact.CompactSettings`
            or the ``compact`` block of ``conf/map.yaml``; ``None``: its defaults).
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
        storage: str = "exact",
        compact: CompactSettings | Mapping[str, Any] | None = None,
    ) -> None:
        if points not in POINTS:
            raise ValueError(f"points={points!r}: expected one of {POINTS}")
        if sum_dtype not in SUM_DTYPES:
            raise ValueError(f"sum_dtype={sum_dtype!r}: expected one of {sorted(SUM_DTYPES)}")
        if max_voxels is not None and (
            isinstance(max_voxels, bool) or not isinstance(max_voxels, int) or max_voxels < 1
        ):
            raise ValueError(f"max_voxels={max_voxels!r}: expected null or an integer >= 1")
        if storage not in STORAGES:
            raise ValueError(f"storage={storage!r}: expected one of {list(STORAGES)}")
        self.storage = storage
        self.compact = CompactSettings.of(compact) if storage == "compact" else None
        if self.compact is not None:
            errors = map_errors({"compact": self.compact.as_dict()})
            if errors:
                raise ValueError("; ".join(errors))
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
        self.keeps_colour = bool(colour)
        self.voxels: VoxelMap | CompactVoxelMap | None = None  # made when the dimension is known
        exact = storage == "exact"
        self.colours = (VoxelMap(self.voxel_size, 3, self.device, self.lattice)
                        if colour and exact else None)  # fmt: skip
        VoxelMap(self.voxel_size, 1, self.device, self.lattice)  # checks voxel_size now
        self._dim: int | None = None
        self.basis: Tensor | None = None  # [D, k]: a compact map's projection
        self.basis_sha256: str | None = None
        self._pending: list[tuple] = []  # windows waiting for the basis
        self._pending_rows: list[Tensor] = []
        self._pending_keys: Tensor | None = None
        if self.compact is not None and self.compact.dim is not None and self.compact.basis:
            self.set_basis(load_basis(self.compact.basis))
        self._texts: OrderedDict[str, Tensor] = OrderedDict()
        self._prototypes: OrderedDict[Any, Tensor] = OrderedDict()
        self.frames = 0  # frames fused
        self.windows = 0  # add / fuse calls that fused frames
        self.meta: dict[str, Any] = {}  # the caller's record, saved with the map (e.g. the source)
        # What the map is made of: its own id, assigned here and kept through save, load and
        # resume; a merge's is the union of its inputs' (merge refuses maps sharing a part).
        self.parts: list[str] = [uuid.uuid4().hex]

    def __len__(self) -> int:
        """Occupied voxels."""
        return 0 if self.voxels is None else len(self.voxels)

    def __repr__(self) -> str:
        return (
            f"SemanticMap(configuration={self.configuration!r}, voxel_size={self.voxel_size}, "
            f"points={self.points!r}, storage={self.storage!r}, voxels={len(self)}, "
            f"frames={self.frames})"
        )

    # ------------------------------------------------------------------ building
    @property
    def dim(self) -> int | None:
        """The dimension of the features fused (``None`` before the first window)."""
        return self._dim

    @property
    def stored_dim(self) -> int | None:
        """The dimension of the stored features: ``compact.dim`` for a compact map with a
        basis, else :attr:`dim`."""
        if self.basis is not None:
            return int(self.basis.shape[1])
        if self.compact is not None and self.compact.dim is not None and self._dim is not None:
            return min(self.compact.dim, self._dim)
        return self._dim

    def set_basis(self, basis: Tensor) -> None:
        """Project this compact map's features with ``basis`` ``[D, k]`` (before any voxel)."""
        if self.compact is None or self.compact.dim is None:
            raise ValueError("a basis is for a compact map with compact.dim set")
        if len(self) or self._pending:
            raise ValueError("set_basis(): the map already holds features")
        if basis.ndim != 2 or basis.shape[1] != self.compact.dim:
            raise ValueError(f"basis of shape {tuple(basis.shape)}: expected [D, "
                             f"compact.dim={self.compact.dim}]")  # fmt: skip
        if self._dim is not None and basis.shape[0] != self._dim:
            raise ValueError(f"basis of shape {tuple(basis.shape)}: the map's features are "
                             f"{self._dim}-d")  # fmt: skip
        self.basis = basis.to(device=self.device, dtype=torch.float32).contiguous()
        self.basis_sha256 = _sha256(self.basis)

    def _needs_basis(self) -> bool:
        return (self.compact is not None and self.compact.dim is not None
                and self.basis is None and self._dim is not None and self.compact.dim < self._dim)  # fmt: skip

    def _fit_basis(self) -> None:
        """The basis of the pending features: the top ``compact.dim`` eigenvectors of their
        uncentred second moment (float64, :func:`resireg.method.pca.pca_from_moments` with a zero
        first moment: the mean direction is kept, as every cosine needs it); then the pending
        windows are fused."""
        from resireg.method.pca import gram, pca_from_moments

        rows = torch.cat(self._pending_rows).to(torch.float64)
        if rows.shape[0] < 2:
            raise ValueError(f"a compact map fits its basis on >= 2 features; it has "
                             f"{rows.shape[0]}: map more frames first")  # fmt: skip
        fit = pca_from_moments(gram(rows), rows.new_zeros(rows.shape[1]), rows.shape[0],
                               self.compact.dim)  # fmt: skip
        pending = self._pending
        self._pending, self._pending_rows, self._pending_keys = [], [], None
        self.set_basis(fit.components.T)
        self.voxels = self._make_voxels()
        for payload in pending:
            self._apply(payload)

    def _make_voxels(self) -> VoxelMap | CompactVoxelMap:
        if self.compact is None:
            return VoxelMap(self.voxel_size, self._dim, self.device, self.lattice,
                            SUM_DTYPES[self.sum_dtype])  # fmt: skip
        c = self.compact
        return CompactVoxelMap(self.voxel_size, self.stored_dim, self.device, self.lattice,
                               STORED_DTYPES[c.dtype], self.keeps_colour, c.hot_voxels)  # fmt: skip

    @property
    def nbytes(self) -> int:
        """Bytes held by the map's tensors (spare rows and the basis included)."""
        held = sum(m.nbytes for m in (self.voxels, self.colours) if m is not None)
        return held + (0 if self.basis is None else self.basis.numel() * 4)

    def bytes_per_voxel(self, dim: int | None = None) -> int:
        """Bytes per occupied voxel without the spare rows (module docstring; 8 for a hash
        slot, its middle)."""
        d = dim or self.stored_dim or 0
        if self.compact is not None:
            if self.basis is None and self.compact.dim is not None:
                d = min(d, self.compact.dim)
            size = 8 + 8 + d * STORED_DTYPES[self.compact.dtype].itemsize + 4 + 4
            return size + (3 + 4 if self.keeps_colour else 0)
        size = 8 + 8 + d * SUM_DTYPES[self.sum_dtype].itemsize + 8
        return size + (8 + 8 + 3 * 8 + 8 if self.colours is not None else 0)

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
        if self._dim is not None and features.shape[1] != self._dim:
            raise ValueError(f"features of shape {tuple(features.shape)}: the map has "
                             f"dim={self._dim}")  # fmt: skip
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
            if self._dim is None:
                self._dim = int(feats.shape[-1])
                if self.basis is not None and self.basis.shape[0] != self._dim:
                    self._dim = None
                    raise ValueError(f"features of {feats.shape[-1]} channels: the basis "
                                     f"projects {self.basis.shape[0]}")  # fmt: skip
            if self.voxels is None and not self._needs_basis():
                self.voxels = self._make_voxels()
            rgb = None
            if self.keeps_colour and colour is not None:
                rgb = F.adaptive_avg_pool2d(colour.float().to(self.device), grid)
                rgb = rgb.permute(0, 2, 3, 1)
            if kind == "patch":
                pts, valid = geometry
                payload = ("patch", pts[valid], feats[valid], None if rgb is None else rgb[valid])
            else:
                index, patch, count = geometry
                payload = ("pixel", index, count, patch, feats.reshape(-1, feats.shape[-1]),
                           None if rgb is None else rgb.reshape(-1, 3))  # fmt: skip
            probe = None
            if self.max_voxels is not None or self._needs_basis():  # (the voxels' indices)
                probe = (voxel_indices(payload[1], self.voxel_size, self.lattice)
                         if kind == "patch" else payload[1])  # fmt: skip
            before = len(self)
            if self.max_voxels is not None:
                new = self._count_new(probe)
                held = before + (0 if self._pending_keys is None else self._pending_keys.numel())
                if held + new > self.max_voxels:
                    raise MapFullError(
                        f"max_voxels={self.max_voxels}: this window of {features.shape[0]} "
                        f"frames adds {new} voxels to the map's {held}; raise max_voxels "
                        f"(each voxel holds ~{self.bytes_per_voxel(feats.shape[-1])} bytes), "
                        "use a coarser voxel_size, sum_dtype=float32 or storage=compact, or "
                        "save this map and start a new one"
                    )
            if self._needs_basis():
                self._pend(payload, probe)
            else:
                self._apply(payload)
        self.frames += int(features.shape[0])
        self.windows += 1
        return len(self) - before

    def _count_new(self, probe: Tensor) -> int:
        """Distinct voxels of indices ``probe`` that neither the map nor its pending windows hold."""
        if self.voxels is not None:
            return self.voxels.count_new(probe)
        keys = torch.unique(pack_keys(probe.to(torch.int64)))
        held = self._pending_keys
        if held is None or not held.numel():
            return int(keys.numel())
        pos = torch.searchsorted(held, keys).clamp_max(held.numel() - 1)
        return int((held[pos] != keys).sum())

    def _pend(self, payload: tuple, probe: Tensor) -> None:
        """Keep a window until the basis is fitted (fitted now if the pending windows hold
        ``compact.basis_rows`` features)."""
        self._pending.append(payload)
        if payload[0] == "patch":
            self._pending_rows.append(payload[2])
        else:  # the lifted patches' features, once each
            self._pending_rows.append(payload[4][torch.unique(payload[3])])
        keys = torch.unique(pack_keys(probe.to(torch.int64)))
        held = self._pending_keys
        self._pending_keys = keys if held is None else torch.unique(torch.cat([held, keys]))
        if sum(r.shape[0] for r in self._pending_rows) >= self.compact.basis_rows:
            self._fit_basis()

    def _apply(self, payload: tuple) -> None:
        """Add one lifted window to the voxels (projected by the basis, if any)."""
        vmap = self.voxels
        if payload[0] == "patch":
            _, pts, feats, rgb = payload
        else:
            _, index, count, patch, feats, rgb = payload
        if self.basis is not None:
            feats = feats @ self.basis
        if isinstance(vmap, CompactVoxelMap):
            if payload[0] == "patch":
                vmap.add(pts, feats, rgb)
            else:
                vmap.add_pairs(index, count, feats, patch, rgb)
            return
        if payload[0] == "patch":
            vmap.add(pts, feats)
            if rgb is not None and self.colours is not None:
                self.colours.add(pts, rgb)
        else:
            vmap.add_pairs(index, count, feats, patch)
            if rgb is not None and self.colours is not None:
                self.colours.add_pairs(index, count, rgb, patch)

    def fit_pending(self) -> None:
        """Fit a compact map's basis now on the features its pending windows hold (a save
        does), and fuse them."""
        if self._pending:
            self._fit_basis()

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
        if self.voxels is None:
            raise ValueError("the map is empty: add frames first")
        return self.voxels.features()

    def mean_colours(self) -> Tensor:
        """``[M, 3]`` uint8 mean colour per voxel, in :attr:`indices` order."""
        if not self.keeps_colour:
            raise ValueError("this map keeps no colour (colour=False)")
        if isinstance(self.voxels, CompactVoxelMap):
            return self.voxels.mean_colours()
        if self.voxels is None or not len(self.colours):
            return torch.zeros(len(self), 3, dtype=torch.uint8)
        at = self.colours.find(self.indices)
        mean = self.colours.means().float()
        out = torch.zeros(len(self), 3, device=mean.device)
        out[at >= 0] = mean[at[at >= 0]]
        return (out.clamp(0, 1) * 255).round().to(torch.uint8).cpu()

    def subsample(self, stride: int = 1) -> tuple[Tensor, Tensor, Tensor | None]:
        """Every ``stride``-th voxel in :attr:`indices` order: centres ``[m, 3]``, features
        ``[m, D]`` (as :meth:`features`) and mean colours ``[m, 3]`` (``None`` without colour),
        computed for those voxels only (a cloud of a large map)."""
        if self.voxels is None:
            raise ValueError("the map is empty: add frames first")
        if stride == 1 and isinstance(self.voxels, VoxelMap):
            centres, feats = self.voxels.features()
        else:
            rows = self.voxels.sorted_rows[::stride]
            centres = voxel_centres(unpack_keys(self.voxels.keys[rows]), self.voxel_size,
                                    self.lattice)  # fmt: skip
            feats = self.voxels.unit_rows(rows)
        colours = self.mean_colours()[::stride] if self.keeps_colour else None
        return centres, feats, colours

    @torch.no_grad()
    def text_queries(self, texts: Sequence[str]) -> Tensor:
        """``[K, D]`` unit-norm queries of the raw texts (the encoder's text path, no template),
        each text embedded once per map (the last 1,024 kept)."""
        if self.encoder is None:
            raise ValueError("this map has no encoder to embed text: pass one to load()")
        texts = [str(t) for t in texts]
        missing = [t for t in dict.fromkeys(texts) if t not in self._texts]
        if missing:
            feats = self.encoder.text_features(missing)
            queries = F.normalize(self.encoder.dense_text(feats).float(), dim=-1)
            for text, q in zip(missing, queries, strict=True):
                self._texts[text] = q
        for text in texts:
            self._texts.move_to_end(text)
        while len(self._texts) > _TEXT_CACHE:
            self._texts.popitem(last=False)
        return torch.stack([self._texts[t] for t in texts]) if texts else torch.empty(0, 0)

    def project(self, queries: Tensor) -> Tensor:
        """Queries ``[K, D]`` in the stored features' space: a compact map's basis applied and
        each renormalised (the cosine in the basis's space, as RayFronts queries its
        compressed map); unchanged for a map without basis."""
        if self.basis is None:
            return queries
        return F.normalize(queries.to(self.basis.device).float() @ self.basis, dim=-1)

    @torch.no_grad()
    def prototypes(
        self, classes: Sequence[str], templates: Sequence[Callable[[str], str]] | None = None
    ) -> Tensor:
        """``[K, D]`` class prototypes as the protocol builds them: every template (default:
        the 80 OpenAI ImageNet templates) per class through ``text_features`` then
        ``dense_text``, averaged (:func:`resireg.ovss.text_prototypes`); kept per class list
        and templates."""
        from resireg.ovss import TEMPLATES, text_prototypes

        if self.encoder is None:
            raise ValueError("this map has no encoder to embed text: pass one to load()")
        key = (tuple(classes), None if templates is None else tuple(map(id, templates)))
        if key in self._prototypes:
            self._prototypes.move_to_end(key)
            return self._prototypes[key]
        enc = self.encoder

        def embed(texts: list[str]) -> Tensor:
            return enc.dense_text(enc.text_features(texts))

        with torch.autocast(self.device.type, enabled=False):
            protos = text_prototypes(embed, list(classes), templates or TEMPLATES)
        self._prototypes[key] = protos
        while len(self._prototypes) > 64:
            self._prototypes.popitem(last=False)
        return protos

    def _queries(self, texts: str | Sequence[str] | Tensor) -> tuple[bool, Tensor]:
        """(one text?, ``[K, D]`` unit queries) of a text, texts, or query embeddings."""
        if isinstance(texts, Tensor):
            q = texts.float()
            single = q.ndim == 1
            q = q[None] if single else q
            if q.ndim != 2 or (self._dim is not None and q.shape[1] != self._dim):
                raise ValueError(f"queries of shape {tuple(texts.shape)}: expected [D] or "
                                 f"[K, D] with D = {self._dim}")  # fmt: skip
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
        if isinstance(self.voxels, CompactVoxelMap):
            scores, _ = self.voxels.approx_scores(self.project(queries), fast=False)
            sim = scores[self.voxels.sorted_rows]
        else:
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
        :meth:`prototypes`: :func:`resireg.mapping.classify` (the 3D task's rule); a compact
        map's labels are the rule's in float64 over its stored features
        (:meth:`CompactVoxelMap.classify`: one float32 pass, the rows it leaves open in float64)."""
        protos = self.prototypes(classes, templates)
        if not isinstance(self.voxels, CompactVoxelMap):
            _, feats = self.features()
            return classify_features(feats, protos.to(feats.device), threshold, denoise, none=-1)
        return self.classify_features(self.project(protos), threshold, denoise)

    def classify_features(self, prototypes: Tensor, threshold: float | None = None,
                          denoise: float | None = None, none: int = -1) -> Tensor:  # fmt: skip
        """:func:`resireg.mapping.classify` of the map's features against ``prototypes`` in
        the stored space (:meth:`project`). A compact map's labels are those of the rule in
        float64 over its stored features, from one float32 pass over them
        (:meth:`CompactVoxelMap.classify`): no float32 copy of the whole map."""
        if self.voxels is None:
            raise ValueError("the map is empty: add frames first")
        if not isinstance(self.voxels, CompactVoxelMap):
            _, feats = self.features()
            return classify_features(feats, prototypes.to(feats.device), threshold, denoise,
                                     none=none)  # fmt: skip
        return self.voxels.classify(prototypes, threshold, denoise, none=none)

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
        D]``: one :class:`TopK` each), optionally among those in a ``box`` (``[[x0, y0, z0], [x1, y1, z1]]`` metres) or a ball
        (``centre``, ``radius``) (:meth:`region`).

        Exact: equal to sorting every voxel's float64 score (its :meth:`features` row with the
        text's query) with ties to the lower voxel index. A compact map scores every voxel in
        low precision first (:meth:`CompactVoxelMap.approx_scores`, with its error bound ``e``)
        and re-scores in float64 the voxels within ``2 e`` of the ``k``-th best: no voxel
        outside can be among the best. An exact map scores in float64 in chunks."""
        if isinstance(k, bool) or not isinstance(k, int) or k < 1:
            raise ValueError(f"k={k!r}: expected an integer >= 1")
        single, queries = self._queries(texts)
        queries = self.project(queries)
        vmap = self.voxels
        whole = box is None and centre is None and radius is None
        if isinstance(vmap, CompactVoxelMap) and len(vmap) and whole and len(queries) > 1:
            # several texts: one pass over the stored features scores them all (a matrix
            # product instead of one memory-bound matrix-vector product per text)
            approx, bound = vmap.approx_scores(queries.to(self.device))
            out = [self._top_k(q, k, None, None, None, (approx[:, i], bound[i]))
                   for i, q in enumerate(queries)]  # fmt: skip
        else:
            out = [self._top_k(q, k, box, centre, radius) for q in queries]
        return out[0] if single else out

    def _top_k(
        self, q: Tensor, k: int, box, centre, radius, approx: tuple[Tensor, Tensor] | None = None
    ) -> TopK:
        """One text's :meth:`top_k`; ``approx``: its low-precision scores and their bound,
        when :meth:`top_k` scored several texts in one pass (compact maps)."""
        vmap = self.voxels
        if vmap is None or not len(vmap):
            empty = torch.empty(0, 3, dtype=torch.int64)
            return TopK(empty, empty.float(), torch.empty(0, dtype=torch.float64))
        q = q[None].to(self.device)
        if box is not None or centre is not None or radius is not None:
            rows = self._region_rows(box, centre, radius)
            scores = vmap.exact_scores(rows, q)[:, 0] if rows.numel() else q.new_zeros(0).double()
        elif isinstance(vmap, CompactVoxelMap):
            if approx is None:
                scored, bounds = vmap.approx_scores(q)
                approx = (scored[:, 0], bounds[0])
            low, bound = approx
            kth = torch.topk(low, min(k, low.shape[0])).values[-1].double()
            rows = (low.double() >= kth - 2 * bound.double()).nonzero().squeeze(1)
            scores = vmap.exact_scores(rows, q)[:, 0]
        else:
            rows = torch.arange(len(vmap), device=self.device)
            scores = vmap.all_scores(q)[:, 0]
        keys = vmap.keys[rows]
        by_key = torch.argsort(keys)
        best = by_key[torch.argsort(-scores[by_key], stable=True)[:k]]
        index = unpack_keys(keys[best])
        return TopK(index.cpu(), voxel_centres(index, self.voxel_size, self.lattice).cpu(),
                    scores[best].cpu())  # fmt: skip

    def _region_rows(self, box: Any, centre: Any, radius: float | None) -> Tensor:
        """Rows of the voxels whose centre lies in ``box`` or within ``radius`` of ``centre``."""
        if box is not None and (centre is not None or radius is not None):
            raise ValueError("region: give box= or centre= and radius=, not both")
        if box is not None:
            b = torch.as_tensor(box, dtype=torch.float64).reshape(-1)
            if b.numel() != 6 or not bool(torch.isfinite(b).all()) or bool((b[3:] < b[:3]).any()):
                raise ValueError(f"box={box!r}: expected [[x0, y0, z0], [x1, y1, z1]] with x0 "
                                 "<= x1 ... (metres)")  # fmt: skip
            lo, hi = b[:3], b[3:]
        else:
            c = torch.as_tensor(centre if centre is not None else [], dtype=torch.float64)
            r = float("nan") if radius is None else float(radius)
            if c.numel() != 3 or not bool(torch.isfinite(c).all()) or not (r >= 0) or math.isinf(r):
                raise ValueError(f"centre={centre!r}, radius={radius!r}: expected a point "
                                 "[x, y, z] and a finite radius >= 0 (metres)")  # fmt: skip
            lo, hi = c - r, c + r
        shift = 0.0 if self.lattice == "round" else 0.5
        first = torch.floor(lo / self.voxel_size - shift).to(torch.int64)
        last = torch.ceil(hi / self.voxel_size - shift).to(torch.int64)
        rows = self.voxels.rows_in_box(first, last)
        if not rows.numel():
            return rows
        at = voxel_centres(unpack_keys(self.voxels.keys[rows]), self.voxel_size, self.lattice)
        at = at.double()
        if box is not None:
            keep = ((at >= lo.to(at.device)) & (at <= hi.to(at.device))).all(dim=1)
        else:
            keep = (at - c.to(at.device)).norm(dim=1) <= r
        return rows[keep]

    def region(self, box: Any = None, centre: Any = None, radius: float | None = None) -> Tensor:
        """``[R, 3]`` int64 indices (lexicographic order) of the voxels whose centre lies in
        ``box`` (``[[x0, y0, z0], [x1, y1, z1]]`` metres, inclusive) or within ``radius`` of
        ``centre``. A region of at most four times as many cells as the map holds voxels is
        looked up cell by cell in the key index, without reading the map."""
        if self.voxels is None:
            return torch.empty(0, 3, dtype=torch.int64)
        rows = self._region_rows(box, centre, radius)
        return unpack_keys(torch.sort(self.voxels.keys[rows]).values).cpu()

    # ------------------------------------------------------------------ merging
    def merge_differences(self, other: SemanticMap) -> list[str]:
        """What keeps ``other`` from merging into this map: settings (but ``max_voxels``),
        the feature dimension, the basis (by SHA-256, not by where it was read from: a map
        fitted its own, the next run read it from that map's folder) and the encoder's weights
        (by the digest ``resireg-map`` and the live node record in
        ``meta["identity"]["weights"]``)."""

        def compared(smap: SemanticMap) -> dict[str, Any]:
            out = {k: v for k, v in smap.settings().items() if k != "max_voxels"}
            if out.get("compact") is not None:
                out["compact"] = {k: v for k, v in out["compact"].items() if k != "basis"}
            return out

        mine, theirs = compared(self), compared(other)
        out = [f"{k}: {mine.get(k)!r} here, {theirs.get(k)!r} in the other map"
               for k in sorted(set(mine) | set(theirs)) if mine.get(k) != theirs.get(k)]  # fmt: skip
        if self.dim is not None and other.dim is not None and self.dim != other.dim:
            out.append(f"dim: {self.dim} here, {other.dim} in the other map")
        if (self.basis_sha256 or other.basis_sha256) and self.basis_sha256 != other.basis_sha256:
            out.append(f"basis_sha256: {self.basis_sha256} here, {other.basis_sha256} in the "
                       "other map (map the second run with compact.basis=<the first map>)")  # fmt: skip
        a = (self.meta.get("identity") or {}).get("weights")
        b = (other.meta.get("identity") or {}).get("weights")
        if a is not None and b is not None and a != b:
            out.append(f"encoder weights: {a} here, {b} in the other map")
        return out

    @torch.no_grad()
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
        mine = set(self.parts)
        shared = next((p for p in other.parts if p in mine), None)
        if shared is not None:  # a map merged with one it is part of: its points count twice
            raise MapError(f"merge: the maps share the part {shared} (one holds the other's "
                           "frames: merged, they would count twice)")  # fmt: skip
        parts = [*self.parts, *other.parts]
        if len(parts) > MAX_PARTS:
            raise MapError(f"merge: the maps are made of {len(parts)} parts, more than "
                           f"{MAX_PARTS}")  # fmt: skip
        self.fit_pending()
        other.fit_pending()
        if self.voxels is None and other.voxels is not None and self.compact is not None:
            if self.basis is None and other.basis is not None:
                self.set_basis(other.basis)
        differ = self.merge_differences(other)
        if differ:
            raise MapError(f"merge: the maps differ ({len(differ)}): " + "; ".join(differ))
        if other.voxels is not None and len(other.voxels):
            if self.voxels is None:
                self._dim = other.dim
                self.voxels = self._make_voxels()
            keys = None if transform is None else transform_keys(
                other.voxels.keys, transform, self.voxel_size, self.lattice)  # fmt: skip
            self.voxels.merge_from(other.voxels, keys)
            if self.colours is not None and other.colours is not None and len(other.colours):
                keys = None if transform is None else transform_keys(
                    other.colours.keys, transform, self.voxel_size, self.lattice)  # fmt: skip
                self.colours.merge_from(other.colours, keys)
        self.frames += other.frames
        self.windows += other.windows
        self.parts = parts
        step = None if transform is None else torch.as_tensor(transform).double().tolist()
        self.meta.setdefault("merged", []).append(
            {"frames": other.frames, "voxels": len(other), "transform": step,
             "identity": (other.meta or {}).get("identity")})  # fmt: skip
        return self

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
            "colour": self.keeps_colour,
            "storage": self.storage,
            "compact": None if self.compact is None else self.compact.as_dict(),
        }

    def snapshot(self, copy: bool = True) -> MapSnapshot:
        """What :meth:`save` writes, taken now: with ``copy`` the map's tensors are copied
        (one copy of the map), so the snapshot is written while the map goes on changing
        (the live node copies under its lock and writes outside it)."""
        self.fit_pending()
        tensors: dict[str, list[Tensor]] = {}
        for prefix, vmap in (("features", self.voxels), ("colour", self.colours)):
            if vmap is not None:
                for name, blocks in vmap.tensors().items():
                    tensors[f"{prefix}.{name}"] = blocks
        if self.basis is not None:
            tensors["basis"] = [self.basis]
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
        SHA-256 of that tensor file, the basis's SHA-256, and ``record_sha256``, the digest of the record
        itself), each through :func:`resireg.integrity.atomic_write` (a temporary file, fsync,
        the umask's mode, ``os.replace``). ``map.json`` is the commit point: a crash before it
        leaves the previous save in force; older tensor files are removed after it, and a save
        that fails (a full disk) removes its own new tensor file and raises an ``OSError``
        naming the file it could not write. Returns ``folder``."""
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
        """A map saved by :meth:`save` (or by an earlier version: :data:`FORMATS`), with
        ``encoder`` for queries and further windows; ``folder``: the map folder or a run
        folder holding it in ``map/`` (:func:`map_folder`).

        Before any tensor is read, ``map.json``'s own digest and its tensor file's SHA-256 are
        verified: a truncated, edited or damaged file is an
        :class:`~resireg.integrity.IntegrityError` naming it, and so is a record that names a
        file outside ``folder``. Then every field of the record is checked (its type and
        range, the settings by their rules) and every size it gives against the tensors'
        shapes, before anything is allocated by it: a record edited with its digests
        recomputed is refused in one line naming the file and the field, and a load allocates
        no more than its file holds. A map saved before maps recorded their digests loads with
        a :class:`MapFormatWarning`. The tensors are memory-mapped (copy-on-write: the file
        never changes). An ``encoder`` whose text features have another dimension than the
        map's is refused here, not at the first query (the weights themselves are the
        caller's to check: ``resireg-map`` records a digest of them in ``meta``).
        ``overrides`` replace saved settings that do not change the content
        (``max_voxels``)."""
        folder = map_folder(folder)
        path = folder / MAP_JSON
        record = read_json(path, "saved map record")
        fmt = record.get("format") if isinstance(record, dict) else type(record).__name__
        if not isinstance(record, dict) or fmt not in FORMATS:
            raise IntegrityError(f"{path}: format {_shown(fmt)}, expected one of {list(FORMATS)}")
        tensor_file = _inside(folder, record.get("tensors"), "tensors", path)
        if "record_sha256" not in record and "sha256" not in record and fmt == FORMATS[0]:
            warnings.warn(
                f"{path}: a map saved before maps recorded their digests (format {fmt} without "
                "sha256): loaded unverified; save it again to record them",
                MapFormatWarning,
                stacklevel=2,
            )
        else:
            if "record_sha256" not in record or "sha256" not in record:
                raise IntegrityError(f"{path}: no record_sha256 / sha256 (an edited record): "
                                     "make the map again")  # fmt: skip
            if record["record_sha256"] != _record_digest(record):
                raise IntegrityError(
                    f"{path}: its content does not match the record_sha256 written with it (the "
                    "file was edited or damaged; a map's settings cannot change after it is made)"
                )
            if not isinstance(record["sha256"], dict):
                raise IntegrityError(f"{path}: sha256={_shown(record['sha256'])}: expected a "
                                     "mapping")  # fmt: skip
            for name in record["sha256"]:
                _inside(folder, name, "sha256", path)
            if tensor_file.name not in record["sha256"]:
                raise IntegrityError(f"{path}: records no SHA-256 of {tensor_file.name}")
            verify_digests(folder, record["sha256"], "saved map")
        # Every field is checked before anything is built from it: a record whose digests were
        # recomputed after an edit is refused here, naming the field, not deep in the code.
        names = set(parameters(cls)) - {"encoder", "prior", "prior_input", "device"}
        errors = _record_errors(record, sorted(names))
        if errors:
            raise IntegrityError(f"{path}: " + "; ".join(errors))
        bad = set(overrides) - {"max_voxels"}
        if bad:
            raise ValueError(f"load(): {sorted(bad)} cannot change on a saved map")
        errors = map_errors(overrides, keys=list(overrides))
        if errors:
            raise ValueError("load(): " + "; ".join(errors))
        settings = {**record["settings"], **overrides}
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
        compact = settings.get("compact")
        if compact is not None:  # the basis comes from the file, not from where it came from
            settings["compact"] = {**compact, "basis": None}
        try:
            smap = cls(encoder if encoder is not None else None, config, voxel_size,
                       params=params, prior=prior,
                       device=device or (encoder.device if encoder is not None else "cpu"),
                       **settings)  # fmt: skip
            if smap.compact is not None and compact is not None:
                smap.compact = CompactSettings.of(compact)
        except (TypeError, ValueError) as err:
            if encoder is not None and prior is None and takes_prior(config):
                raise  # the caller's: a +prior configuration loaded without prior=
            raise IntegrityError(f"{path}: settings: {err}") from err
        tensors = read_tensors(tensor_file, "saved map")
        try:
            smap._restore(record, tensors)
        except (KeyError, ValueError, RuntimeError) as err:
            raise IntegrityError(f"{tensor_file}: does not hold the map its record {path} "
                                 f"describes ({err})") from err  # fmt: skip
        smap.frames, smap.windows = record["frames"], record["windows"]
        smap.meta = dict(record.get("meta") or {})
        # A map saved before maps recorded their parts is one part: its tensor file's SHA-256.
        smap.parts = (
            list(record["parts"])
            if "parts" in record
            else [(record.get("sha256") or {}).get(tensor_file.name) or sha256_file(tensor_file)]
        )
        return smap

    def _restore(self, record: Mapping[str, Any], tensors: Mapping[str, Tensor]) -> None:
        """Fill a freshly built map from the tensors of its file (used in place)."""
        old = record["format"] == FORMATS[0]

        def part(prefix: str) -> dict[str, Tensor]:
            return {k.split(".", 1)[1]: v.to(self.device) for k, v in tensors.items()
                    if k.startswith(f"{prefix}.")}  # fmt: skip

        # The record's sizes are checked against the tensors before anything is allocated by
        # them (the file's tensors are mapped, not read: only what a size names is allocated).
        if record["dim"] is None:
            held = sorted(k for k in tensors if k.startswith("features.") or k == "basis")
            if record["voxels"] or held:
                raise ValueError(f"dim=null (no feature yet), but voxels={record['voxels']} "
                                 f"and tensors {held}")  # fmt: skip
        else:
            self._dim = record["dim"]
            if "basis" in tensors:
                basis = tensors["basis"]
                k = self.compact.dim if self.compact is not None else None
                if basis.ndim != 2 or tuple(basis.shape) != (self._dim, k):
                    raise ValueError(f"basis of shape {list(basis.shape)}: expected [dim="
                                     f"{self._dim}, settings.compact.dim={k}]")  # fmt: skip
                basis = basis.to(self.device, torch.float32)
                if _sha256(basis) != record.get("basis_sha256"):
                    raise ValueError("its basis does not match basis_sha256")
                self.basis, self.basis_sha256 = basis, record["basis_sha256"]
            elif record.get("basis_sha256"):
                raise ValueError("no basis")
            if record.get("stored_dim", self.stored_dim) != self.stored_dim:
                raise ValueError(f"stored_dim={record['stored_dim']}: the map's settings and "
                                 f"basis store {self.stored_dim}-d features")  # fmt: skip
            self.voxels = self._make_voxels()
            state = part("features")
            if old:
                self.voxels.load_state(state)
            elif isinstance(self.voxels, CompactVoxelMap):
                self.voxels.load_tensors(state)
            else:
                self.voxels.load_tensors(state)
            if len(self.voxels) != int(record["voxels"]):
                raise ValueError(f"{len(self.voxels)} voxels, the record says {record['voxels']}")
        if self.colours is not None:
            state = part("colour")
            if old:
                self.colours.load_state(state or self.colours.state())
            elif state:
                self.colours.load_tensors(state)

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
