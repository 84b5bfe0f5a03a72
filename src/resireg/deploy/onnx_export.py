"""ONNX graphs of the 25M VLM for onnxruntime and TensorRT (``resireg-export onnx``).

Two graphs, exported with PyTorch's dynamo exporter (``torch.onnx.export(..., dynamo=True)``)
and checked with ``onnx.checker``:

- the **image graph** (:class:`ImageGraph`): normalised images ``images [B, 3, H, W]`` ->
  ``intermediates [B, Dv, H/p, W/p]`` (ReSiReg's intermediates), ``language [B, Dl, H/p, W/p]``
  (the head's dense language tokens), ``embedding [B, 2 Dl]`` and, with ``lite``,
  ``lite [B, Dl, s H/p, s W/p]``: ReSiReg Lite's reconstructed unit features in the same graph;
- the **text graph** (:class:`TextGraph`): token ids ``tokens [K, context]`` (int64, from the
  model's tokenizer, which stays in Python) -> ``text [K, Dl]``, the normalised dense text
  queries of :meth:`ResiregVLM.encode_text`; float32 also with ``fp16`` (it runs once per
  vocabulary).

ReSiReg Lite exports in either exact form (``attention``): ``sdpa`` (one
``scaled_dot_product_attention`` over the upsampled points; TensorRT fuses it, onnxruntime's CPU
provider runs it as ``MatMul -> Softmax -> MatMul`` with ``4 N^2 W`` FLOP per image) or
``factorised`` (:meth:`ReSiRegLite._factorised_graph`: the coarse Gram matrix, bilinearly
upsampled on both sides by ``Resize``, exponentiated and summed per language token, about 6.7x
fewer FLOP at the protocol's size; the faster graph on onnxruntime's CPU provider,
docs/benchmarks.md). Both keep ``B N^2`` elements in memory at once on onnxruntime's CPU
provider. ReSiReg Full stays in torch: its
k-means is data-dependent (iterations until convergence); run it on the image graph's
``intermediates`` and ``language`` (docs/deployment.md).

A manifest ``<out>.json`` beside the graphs records what a runtime needs to feed them: the
input size (or that it is dynamic), the normalisation (mean, std), the patch size, the output
names, Lite's parameters, the text tower (tokenizer) spec, the operator sets and the graphs'
SHA-256.
"""

from __future__ import annotations

import copy
import json
import os
import shutil
import time
import uuid
from dataclasses import dataclass, field
from pathlib import Path
from typing import Any

import torch
from torch import Tensor, nn

from resireg.deploy.runtime import GRAPH_FORMAT, manifest_path, open_graph, text_graph_path
from resireg.errors import ConfigError
from resireg.integrity import atomic_write, digests
from resireg.method.lite import ReSiRegLite
from resireg.models.vlm.model import ResiregVLM
from resireg.models.vlm.text import dense_text_half

__all__ = [
    "IMAGE_OUTPUTS",
    "ImageGraph",
    "OnnxExport",
    "TextGraph",
    "check_graph",
    "check_outputs",
    "export_onnx",
    "run_graph",
    "text_graph_path",
    "validate",
]

#: The image graph's outputs, in order (``lite`` only with ``lite=True``).
IMAGE_OUTPUTS: tuple[str, ...] = ("intermediates", "language", "embedding")

#: The largest batch and patch grid side a dynamic graph declares (TensorRT optimisation
#: profiles take their own min/opt/max shapes within these).
_MAX_BATCH = 1024
_MAX_GRID = 512


class ImageGraph(nn.Module):
    """The VLM's image path as one module: ``images -> (intermediates, language, embedding[,
    lite])`` (:meth:`ResiregVLM.encode`, then :class:`~resireg.method.lite.ReSiRegLite`)."""

    def __init__(self, model: ResiregVLM, lite: ReSiRegLite | None = None) -> None:
        super().__init__()
        self.model = model
        self.lite = lite

    @property
    def output_names(self) -> list[str]:
        return [*IMAGE_OUTPUTS, *(["lite"] if self.lite is not None else [])]

    def forward(self, images: Tensor) -> tuple[Tensor, ...]:
        out = self.model.encode(images)
        outs = (out.intermediates, out.language, out.embedding)
        if self.lite is not None:
            outs += (self.lite(out.intermediates, out.language),)
        return outs


