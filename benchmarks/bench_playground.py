"""Response time of the playground for one query (three text queries on the astronaut example).

Two measurements per model, best of ``--repeats`` after one warm-up:

- **in process**: ``Playground.compute`` + ``render`` (what the Run button runs), split into
  the encoder pass, the text queries and each variant's own ReSiReg step; run in a worker
  thread, as Gradio runs it (torch's OpenMP settings are per thread: on a loaded 2-core
  machine a worker thread ran the 25M encoder in 3.4 s, the main thread with 2 OpenMP threads
  in 7.1 s and with 1 in 3.1 s);
- **through the server** (``--http``): ``resireg-playground`` started as a subprocess on a
  free local port, queried with ``gradio_client`` (``/run``): the page's whole round trip,
  PNG encoding and download of the panels included.

Models: ``tiny`` (the tests' tiny VLM) and ``vlm25m`` (EUPE ViT-S/16 + the language head with
random weights: the real image-side architecture, whose cost does not depend on the weights;
the text tower is the tiny one, since SigLIP 2 cannot be downloaded here, so the real text
tower's cost is not included).

    python benchmarks/bench_playground.py [--models tiny vlm25m] [--short-side 576] [--http]
"""

from __future__ import annotations

import argparse
import os
import socket
import subprocess
import sys
import tempfile
import time
import urllib.request
from concurrent.futures import ThreadPoolExecutor
from pathlib import Path

import torch

from _common import build_model
from resireg.models import ResiregVLM
from resireg_train.playground.core import Playground, render, resireg_defaults
from resireg_train.playground.examples import EXAMPLES, example_image

MODELS = ("tiny", "vlm25m")


def _build(name: str) -> ResiregVLM:
    torch.manual_seed(0)
    return build_model(tiny=name == "tiny")


def in_process(name: str, short_side: int, repeats: int) -> None:
    playground = Playground(_build(name), resireg_defaults(), short_side)
    image, queries = example_image("astronaut"), EXAMPLES["astronaut"][1]

    def query():
        t = time.perf_counter()
        result = playground.compute(image, queries)
        render(result)
        return time.perf_counter() - t, result

    best = None
    with ThreadPoolExecutor(1) as worker:
        for i in range(repeats + 1):
            total, result = worker.submit(query).result()
            if i and (best is None or total < best[0]):  # the first run warms up
                best = (total, result)
    total, result = best
    s = result.seconds
    h, w = result.canvas.shape[:2]
    print(f"{name:>7} | {h}x{w} | {total:7.3f} | {s['encoder']:7.3f} | {s['text']:5.3f} | "
          f"{s['bb']:5.3f} | {s['lite']:6.3f} | {s['full']:6.3f}")  # fmt: skip


def _free_port() -> int:
    with socket.socket() as sock:
        sock.bind(("127.0.0.1", 0))
        return sock.getsockname()[1]


def through_server(name: str, short_side: int, repeats: int) -> None:
    from gradio_client import Client

    defaults = resireg_defaults()
    sliders = [defaults["lite"][k] for k in ("alpha", "tau", "upscale")] + [
        defaults["full"][k] for k in ("n_prototypes", "alpha", "tau", "upscale")
    ]
    with tempfile.TemporaryDirectory() as tmp:
        export = _build(name).save_pretrained(Path(tmp) / "export", include_frozen=True)
        port = _free_port()
        cmd = [sys.executable, "-m", "resireg_train.cli.playground", "--model-path", str(export),
               "--port", str(port), "--short-side", str(short_side), "--device", "cpu"]  # fmt: skip
        env = {**os.environ, "HF_HUB_OFFLINE": "1", "GRADIO_ANALYTICS_ENABLED": "False"}
        started = time.perf_counter()
        proc = subprocess.Popen(cmd, stdout=subprocess.DEVNULL, stderr=subprocess.DEVNULL, env=env)
        try:
            url = f"http://127.0.0.1:{port}/"
            while True:
                if proc.poll() is not None:
                    raise RuntimeError(f"the playground exited with {proc.returncode}")
                try:
                    urllib.request.urlopen(url, timeout=2).close()
                    break
                except OSError:
                    time.sleep(0.2)
            ready = time.perf_counter() - started
            client = Client(url, verbose=False)
            times = []
            for _ in range(repeats + 1):
                t = time.perf_counter()
                out = client.predict(None, "astronaut", EXAMPLES["astronaut"][1], short_side,
                                     *sliders, api_name="/run")  # fmt: skip
                times.append(time.perf_counter() - t)
            assert str(out[0]).startswith("Done:"), out[0]
            shared = str(out[-1]).rsplit("Shared by every variant: ", 1)[-1].strip()
            print(f"{name:>7} | server up in {ready:5.1f} s | one query {min(times[1:]):6.3f} s "
                  f"(first {times[0]:.3f} s) | last query's page: {shared}")  # fmt: skip
        finally:
            proc.terminate()
            proc.wait(timeout=30)


def main() -> None:
    parser = argparse.ArgumentParser(
        description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter
    )
    parser.add_argument("--models", nargs="+", choices=sorted(MODELS), default=["tiny", "vlm25m"])
    parser.add_argument("--short-side", type=int, default=576)
    parser.add_argument("--repeats", type=int, default=3)
    parser.add_argument("--http", action="store_true", help="also through the running server")
    args = parser.parse_args()
    print(f"threads {torch.get_num_threads()}, astronaut 512x512 at short side {args.short_side}, "
          f"3 queries; seconds, best of {args.repeats}")  # fmt: skip
    print("  model | image | compute+render | encoder | text | BB | Lite | Full")
    for name in args.models:
        in_process(name, args.short_side, args.repeats)
    if args.http:
        for name in args.models:
            through_server(name, args.short_side, args.repeats)


if __name__ == "__main__":
    main()
