"""resireg.integrity (digests, atomic writes, named read errors) and resireg.method.checks (the one
finite-features rule), against hashlib / numpy / os references."""

from __future__ import annotations

import errno
import hashlib
import json
import os
import stat

import numpy as np
import pytest
import torch
from safetensors.torch import save_file

from resireg.integrity import (
    IntegrityError,
    atomic_write,
    digests,
    load_safetensors,
    read_json,
    sha256_file,
    verify_digests,
)
from resireg.method.checks import NonFiniteError, check_features, count_nonfinite


def test_sha256_matches_hashlib_across_chunks(tmp_path):
    data = os.urandom((1 << 20) * 2 + 12345)  # crosses the 1 MiB chunk boundary twice
    (tmp_path / "f").write_bytes(data)
    assert sha256_file(tmp_path / "f") == hashlib.sha256(data).hexdigest()


def test_verify_digests_names_the_changed_file(tmp_path):
    for name in ("a.bin", "b.bin"):
        (tmp_path / name).write_bytes(os.urandom(4096))
    recorded = digests(tmp_path, ["b.bin", "a.bin"])
    assert list(recorded) == ["a.bin", "b.bin"]
    verify_digests(tmp_path, recorded, "saved map")  # unchanged: passes
    raw = bytearray((tmp_path / "b.bin").read_bytes())
    raw[100] ^= 0x01  # one flipped bit
    (tmp_path / "b.bin").write_bytes(bytes(raw))
    with pytest.raises(IntegrityError, match=r"b\.bin.*saved map recorded"):
        verify_digests(tmp_path, recorded, "saved map")
    (tmp_path / "a.bin").unlink()
    with pytest.raises(IntegrityError, match=r"a\.bin: missing"):
        verify_digests(tmp_path, recorded, "saved map")


def test_truncated_json_and_safetensors_name_the_file(tmp_path):
    (tmp_path / "map.json").write_text(json.dumps({"a": 1, "b": [1, 2, 3]})[:9])
    with pytest.raises(IntegrityError, match=r"map\.json: not a readable saved map"):
        read_json(tmp_path / "map.json", "saved map")
    with pytest.raises(IntegrityError, match=r"nope\.json: missing"):
        read_json(tmp_path / "nope.json", "saved map")
    save_file({"x": torch.arange(1000, dtype=torch.float32)}, str(tmp_path / "t.safetensors"))
    whole = (tmp_path / "t.safetensors").read_bytes()
    assert torch.equal(load_safetensors(tmp_path / "t.safetensors", "export")["x"],
                       torch.arange(1000, dtype=torch.float32))  # fmt: skip
    (tmp_path / "t.safetensors").write_bytes(whole[: len(whole) // 2])
    with pytest.raises(IntegrityError, match=r"t\.safetensors: not a readable safetensors"):
        load_safetensors(tmp_path / "t.safetensors", "export")


def test_atomic_write_follows_the_umask_and_keeps_the_old_file_on_failure(tmp_path):
    target = tmp_path / "t.safetensors"
    old = os.umask(0o022)
    try:
        atomic_write(target, lambda tmp: save_file({"x": torch.ones(3)}, str(tmp)))
    finally:
        os.umask(old)
    # safetensors itself creates 0600 files; the umask 022 gives 0644
    assert stat.S_IMODE(target.stat().st_mode) == 0o644
    before = target.read_bytes()

    def full_disk(tmp):
        tmp.write_bytes(b"partial")
        raise OSError(errno.ENOSPC, "No space left on device")

    with pytest.raises(OSError, match=r"could not write .*t\.safetensors") as info:
        atomic_write(target, full_disk)
    assert info.value.errno == errno.ENOSPC
    assert target.read_bytes() == before
    assert sorted(p.name for p in tmp_path.iterdir()) == ["t.safetensors"]  # no temp file left


@pytest.mark.parametrize("dtype", [torch.float32, torch.bfloat16, torch.float16, torch.float64])
def test_check_features_counts_like_numpy(dtype):
    x = torch.randn(2, 8, 5, 5).to(dtype)
    assert check_features("language", x) is x
    x[0, 1, 2, 3] = float("nan")
    x[1, 0, 0, 0] = float("inf")
    x[1, 7, 4, 4] = float("-inf")
    ref = int((~np.isfinite(x.float().numpy())).sum())
    assert count_nonfinite(x) == ref == 3
    with pytest.raises(NonFiniteError, match=r"language holds 3 non-finite value\(s\)"):
        check_features("language", x)


def test_check_features_refuses_non_floating():
    with pytest.raises(
        TypeError, match="intermediates must be a floating-point tensor, got dtype torch.int64"
    ):
        check_features("intermediates", torch.ones(1, 2, 3, 3, dtype=torch.long))
    with pytest.raises(TypeError, match="must be a torch.Tensor, got ndarray"):
        check_features("depth", np.ones(3))
    assert check_features("empty", torch.empty(0, 4)).numel() == 0
