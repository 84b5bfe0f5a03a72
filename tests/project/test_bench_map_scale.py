"""benchmarks/bench_map_scale.py's one-row modes, the real command: a size that is no positive
integer is refused in one line naming the flag (argparse's exit code 2), never taken for "no
flag" (which runs every size, minutes); a valid one prints its row."""

from __future__ import annotations

import json
import sys

import pytest

from helpers.paths import ROOT
from helpers.run import run

SCRIPT = ROOT / "benchmarks" / "bench_map_scale.py"


@pytest.mark.parametrize("flag", ["--classify-floor", "--classify-cpu"])
@pytest.mark.parametrize("value", ["0", "-5", "1e6"])
def test_a_size_that_is_no_positive_integer_is_refused_naming_the_flag(flag, value):
    proc = run(sys.executable, SCRIPT, flag, value, check=False, timeout=120)
    assert proc.returncode == 2 and proc.stdout == ""
    assert proc.stderr.splitlines()[-1] == (
        f"bench_map_scale.py: error: argument {flag}: '{value}': expected an integer >= 1"
    )


def test_the_classify_floor_prints_the_products_of_its_size():
    proc = run(sys.executable, SCRIPT, "--classify-floor", "256", "--threads", "1", timeout=120)
    row = json.loads(proc.stdout)
    assert (row["size"], row["channels"], row["threads"]) == (256, 128, 1)
    assert set(row) - {"size", "channels", "threads", "torch", "cpu_capability"} == {
        "widen_float16_to_float32_ms", "product_16_float32_ms", "product_150_float32_ms",
        "product_16_bfloat16_ms", "product_150_bfloat16_ms",
    }  # fmt: skip