class TextGraph(nn.Module):
    """The VLM's text path: token ids ``[K, context]`` -> unit dense queries ``[K, Dl]`` (the
    frozen tower, the trained projection, the normalised dense half: :meth:`ResiregVLM.encode_text`
    after tokenisation)."""

    def __init__(self, model: ResiregVLM) -> None:
        super().__init__()
        self.tower = model.text.tower
        self.proj = model.text_proj

    def forward(self, tokens: Tensor) -> Tensor:
        features = self.tower(tokens)
        return dense_text_half(self.proj(features.to(self.proj.weight.dtype)))


@dataclass
class OnnxExport:
    """What :func:`export_onnx` wrote.

    Attributes:
        image: the image graph (``--out``).
        text: the text graph (``<stem>.text.onnx``).
        manifest: ``<out>.json`` (see the module docstring).
        opsets: ``{domain: version}`` of the image graph (``""`` = the ONNX standard ops).
        seconds: ``{"image": s, "text": s}`` export wall time.
    """

    image: Path
    text: Path
    manifest: Path
    opsets: dict[str, int] = field(default_factory=dict)
    seconds: dict[str, float] = field(default_factory=dict)


def check_outputs(out: str | os.PathLike, text: bool = True, name: str = "out") -> Path:
    """Check before an export starts that its files can be written: the image graph ``out``,
    the text graph (:func:`~resireg.deploy.runtime.text_graph_path`, with ``text``) and the
    manifest (``<out>.json``) are not folders, and the nearest existing folder above ``out``
    is a folder (not a regular file) this process can write. Returns that folder (where
    :func:`export_onnx` stages the files). A :class:`~resireg.errors.ConfigError` names
    ``name`` (the argument: ``--out`` on the command line), the value and the path at fault."""
    out = Path(out)
    where = f"{name}={os.fspath(out)!r}"
    if not out.name or out.name in (".", ".."):
        raise ConfigError(f"{where}: expected a file path, e.g. model.onnx")
    for path, role in ((out, "the image graph"), (manifest_path(out), "the manifest"),
                       *([(text_graph_path(out), "the text graph")] if text else [])):  # fmt: skip
        if path.is_dir():
            raise ConfigError(f"{where}: {role}'s path {path} is a folder")
    folder = out.parent
    while not folder.exists() and folder != folder.parent:
        folder = folder.parent
    if not folder.is_dir():
        raise ConfigError(f"{where}: {folder} is a regular file, not a folder")
    if not os.access(folder, os.W_OK | os.X_OK):
        raise ConfigError(f"{where}: the folder {folder} cannot be written by this user")
    return folder


def check_graph(path: str | os.PathLike) -> dict[str, int]:
    """``onnx.checker.check_model`` (with shape inference: ``full_check``) of a saved graph;
    returns its operator sets ``{domain: version}``."""
    import onnx

    onnx.checker.check_model(os.fspath(path), full_check=True)
    model = onnx.load(os.fspath(path), load_external_data=False)
    return {op.domain: int(op.version) for op in model.opset_import}


def _lite_module(attention: str, lite_kwargs: dict[str, Any] | None) -> ReSiRegLite:
    if attention not in ("auto", "sdpa", "factorised"):
        raise ValueError(
            f"attention={attention!r}: expected 'sdpa' (or 'auto', the same here) or 'factorised'"
        )
    form = "factorised" if attention == "factorised" else "sdpa"
    return ReSiRegLite(**{**(lite_kwargs or {}), "attention": form})


def _save(program: Any, path: Path) -> None:
    """An ``ONNXProgram`` written atomically with the umask's mode (one file: the weights
    inline, as the 25M model's ~100 MB are far below protobuf's 2 GB)."""
    atomic_write(path, lambda tmp: program.save(os.fspath(tmp)))


