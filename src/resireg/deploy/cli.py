"""``resireg-export`` and ``resireg-segment``: the deployment commands (argparse; the core
install and the ``export`` extra, no Lightning or Hydra).

    resireg-export onnx <export> --out model.onnx [--lite] [--fp16] [--height H --width W | --dynamic]
    resireg-segment image.jpg --labels "floor,chair,table" --model-path <export> --variant lite --out seg.png
"""

from __future__ import annotations

import argparse
import json
import os
import sys
from collections.abc import Sequence

from resireg.deploy.labels import parse_labels
from resireg.deploy.photo import MAX_PIXELS, check_max_pixels, load_photo

__all__ = ["export_main", "segment_main"]


def _fail(message: str) -> int:
    print(f"error: {message}", file=sys.stderr)
    return 2


def export_main(argv: Sequence[str] | None = None) -> int:
    parser = argparse.ArgumentParser(
        prog="resireg-export", description="Export a ResiregVLM export folder to deployable graphs."
    )
    sub = parser.add_subparsers(dest="format", required=True)
    onnx = sub.add_parser(
        "onnx",
        help="ONNX image graph (+ ReSiReg Lite) and text graph, checked and validated",
        description="Writes OUT (image graph), <stem>.text.onnx (text graph) and OUT.json "
        "(manifest: input size, normalisation, outputs, opsets, digests).",
    )
    onnx.add_argument("export", help="export folder (resireg-train's <run>/export) or Hub repo id")
    onnx.add_argument("--out", required=True, help="the image graph's path, e.g. model.onnx")
    onnx.add_argument(
        "--lite", action="store_true", help="add ReSiReg Lite's features (output 'lite')"
    )
    onnx.add_argument("--lite-attention", default="sdpa", choices=["sdpa", "factorised"],
                      help="Lite's computation (the same function; factorised runs faster on onnxruntime's CPU provider)")  # fmt: skip
    onnx.add_argument(
        "--fp16",
        action="store_true",
        help="float16 image graph (inputs and outputs too; the text graph stays float32)",
    )
    onnx.add_argument("--height", type=int, help="fixed input height (default 576)")
    onnx.add_argument("--width", type=int, help="fixed input width (default 768)")
    onnx.add_argument("--batch", type=int, default=1, help="fixed batch size (default 1)")
    onnx.add_argument("--dynamic", action="store_true", help="dynamic batch, height and width")
    onnx.add_argument("--no-text", action="store_true", help="skip the text graph")
    onnx.add_argument("--no-validate", action="store_true",
                      help="skip the onnxruntime-vs-torch comparison on random inputs")  # fmt: skip
    args = parser.parse_args(argv)
    if args.dynamic and (args.height is not None or args.width is not None):
        return _fail("--dynamic takes no --height/--width")
    try:
        import onnx  # noqa: F401
        import onnxruntime  # noqa: F401
        import onnxscript  # noqa: F401
    except ImportError as err:
        return _fail(f"{err.name} is not installed: pip install 'resireg[export]'")

    from resireg.deploy.onnx_export import check_outputs, export_onnx, validate
    from resireg.errors import ResiregError
    from resireg.models import ResiregVLM

    try:  # the paths first: a bad --out is reported before the model loads
        check_outputs(args.out, not args.no_text, "--out")
    except ValueError as err:
        return _fail(str(err))
    try:  # a missing, damaged or unreachable export (WeightsUnavailableError offline)
        model = ResiregVLM.from_pretrained(args.export)
    except (OSError, ResiregError, ValueError) as err:
        return _fail(f"{args.export}: {err}")
    try:
        result = export_onnx(
            model, args.out, lite=args.lite, attention=args.lite_attention, fp16=args.fp16,
            height=args.height, width=args.width, batch=args.batch, dynamic=args.dynamic,
            text=not args.no_text,
        )  # fmt: skip
    except ValueError as err:
        return _fail(str(err))
    except OSError as err:  # e.g. a full disk: the staged files are removed, none at --out
        reason = os.strerror(err.errno) if err.errno else str(err)
        return _fail(f"--out={args.out!r}: could not write the graphs ({reason}); none was left")
    print(f"image graph: {result.image} ({result.seconds['image']:.1f} s)")
    if not args.no_text:
        print(f"text graph:  {result.text} ({result.seconds['text']:.1f} s)")
    print(f"manifest:    {result.manifest}")
    print(f"opsets:      {json.dumps(result.opsets)}")
    if not args.no_validate:
        for name, diff in validate(result, model).items():
            print(f"onnxruntime vs torch, {name}: max |diff| {diff['max_abs_diff']:.2e}, "
                  f"min cosine {diff['min_cosine']:.6f} (unit features)")  # fmt: skip
    return 0


