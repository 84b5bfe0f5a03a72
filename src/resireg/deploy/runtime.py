"""Open an exported ONNX graph for inference, verified first: :func:`open_graph`.

``resireg-export onnx`` writes the image graph ``model.onnx``, the text graph
``model.text.onnx`` and the manifest ``model.onnx.json``, which records each graph's file name
and SHA-256 (:mod:`resireg.deploy.onnx_export`). :func:`open_graph` reads the graph's bytes
once, checks their SHA-256 against the manifest and gives onnxruntime those same bytes, so the
graph that runs is the one that was checked (no window between the check and the load). A
damaged graph, one swapped for another (the text graph copied over the image graph, a graph of
another export), a graph without its manifest and a manifest that names a file outside its
folder are each an :class:`~resireg.integrity.IntegrityError` naming the file.

Only onnxruntime and the standard library are imported (no torch), so a robot's runtime can
use it on its own.
"""

from __future__ import annotations

import hashlib
import os
from collections.abc import Sequence
from pathlib import Path
from typing import Any

from resireg.integrity import IntegrityError, read_json, resolve_inside

__all__ = ["GRAPH_FORMAT", "find_manifest", "manifest_path", "open_graph", "text_graph_path"]

#: The manifest's ``format``.
GRAPH_FORMAT = "resireg-vlm-onnx"
_WHAT = "ONNX manifest"


def manifest_path(image: str | os.PathLike) -> Path:
    """The manifest of an image graph ``model.onnx``: ``model.onnx.json``."""
    return Path(f"{os.fspath(image)}.json")


def text_graph_path(image: str | os.PathLike) -> Path:
    """Where the text graph of an image graph ``model.onnx`` goes: ``model.text.onnx``."""
    image = Path(image)
    return image.with_name(f"{image.stem}.text{image.suffix or '.onnx'}")


def find_manifest(graph: str | os.PathLike) -> tuple[Path, str]:
    """``(manifest, role)`` of a graph file: ``<graph>.json`` when it exists (the graph is an
    image graph, ``role`` ``"image"``), else the manifest of the image graph whose text graph
    (:func:`text_graph_path`) it is (``role`` ``"text"``). An :class:`IntegrityError` when
    there is none."""
    graph = Path(graph)
    own = manifest_path(graph)
    if own.is_file():
        return own, "image"
    stem = Path(graph.stem)
    if stem.suffix == ".text":  # model.text.onnx: the text graph of model.onnx (or of model)
        for image in (graph.with_name(f"{stem.stem}{graph.suffix}"), graph.with_name(stem.stem)):
            if text_graph_path(image) == graph and manifest_path(image).is_file():
                return manifest_path(image), "text"
    raise IntegrityError(
        f"{graph}: no manifest beside it ({own.name}, or its image graph's for a text graph); "
        "open_graph verifies a graph against the manifest resireg-export onnx writes"
    )


def _recorded_digest(graph: Path, manifest: Path, role: str) -> str:
    """The SHA-256 that ``manifest`` records for ``graph`` in the role ``role``."""
    record = read_json(manifest, _WHAT)
    if not isinstance(record, dict) or record.get("format") != GRAPH_FORMAT:
        found = record.get("format") if isinstance(record, dict) else type(record).__name__
        raise IntegrityError(f"{manifest}: not a {GRAPH_FORMAT} manifest (format={found!r})")
    entry = record.get(role)
    if not isinstance(entry, dict):
        raise IntegrityError(f"{manifest}: records no {role} graph, so {graph} is not its graph")
    named = resolve_inside(manifest.parent, entry.get("file"), f"{manifest}: {role}.file")
    if named.name != graph.name:  # a manifest for another file
        raise IntegrityError(
            f"{graph}: the manifest {manifest} is for the {role} graph {named.name!r}, not this file"
        )
    recorded = record.get("digests")
    if not isinstance(recorded, dict) or not isinstance(recorded.get(graph.name), str):
        raise IntegrityError(f"{manifest}: digests records no SHA-256 of {graph.name}")
    return recorded[graph.name]


def open_graph(
    path: str | os.PathLike,
    *,
    threads: int | None = None,
    providers: Sequence[Any] = ("CPUExecutionProvider",),
    options: Any = None,
) -> Any:
    """An ``onnxruntime.InferenceSession`` of an exported image or text graph, after checking
    the graph's SHA-256 against its manifest (:func:`find_manifest`).

    Args:
        path: the image graph (``model.onnx``) or the text graph (``model.text.onnx``).
        threads: onnxruntime's intra-op threads (default: onnxruntime's own choice).
        providers: the execution providers, in order (default the CPU's; e.g.
            ``["CUDAExecutionProvider", "CPUExecutionProvider"]``).
        options: an ``onnxruntime.SessionOptions`` (``threads`` is set on it).

    Raises:
        IntegrityError: the graph differs from what its manifest records (damaged, swapped),
            or it has no manifest; the message names the file.
    """
    import onnxruntime as ort

    path = Path(path)
    if not path.is_file():
        raise FileNotFoundError(f"{path}: no such graph file")
    manifest, role = find_manifest(path)
    expected = _recorded_digest(path, manifest, role)
    data = path.read_bytes()  # once: the bytes checked are the bytes loaded
    actual = hashlib.sha256(data).hexdigest()
    if actual != expected:
        raise IntegrityError(
            f"{path}: SHA-256 {actual[:16]}... does not match the {expected[:16]}... that "
            f"{manifest.name} records for its {role} graph (the file was changed, damaged or "
            "swapped)"
        )
    options = options if options is not None else ort.SessionOptions()
    if threads is not None:
        options.intra_op_num_threads = threads
    return ort.InferenceSession(data, options, providers=list(providers))
