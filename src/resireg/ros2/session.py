"""The live node's map session: the encoder, the map it builds in ``<output_dir>/map`` (a fresh
map or, with ``resume:=true``, the saved one: :func:`resireg.mapping.opening.open_map`, the
rule ``resireg-map`` follows, refusing a map of other settings, another source, encoder entry or
weights, naming what differs), the mapping thread that feeds it
(:class:`~resireg.ros2.pipeline.MapWorker`) and its saves (a copy taken under the map's lock,
written outside it, one save at a time). No rclpy.

Imported by :mod:`resireg.ros2.node`.
"""

from __future__ import annotations

import threading
from collections.abc import Callable, Mapping
from pathlib import Path
from typing import Any

from resireg.errors import ConfigError, ResiregError
from resireg.mapping.opening import map_identity, open_map
from resireg.ros2.pipeline import MapWorker
from resireg.ros2.settings import (
    SOURCE_KEYS,
    SettingsError,
    compact_settings,
    encoder_entry,
    variant_params,
)

__all__ = ["MapSession", "build_encoder"]


def build_encoder(values: Mapping[str, Any]) -> Any:
    """The encoder of the ``encoder`` / ``model_path`` parameters, on ``device``, with the
    ``seed``; a :class:`SettingsError` naming them when it cannot be built."""
    import torch

    from resireg.models import build_encoder as build
    from resireg.models.factory import resolve_device

    entry = encoder_entry(values)
    device = resolve_device(values["device"])
    torch.manual_seed(int(values["seed"]))
    try:
        return build(**entry, device=device)
    except (OSError, ValueError, TypeError) as err:
        raise SettingsError(f"encoder={values['encoder']!r} (model_path="
                            f"{values['model_path']!r}): {err}") from err  # fmt: skip


class MapSession:
    """The map of the node's checked parameters ``values`` (module docstring).

    Args:
        values: the checked parameters (:func:`resireg.ros2.settings.check`).
        encoder: a built dense encoder, or ``None`` to build the parameters' one.
        on_window: the mapping thread's callback after each window (:class:`MapWorker`).

    Attributes: ``encoder``, ``folder`` (where the map is saved), ``resumed`` (a saved map
    continued), ``worker`` (the mapping thread, not started; its ``smap`` is the map).
    Raises :class:`SettingsError` (one line) for a bad setting or a refused resume.
    """

    def __init__(self, values: Mapping[str, Any], encoder: Any = None,
                 on_window: Callable[[dict, dict], None] | None = None) -> None:  # fmt: skip
        self.values = values
        self.encoder = encoder if encoder is not None else build_encoder(values)
        from resireg.models.factory import weights_fingerprint

        fresh = self.new_map()
        entry = dict(encoder_entry(values)) if values["model_path"] else {}
        identity = map_identity(fresh, encoder=entry, window=values["window"],
                                source={k: values[f"source.{k}"] for k in SOURCE_KEYS},
                                weights=weights_fingerprint(self.encoder))  # fmt: skip
        try:
            opened = open_map(Path(values["output_dir"]).expanduser() / "map", fresh, identity,
                              resume=bool(values["resume"]), encoder=self.encoder,
                              resume_flag="-p resume:=true",
                              elsewhere="set another -p output_dir:=...")  # fmt: skip
        except ConfigError as err:
            raise SettingsError(str(err)) from err
        self.folder, self.resumed = opened.folder, opened.resumed
        self.worker = MapWorker(opened.map, self.new_map, values["window"],
                                values["queue_size"], values["window_timeout"],
                                values["source.max_depth"], on_window)  # fmt: skip
        self._save_lock = threading.Lock()  # one write of the map folder at a time

    def new_map(self) -> Any:
        """An empty map of the parameters (as ``resireg-map``'s job makes its map)."""
        from resireg.mapping import SemanticMap

        v = self.values
        try:
            return SemanticMap(self.encoder, v["variant"], float(v["voxel_size"]),
                               params=variant_params(v), points=v["points"],
                               lattice=v["lattice"], sum_dtype=v["sum_dtype"],
                               max_voxels=v["max_voxels"], short_side=v["short_side"],
                               storage=v["storage"], compact=compact_settings(v))  # fmt: skip
        except (ValueError, OSError, ResiregError) as err:
            raise SettingsError(str(err)) from err

    def save(self) -> Path:
        """Save the map to :attr:`folder`: a copy of it taken under the map's lock
        (:meth:`SemanticMap.snapshot`), written outside it, one save at a time."""
        with self._save_lock:
            with self.worker.lock:
                self.worker.smap.meta["kept_frames"] = self.worker.smap.frames
                snapshot = self.worker.smap.snapshot(copy=True)
            return snapshot.write(self.folder)
