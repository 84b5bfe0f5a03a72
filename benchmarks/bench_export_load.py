"""The cost of the path checks on loading an export (``resireg.integrity.resolve_inside``:
every file name that ``config.json`` holds stays inside the export folder).

Two exports of random weights are written to a temporary folder: the 25M architecture
(``_common.build_model``: EUPE ViT-S/16 and the 25M head, the backbone's weights embedded in
``frozen.safetensors``) and the tests' tiny one. Each is loaded with
``ResiregVLM.from_pretrained`` in alternating rounds, with the checks ("after") and with
``resolve_inside`` replaced by the bare ``folder / name`` it guards ("before": the loading code
of this checkout, the checks alone taken out). Medians and the ratio after / before; also the
cost of one check, timed alone.

    python benchmarks/bench_export_load.py               # 7 rounds
    python benchmarks/bench_export_load.py --rounds 3
"""

from __future__ import annotations

import argparse
import statistics
import tempfile
import time
import timeit
from contextlib import contextmanager
from pathlib import Path

import torch

import resireg.integrity
import resireg.models.vlm.folder
import resireg.models.vlm.model
from _common import build_model
from resireg.integrity import resolve_inside
from resireg.models import ResiregVLM

#: The modules that call resolve_inside on a load (the check swapped out of each for "before").
_CALLERS = (resireg.integrity, resireg.models.vlm.folder, resireg.models.vlm.model)


@contextmanager
def _without_checks():
    def bare(folder, name, field):
        return Path(folder) / name

    saved = [m.resolve_inside for m in _CALLERS]
    for module in _CALLERS:
        module.resolve_inside = bare
    try:
        yield
    finally:
        for module, original in zip(_CALLERS, saved, strict=True):
            module.resolve_inside = original


def _load(path: Path) -> float:
    start = time.perf_counter()
    ResiregVLM.from_pretrained(path)
    return time.perf_counter() - start


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    parser.add_argument("--rounds", type=int, default=7)
    args = parser.parse_args()
    torch.manual_seed(0)
    with tempfile.TemporaryDirectory() as tmp:
        exports = {
            "25M": build_model().save_pretrained(Path(tmp) / "m25", include_frozen=True),
            "tiny": build_model(tiny=True).save_pretrained(Path(tmp) / "tiny"),
        }
        print(f"torch {torch.__version__}, {torch.get_num_threads()} threads, medians of "
              f"{args.rounds} alternating rounds")  # fmt: skip
        loads = {}
        print("\n| export | size MB | before s | after s | after / before |")
        print("| --- | ---: | ---: | ---: | ---: |")
        for name, path in exports.items():
            size = sum(p.stat().st_size for p in path.iterdir()) / 1e6
            _load(path)  # warm-up (file cache, imports)
            with _without_checks():
                _load(path)
            before, after = [], []
            for _ in range(args.rounds):
                after.append(_load(path))
                with _without_checks():
                    before.append(_load(path))
            b, a = statistics.median(before), statistics.median(after)
            loads[name] = b
            print(f"| {name} | {size:.1f} | {b:.4f} | {a:.4f} | {a / b:.3f} |")
        number = 100_000
        folder = exports["25M"]
        one = timeit.timeit(
            lambda: resolve_inside(folder, "frozen.safetensors", "config.json: frozen_weights"),
            number=number,
        )
        print(f"\none check: {1e6 * one / number:.2f} us; a load of an export with "
              "frozen.safetensors makes 4 (frozen_weights in read_config and in from_pretrained, "
              "each of the 2 digests' names once)")  # fmt: skip
        for name, seconds in loads.items():
            print(f"{name}: the 4 checks / a load without them = {4 * one / number / seconds:.1e}")


if __name__ == "__main__":
    main()
