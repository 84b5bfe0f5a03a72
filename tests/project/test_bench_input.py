"""benchmarks/bench_input.py on bad input, the real command: an undecodable JPEG, a truncated
JPEG and a 0-byte shard are skipped and counted (in the floor's pass and by the stream), the
figures still printed."""

from __future__ import annotations

import io
import sys
import tarfile

import numpy as np
import pytest
from PIL import Image

from helpers.paths import ROOT
from helpers.run import run


def _jpeg(w, h, seed):
    g = np.random.default_rng(seed)
    buf = io.BytesIO()
    Image.fromarray(g.integers(0, 255, (h, w, 3), dtype=np.uint8)).save(buf, "JPEG")
    return buf.getvalue()


@pytest.mark.slow
@pytest.mark.parametrize("bad", ["undecodable", "truncated", "empty shard"])
def test_bench_input_skips_and_counts_bad_jpegs_and_empty_shards(bad, tmp_path):
    items = [[(f"{s}{i}", _jpeg(120, 90, 10 * s + i)) for i in range(3)] for s in range(2)]
    whole = _jpeg(400, 300, 99)
    if bad == "undecodable":
        items[0].insert(1, ("bad", b"\xff\xd8\xff\xe0 not a JPEG"))
    elif bad == "truncated":
        items[1].insert(0, ("bad", whole[: len(whole) // 2]))
    for s, shard in enumerate(items):
        with tarfile.open(tmp_path / f"shard-{s}.tar", "w") as tar:
            for key, data in shard:
                for ext, payload in (("jpg", data), ("txt", f"caption {key}".encode())):
                    info = tarfile.TarInfo(f"{key}.{ext}")
                    info.size = len(payload)
                    tar.addfile(info, io.BytesIO(payload))
    if bad == "empty shard":
        (tmp_path / "shard-2.tar").write_bytes(b"")
    proc = run(sys.executable, ROOT / "benchmarks" / "bench_input.py", "--shards", tmp_path,
               "--no-flops", "--batch", "2", "--crop", "64")  # fmt: skip
    out = proc.stdout
    n_bad = int(bad != "empty shard")
    assert f"{6 + n_bad} JPEGs" in out
    assert f"{int(bad == 'empty shard')} empty (0-byte) shard(s) skipped" in out
    assert f"undecodable or truncated JPEGs skipped: {n_bad} (floor's pass), {n_bad} " in out
    assert "(over 6 images)" in out  # every good image went through the stream
    if bad == "empty shard":  # the stream's own count, in its one warning
        assert "skipped 1 empty (0-byte) shard(s): shard-2.tar" in proc.stderr
    assert "Traceback" not in proc.stderr
