"""Peak memory of ``resireg-segment`` on large images, with its pixel limit and without.

Gradient PNGs of each ``--sizes`` (written row by row through zlib, so neither the file nor
this script holds the image) are segmented by ``resireg-segment`` with the 25M architecture
(random weights, exported to a temporary folder; ``--model tiny``: the tests' tiny one), the
variant ``--variant`` (default lite), 3 labels, each run in a fresh process that reports its
own peak resident memory (``ru_maxrss``) and wall time: once at the default ``--max-pixels``
(1024 x 1024) and, for images of at most ``--unlimited-up-to`` pixels, once with no limit
(``--max-pixels`` above the image's size: the whole image to the model, as before the limit).

    python benchmarks/bench_segment.py                                  # 2000x1500 .. 9000x9000
    python benchmarks/bench_segment.py --model tiny --sizes 9000x9000 --unlimited-up-to 0
"""

from __future__ import annotations

import argparse
import os
import struct
import subprocess
import sys
import tempfile
import time
import zlib
from pathlib import Path

import numpy as np
import torch
from PIL import Image

from _common import build_model
from resireg.deploy.photo import MAX_PIXELS

_CHILD = (
    "import resource, sys\n"
    "from resireg.deploy.cli import segment_main\n"
    "code = segment_main(sys.argv[1:])\n"
    "print('PEAK_KB', resource.getrusage(resource.RUSAGE_SELF).ru_maxrss)\n"
    "sys.exit(code)\n"
)


def write_png(path: Path, width: int, height: int) -> Path:
    """An RGB gradient PNG, compressed row by row (the image is never in memory)."""

    def chunk(kind: bytes, data: bytes) -> bytes:
        return (
            struct.pack(">I", len(data)) + kind + data + struct.pack(">I", zlib.crc32(kind + data))
        )

    packer = zlib.compressobj(6)
    ramp = np.linspace(0, 255, 3 * width).astype(np.uint8).tobytes()
    with open(path, "wb") as f:
        f.write(b"\x89PNG\r\n\x1a\n")
        f.write(chunk(b"IHDR", struct.pack(">IIBBBBB", width, height, 8, 2, 0, 0, 0)))
        data = [packer.compress(b"\x00" + ramp) for _ in range(height)]
        f.write(chunk(b"IDAT", b"".join(data) + packer.flush()))
        f.write(chunk(b"IEND", b""))
    return path


def _run(
    image: Path, export: Path, out: Path, variant: str, max_pixels: int
) -> tuple[float, float]:
    """``(peak GiB, seconds)`` of one resireg-segment run in a fresh process."""
    cmd = [sys.executable, "-c", _CHILD, str(image), "--labels", "floor,wall,sky", "--model-path",
           str(export), "--variant", variant, "--max-pixels", str(max_pixels), "--out", str(out)]  # fmt: skip
    start = time.perf_counter()
    proc = subprocess.run(
        cmd, capture_output=True, text=True, env={**os.environ, "HF_HUB_OFFLINE": "1"}
    )
    seconds = time.perf_counter() - start
    if proc.returncode != 0:
        raise SystemExit(proc.stderr[-2000:])
    peak_kb = int(proc.stdout.split("PEAK_KB")[-1])
    return peak_kb / 2**20, seconds


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    parser.add_argument("--sizes", nargs="+", default=["2000x1500", "4000x3000", "9000x9000"])
    parser.add_argument("--model", choices=["25m", "tiny"], default="25m")
    parser.add_argument("--variant", default="lite")
    parser.add_argument("--unlimited-up-to", type=int, default=2000 * 1500,
                        help="run without a limit only images of at most this many pixels")  # fmt: skip
    args = parser.parse_args()
    torch.manual_seed(0)
    with tempfile.TemporaryDirectory() as tmp:
        tmp = Path(tmp)
        model = build_model(tiny=args.model == "tiny")
        export = model.save_pretrained(tmp / "export", include_frozen=args.model == "25m")
        print(f"resireg-segment, {args.model} model (random weights), variant {args.variant}, "
              f"torch {torch.__version__}, {torch.get_num_threads()} threads")  # fmt: skip
        print("\n| image | file MB | --max-pixels | model's image | peak GiB | s |")
        print("| --- | ---: | ---: | --- | ---: | ---: |")
        for size in args.sizes:
            w, h = map(int, size.split("x"))
            png = write_png(tmp / f"{size}.png", w, h)
            limits = [MAX_PIXELS] + ([w * h] if w * h <= args.unlimited_up_to else [])
            for limit in limits:
                out = tmp / "seg" / f"{size}-{limit}.png"
                peak, seconds = _run(png, export, out, args.variant, limit)
                with Image.open(out) as im:
                    got = f"{im.size[0]} x {im.size[1]}"
                label = f"{limit:,}" + (" (none)" if limit == w * h else "")
                print(f"| {w} x {h} | {png.stat().st_size / 1e6:.2f} | {label} | {got} | "
                      f"{peak:.2f} | {seconds:.1f} |")  # fmt: skip


if __name__ == "__main__":
    main()