def segment_main(argv: Sequence[str] | None = None) -> int:
    parser = argparse.ArgumentParser(
        prog="resireg-segment",
        description="Open-vocabulary segmentation of one image: writes OUT (label map PNG, "
        "pixel value = label index), <stem>.overlay.png (photo, colours, legend) and "
        "<stem>.similarity.<i>-<label>.png per label.",
    )
    parser.add_argument("image", help="an image file (JPEG, PNG, ...)")
    parser.add_argument(
        "--labels", required=True, help='labels separated by commas: "floor,chair,table"'
    )
    parser.add_argument("--model-path", help="our VLM: an export folder or Hugging Face repo id")
    parser.add_argument("--encoder", help="an encoder of the zoo: a conf/encoder/ name or YAML "
                        "file (needs the train extra to read it); default resireg_vlm")  # fmt: skip
    parser.add_argument("--variant", default="lite", help="bb, lite, full or calib (default lite)")
    parser.add_argument(
        "--short-side", type=int, help="model input's shorter side (default: the image's)"
    )
    parser.add_argument("--max-pixels", type=int, default=MAX_PIXELS,
                        help="a larger image is resized (aspect kept) to at most this many pixels "
                        f"before the model; the outputs are at that size (default {MAX_PIXELS:,}: "
                        "1024 x 1024, sized for the 25M VLM)")  # fmt: skip
    parser.add_argument("--device", default="cpu")
    parser.add_argument("--out", required=True, help="the label map PNG, e.g. seg.png")
    args = parser.parse_args(argv)

    try:
        labels = parse_labels(args.labels, "--labels")
        check_max_pixels(args.max_pixels, "--max-pixels")
    except ValueError as err:
        return _fail(str(err))
    from resireg.specs.variants import VARIANTS

    if args.variant not in VARIANTS:
        return _fail(f"--variant={args.variant!r}: expected one of {list(VARIANTS)}")
    if args.encoder is None and not args.model_path:
        return _fail("--model-path (an export folder or Hub repo id) or --encoder is required")
    if args.encoder is not None:
        from resireg.specs.encoders import encoder_entry

        try:
            encoder = encoder_entry(args.encoder, args.model_path)
        except ImportError as err:
            return _fail(f"--encoder reads conf/encoder/ with the train extra ({err}); "
                         "pass --model-path instead")  # fmt: skip
        except ValueError as err:
            return _fail(str(err))
    else:
        encoder = args.model_path

    try:  # before torch loads: a bad file is reported at once; a large one decoded small
        photo = load_photo(args.image, args.max_pixels)
    except ValueError as err:  # unreadable, or over PIL's decompression-bomb limit
        return _fail(str(err))

    from resireg.deploy.segment import save_outputs, segment
    from resireg.errors import IntegrityError, OfflineError, rename_arguments

    try:
        result = segment(photo, labels, encoder, args.variant, short_side=args.short_side,
                         max_pixels=args.max_pixels, device=args.device)  # fmt: skip
    except (OSError, IntegrityError, OfflineError) as err:  # a missing, damaged, offline model
        return _fail(f"--model-path={args.model_path}: {err}")
    except ValueError as err:  # e.g. --short-side over --max-pixels
        names = {"short_side": "--short-side", "max_pixels": "--max-pixels"}
        return _fail(rename_arguments(str(err), names)[0])
    paths = save_outputs(photo, result, args.out)
    print(f"label map:  {paths['label_map']}")
    print(f"overlay:    {paths['overlay']}")
    for p in paths["similarity"]:
        print(f"similarity: {p}")
    for name, share in result.shares().items():
        print(f"  {name}: {100 * share:.1f}% of the pixels")
    return 0


def _exit(code: int) -> None:
    raise SystemExit(code)


def export_entry() -> None:
    _exit(export_main())


def segment_entry() -> None:
    _exit(segment_main())


if __name__ == "__main__":  # python -m resireg.deploy.cli {export,segment} ARGS (no console script)
    _COMMANDS = {"export": export_main, "segment": segment_main}
    if len(sys.argv) < 2 or sys.argv[1] not in _COMMANDS:
        _exit(_fail(f"usage: python -m resireg.deploy.cli {{{','.join(_COMMANDS)}}} ARGS"))
    _exit(_COMMANDS[sys.argv[1]](sys.argv[2:]))
