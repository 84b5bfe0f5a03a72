"""A live 3D view of a mapping run with Rerun (``rerun-sdk``, the ``robot`` extra, imported when a
view is made; docs/maps.md#robot-maps-semanticmap): ``resireg-map``'s recording and ``resireg-ros2``'s
live stream log the same entities.

Entities (world frame, metres; Rerun's ``Pinhole`` takes OpenCV camera axes, RDF, by default)::

    world/camera            Transform3D: the frame's camera-to-world pose
    world/camera/image      Pinhole (the depth image's K) + Image (colour)
    world/camera/depth      DepthImage (metres)
    world/trajectory        LineStrips3D: the camera centres so far
    world/map/rgb           Points3D: voxel centres, mean colour
    world/map/pca           Points3D: coloured by the PCA of the features
    world/map/query         Points3D: coloured by the similarity to ``query`` (blue..red)

on the ``frame`` timeline (the kept frame's position). ``save`` writes a ``.rrd`` file (open it
with ``rerun map.rrd``; read it back with ``rerun.chunk.RrdReader``); ``spawn`` starts a viewer;
``connect`` streams to a running viewer's gRPC URL (``rr.connect_grpc``); ``serve`` serves the
stream over gRPC (``rr.serve_grpc``, port 9876: ``rerun --connect
rerun+http://<host>:9876/proxy``). Any of them together.
"""

from __future__ import annotations

from pathlib import Path
from typing import Any

import numpy as np

__all__ = ["RerunView"]


class RerunView:
    """Logs windows and maps to one Rerun recording (module docstring).

    Args:
        save: ``.rrd`` path or ``None``.
        spawn: open a viewer.
        query: a text whose similarity colours ``world/map/query``.
        connect: a running viewer's gRPC URL (``rerun+http://host:9876/proxy``) or ``None``.
        serve: serve the stream over gRPC (``rr.serve_grpc``); :attr:`url` is its address.
        application: the recording's application id.
    """

    def __init__(self, save: str | Path | None, spawn: bool = False, query: str | None = None,
                 connect: str | None = None, serve: bool = False,
                 application: str = "resireg-map") -> None:  # fmt: skip
        import rerun as rr

        self.rr = rr
        self.rec = rr.RecordingStream(application)
        self.url: str | None = None
        if save:
            Path(save).parent.mkdir(parents=True, exist_ok=True)
        if save and not (spawn or connect or serve):
            self.rec.save(str(save))
        elif spawn and not (save or connect or serve):
            self.rec.spawn()
        elif save or spawn or connect or serve:  # several sinks: a spawned viewer is connected to
            if spawn:
                self.rec.spawn(connect=False)
            sinks = [rr.FileSink(str(save))] if save else []
            sinks += [rr.GrpcSink()] if spawn else []
            sinks += [rr.GrpcSink(connect)] if connect else []
            sinks += [rr.GrpcServerSink()] if serve else []
            self.rec.set_sinks(*sinks)
        if serve:
            self.url = "rerun+http://127.0.0.1:9876/proxy"
        self.query = query
        self.centres: list[np.ndarray] = []

    def log_window(self, window: dict[str, Any], start: int) -> None:
        """Colour, depth, pose and the camera path of each frame of a window (``start``: the
        first frame's position on the ``frame`` timeline)."""
        rr, rec = self.rr, self.rec
        for i in range(len(window["name"])):
            rec.set_time("frame", sequence=start + i)
            pose = window["pose"][i].numpy()
            depth = window["depth"][i].numpy()
            rec.log("world/camera", rr.Transform3D(translation=pose[:3, 3], mat3x3=pose[:3, :3]))
            rec.log("world/camera/image", rr.Pinhole(
                image_from_camera=window["intrinsics"][i].numpy(),
                resolution=[depth.shape[1], depth.shape[0]]))  # fmt: skip
            rec.log("world/camera/image", rr.Image(window["image"][i].permute(1, 2, 0).numpy()))
            rec.log("world/camera/depth", rr.DepthImage(depth, meter=1.0))
            self.centres.append(pose[:3, 3].copy())
            rec.log("world/trajectory", rr.LineStrips3D([np.stack(self.centres)]))

    def log_map(self, smap: Any) -> None:
        """The map's voxel centres, coloured by mean colour (if kept), PCA and the query."""
        rr, rec = self.rr, self.rec
        if not len(smap):
            return
        centres = smap.centres().cpu().numpy()
        if smap.colours is not None:
            rec.log("world/map/rgb", rr.Points3D(centres, colors=smap.mean_colours().numpy(),
                                                 radii=smap.voxel_size / 2))  # fmt: skip
        rec.log("world/map/pca", rr.Points3D(centres, colors=smap.colours_by("pca").numpy(),
                                             radii=smap.voxel_size / 2))  # fmt: skip
        if self.query:
            colours = smap.colours_by("query", text=self.query).numpy()
            rec.log("world/map/query", rr.Points3D(centres, colors=colours,
                                                   radii=smap.voxel_size / 2))  # fmt: skip

    def close(self) -> None:
        self.rec.flush()
        self.rec.disconnect()