def export_onnx(
    model: ResiregVLM,
    out: str | os.PathLike,
    *,
    lite: bool = False,
    attention: str = "sdpa",
    lite_kwargs: dict[str, Any] | None = None,
    fp16: bool = False,
    height: int | None = None,
    width: int | None = None,
    batch: int = 1,
    dynamic: bool = False,
    text: bool = True,
) -> OnnxExport:
    """Export ``model``'s image graph to ``out`` and its text graph beside it.

    Args:
        model: a :class:`ResiregVLM` (e.g. ``ResiregVLM.from_pretrained(export)``).
        out: the image graph's path (``model.onnx``); the text graph is
            :func:`text_graph_path` of it and the manifest ``<out>.json``.
        lite: add ReSiReg Lite's reconstructed features (output ``lite``).
        attention: Lite's computation: ``"sdpa"`` (``"auto"`` means the same here) or
            ``"factorised"`` (the same function; faster on onnxruntime's CPU provider).
        lite_kwargs: Lite's ``alpha``, ``tau``, ``upscale`` (default: the class's, which
            equal ``conf/resireg/default.yaml``).
        fp16: export the image graph in float16 (inputs and outputs too); float32
            otherwise. The text graph is float32 either way (see the comment below).
        height, width: the fixed input size (multiples of the patch size); default the
            protocol's 576 x 768. Not with ``dynamic``.
        batch: the fixed batch size (not with ``dynamic``).
        dynamic: batch, height and width dynamic (height and width multiples of the patch
            size; ``[1, 1024]`` images, ``[1, 512]`` patches a side).
        text: export the text graph too.
    """
    if not isinstance(model, ResiregVLM):
        raise TypeError(f"model must be a ResiregVLM, got {type(model).__name__}")
    patch = model.input_rule.patch_size
    if dynamic and (height is not None or width is not None):
        raise ValueError("--dynamic takes no --height/--width (the graph takes any size)")
    if isinstance(batch, bool) or not isinstance(batch, int) or batch < 1:
        raise ValueError(f"batch={batch!r}: expected an integer >= 1")
    height = 576 if height is None else height
    width = 768 if width is None else width
    for name, side in (("height", height), ("width", width)):
        if isinstance(side, bool) or not isinstance(side, int) or side < patch or side % patch:
            raise ValueError(
                f"{name}={side!r}: expected a positive multiple of the patch size {patch}"
            )
    lite_module = _lite_module(attention, lite_kwargs) if lite else None
    out = Path(out)
    existing = check_outputs(out, text)
    # the files are written into a staging folder beside them and moved to ``out`` at the
    # end: the graphs and their manifest appear together or not at all
    stage = existing / f".{out.name}.{uuid.uuid4().hex[:8]}.tmp"
    stage.mkdir()
    try:
        staged = _export(model, stage / out.name, lite_module, fp16, height, width, batch, dynamic,
                         text)  # fmt: skip
        out.parent.mkdir(parents=True, exist_ok=True)
        result = OnnxExport(image=out, text=text_graph_path(out), manifest=manifest_path(out),
                            opsets=staged.opsets, seconds=staged.seconds)  # fmt: skip
        moves = [(staged.image, result.image), (staged.manifest, result.manifest)]
        if text:
            moves.insert(0, (staged.text, result.text))
        for src, dest in moves:  # the manifest last: a reader finds it with its graphs
            os.replace(src, dest)
    finally:
        shutil.rmtree(stage, ignore_errors=True)
    return result


