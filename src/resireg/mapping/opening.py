"""Opening the map a mapping run builds: a fresh one, or the saved one it resumes.

One rule for ``resireg-map`` (:mod:`resireg_train.jobs.map`) and the live node
(:mod:`resireg.ros2.session`). A map records its *identity* in ``meta["identity"]``
(:func:`map_identity`): the map's settings (:meth:`SemanticMap.settings`: the variant and its
parameters, the voxel size, points, lattice, sums, short side, colour, storage and the
``compact`` block; not ``max_voxels``, which a resumed map may raise), the encoder's entry (its
``path`` resolved), a digest of its weights (:func:`resireg.models.factory.weights_fingerprint`:
another model at the same path differs), the source (its ``path`` resolved; without its stop
rules, ``limit`` and ``idle``: a run cut short by them resumes without them), the window and
the prior. :func:`open_map` resumes a saved map only when every field of the identity to build
equals the saved one, and refuses otherwise in one line naming each field that differs, the
saved value and today's (:func:`identity_differences`). The saved side of the map's settings is
read from the map's own record (``map.json``, digest-checked), not from its ``meta``; a field a
map saved by an earlier release does not record (the node recorded no window) is not compared.
"""

from __future__ import annotations

from collections.abc import Mapping
from pathlib import Path
from typing import Any, NamedTuple

from resireg.errors import ConfigError
from resireg.mapping import SemanticMap, map_folder
from resireg.specs.tree import MISSING, differences

__all__ = ["FREE_SETTINGS", "STOP_RULES", "OpenedMap", "identity_differences", "local_path",
           "map_identity", "open_map"]  # fmt: skip

#: Settings a resumed map may change (they bound the map, they do not change its content).
FREE_SETTINGS = ("max_voxels",)
#: A source's stop rules: a run they cut short resumes without them.
STOP_RULES = ("limit", "idle")


class OpenedMap(NamedTuple):
    """What :func:`open_map` returns: the map, the folder it is saved to, and whether it is a
    saved map resumed."""

    map: SemanticMap
    folder: Path
    resumed: bool


def local_path(value: Any) -> Any:
    """A local path as its absolute, resolved form; anything else (a Hugging Face repo id, a
    name, ``None``) as it is."""
    if isinstance(value, str) and value and Path(value).expanduser().exists():
        return str(Path(value).expanduser().resolve())
    return value


def map_identity(
    smap: SemanticMap,
    *,
    encoder: Mapping[str, Any],
    source: Mapping[str, Any],
    window: int | None,
    prior: Any = None,
    weights: str | None = None,
) -> dict[str, Any]:
    """The identity of the map ``smap`` (a fresh map of today's settings) fed by ``source``
    through ``encoder`` (its entry: ``build_encoder``'s keywords) in windows of ``window``
    frames with ``prior`` (its config block or ``None``); ``weights``: the encoder's weights'
    digest, ``None`` before the encoder is built (the field is then left out). Module
    docstring."""
    out: dict[str, Any] = {
        "source": {k: local_path(v) if k == "path" else v for k, v in source.items()
                   if k not in STOP_RULES},  # fmt: skip
        "encoder": {k: local_path(v) if k == "path" else v for k, v in encoder.items()},
        "window": window,
        "prior": prior,
        **{k: v for k, v in smap.settings().items() if k not in FREE_SETTINGS},
    }
    if weights is not None:
        out["weights"] = weights
    return out


def identity_differences(saved: SemanticMap, identity: Mapping[str, Any]) -> list[str]:
    """``key: <saved> in the map, <now> now`` for each field of ``identity`` (today's,
    :func:`map_identity`) that differs from the saved map's, the shallowest keys first: the
    map's settings as its record gives them, the other fields as its ``meta["identity"]``
    records them (a field it does not record is not compared; a key inside a recorded field
    that one side lacks is shown as ``(not recorded)``)."""
    recorded = (saved.meta or {}).get("identity") or {}
    settings = {k: v for k, v in saved.settings().items() if k not in FREE_SETTINGS}
    was = {k: recorded[k] for k in identity if k in recorded and k not in settings}
    was.update(settings)
    now = {k: v for k, v in identity.items() if k in was}
    shown = {id(MISSING): "(not recorded)"}
    return [f"{key}: {shown.get(id(a), repr(a))} in the map, {shown.get(id(b), repr(b))} now"
            for key, a, b in differences(was, now)]  # fmt: skip


def open_map(
    folder: str | Path,
    fresh: SemanticMap,
    identity: Mapping[str, Any],
    *,
    resume: bool,
    encoder: Any,
    prior: Any = None,
    resume_flag: str = "resume=true",
    elsewhere: str = "use a new run folder",
) -> OpenedMap:
    """The map a run builds in ``folder`` (a map folder, or a run folder holding one in
    ``map/``: :func:`~resireg.mapping.map_file.map_folder`'s rule).

    No saved map there: ``fresh`` (an empty map of today's settings) with ``identity`` and no
    frame kept in its ``meta``. A saved map and ``resume``: the saved map, loaded with
    ``encoder`` and ``prior`` and today's ``max_voxels``, its recorded identity replaced by
    ``identity``, when nothing differs (:func:`identity_differences`); else a
    :class:`~resireg.errors.ConfigError` of one line naming each difference. A saved map
    without ``resume``: a ``ConfigError`` (a map is never overwritten). ``resume_flag`` and
    ``elsewhere`` word the refusals as the caller's users type them (``resume=true``,
    ``-p resume:=true``)."""
    try:
        saved = map_folder(folder)
    except FileNotFoundError:
        fresh.meta = {"identity": dict(identity), "kept_frames": 0}
        return OpenedMap(fresh, Path(folder).expanduser(), False)
    if not resume:
        raise ConfigError(f"{saved} holds a map: {resume_flag} continues it, or {elsewhere}")
    smap = SemanticMap.load(saved, encoder, prior, max_voxels=fresh.settings()["max_voxels"])
    differ = identity_differences(smap, identity)
    if differ:
        flag = resume_flag.removeprefix("-p ")
        raise ConfigError(f"{flag}: {saved} was made with other settings ({len(differ)} "
                          "differ): " + "; ".join(differ) + ". Resume with the map's values, or "
                          f"{elsewhere}")  # fmt: skip
    smap.meta = {**smap.meta, "identity": dict(identity)}
    return OpenedMap(smap, saved, True)