def _export(
    model: ResiregVLM,
    out: Path,
    lite_module: ReSiRegLite | None,
    fp16: bool,
    height: int,
    width: int,
    batch: int,
    dynamic: bool,
    text: bool,
) -> OnnxExport:
    """:func:`export_onnx`'s work, its arguments checked, into ``out``'s folder (staging)."""
    patch = model.input_rule.patch_size
    dtype = torch.float16 if fp16 else torch.float32
    # copies, so the caller's model keeps its dtype and device
    net32 = copy.deepcopy(model).to("cpu", torch.float32).eval()
    net = copy.deepcopy(net32).half() if fp16 else net32
    result = OnnxExport(image=out, text=text_graph_path(out), manifest=manifest_path(out))

    graph = ImageGraph(net, lite_module).eval()
    if dynamic:
        from torch.export import Dim

        gh = Dim("grid_h", min=1, max=_MAX_GRID)
        gw = Dim("grid_w", min=1, max=_MAX_GRID)
        shapes = {"images": {0: Dim("batch", min=1, max=_MAX_BATCH), 2: patch * gh, 3: patch * gw}}
        example = torch.randn(2, 3, 4 * patch, 6 * patch, dtype=dtype)  # no 0/1 specialisation
    else:
        shapes = None
        example = torch.randn(batch, 3, height, width, dtype=dtype)
    start = time.perf_counter()
    with torch.no_grad():
        program = torch.onnx.export(
            graph, (example,), input_names=["images"], output_names=graph.output_names,
            dynamic_shapes=shapes, dynamo=True, verbose=False,
        )  # fmt: skip
    _save(program, result.image)
    result.seconds["image"] = time.perf_counter() - start
    result.opsets = check_graph(result.image)

    files = [result.image.name]
    if text:
        from torch.export import Dim

        # float32 always: it runs once per vocabulary, and onnxruntime's CPU provider
        # (1.31) crashes creating a session of the float16 text tower at its default
        # optimisation level (ORT_ENABLE_ALL; BASIC and EXTENDED run it)
        tg = TextGraph(net32).eval()
        tokens = net32.text.tokenizer(["a photo of a chair.", "floor"]).long()
        start = time.perf_counter()
        with torch.no_grad():
            program = torch.onnx.export(
                tg, (tokens,), input_names=["tokens"], output_names=["text"],
                dynamic_shapes={"tokens": {0: Dim("queries", min=1, max=1 << 16)}}, dynamo=True,
                verbose=False,
            )  # fmt: skip
        _save(program, result.text)
        result.seconds["text"] = time.perf_counter() - start
        check_graph(result.text)
        files.append(result.text.name)

    rule = model.input_rule
    manifest = {
        "format": GRAPH_FORMAT,
        "version": 1,
        "dtype": "float16" if fp16 else "float32",
        "image": {
            "file": result.image.name,
            "input": "images",
            "shape": ["batch", 3, f"{patch}*grid_h", f"{patch}*grid_w"]
            if dynamic
            else [batch, 3, height, width],
            "dynamic": dynamic,
            "outputs": graph.output_names,
            "patch_size": patch,
            "mean": list(rule.mean),
            "std": list(rule.std),
        },
        "lite": None
        if lite_module is None
        else {
            "alpha": lite_module.alpha,
            "tau": lite_module.tau,
            "upscale": lite_module.upscale,
            "attention": lite_module.attention,
        },  # fmt: skip
        "text": None
        if not text
        else {
            "file": result.text.name,
            "input": "tokens",
            "output": "text",
            "dtype": "float32",
            "context_length": int(tokens.shape[1]),
            "tower": model.text.spec(),
        },  # fmt: skip
        "opsets": result.opsets,
        "source": model.export_source,
        "digests": digests(out.parent, files),
    }
    text_json = json.dumps(manifest, indent=2)
    atomic_write(result.manifest, lambda tmp: tmp.write_text(text_json))
    return result


def run_graph(path: str | os.PathLike, feeds: dict[str, Any], threads: int | None = None) -> dict:
    """Run a saved graph, verified against its manifest
    (:func:`~resireg.deploy.runtime.open_graph`), with onnxruntime's CPU execution provider:
    ``{output name: array}``."""
    session = open_graph(path, threads=threads)
    names = [o.name for o in session.get_outputs()]
    arrays = {k: (v.numpy() if isinstance(v, Tensor) else v) for k, v in feeds.items()}
    return dict(zip(names, session.run(names, arrays), strict=True))


def validate(result: OnnxExport, model: ResiregVLM, seed: int = 0) -> dict[str, dict[str, float]]:
    """Run the exported graphs with onnxruntime (CPU) and ``model`` in float32 torch on the
    same random inputs (the manifest's fixed size, or batch 2 at 4 x 6 patches for a dynamic
    graph; two text queries): per output, the largest absolute difference and the smallest
    cosine of the unit features (normalised over channels), for ``resireg-export``'s report."""
    import torch.nn.functional as F

    manifest = json.loads(result.manifest.read_text())
    image = manifest["image"]
    patch = image["patch_size"]
    shape = [2, 3, 4 * patch, 6 * patch] if image["dynamic"] else image["shape"]
    dtype = torch.float16 if manifest["dtype"] == "float16" else torch.float32
    gen = torch.Generator().manual_seed(seed)
    images = torch.randn(*shape, generator=gen).to(dtype)
    lite = None
    if manifest["lite"] is not None:
        lite = ReSiRegLite(**{k: v for k, v in manifest["lite"].items()})
    net = copy.deepcopy(model).to("cpu", torch.float32).eval()
    with torch.no_grad():
        reference = dict(zip(image["outputs"], ImageGraph(net, lite)(images.float()), strict=True))
    got = run_graph(result.image, {"images": images})
    if manifest["text"] is not None:
        texts = ["a photo of a chair.", "floor"]
        reference["text"] = net.encode_text(texts)
        got.update(run_graph(result.text, {"tokens": net.text.tokenizer(texts).long()}))
    report = {}
    for name, ref in reference.items():
        a = F.normalize(ref.float(), dim=1)
        b = F.normalize(torch.from_numpy(got[name]).float(), dim=1)
        report[name] = {
            "max_abs_diff": float((a - b).abs().max()),
            "min_cosine": float((a * b).sum(1).min()),
        }
    return report
