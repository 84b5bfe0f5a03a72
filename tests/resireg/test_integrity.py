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
    resolve_inside,
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


#: Names a record may hold, good and hostile (issue 44 item 6).
NAMES = ["model.safetensors", "sub/a.bin", "sub/../a.bin", "./a.bin", "a//b.bin", "../a.bin",
         "a/../../b.bin", "..", ".", "sub/..", "../export2/a.bin", "/etc/passwd", "//host/x",
         "..\\a.bin", "sub\\..\\..\\a.bin", "C:\\x.bin", "C:x.bin", "\\\\server\\share\\x"]  # fmt: skip


def _inside_by_the_file_system(folder, name):
    """The reference: the path the OS makes of ``folder/name`` (a backslash read as a
    separator, as on Windows; realpath with no links in the way), under ``folder`` and not
    the folder itself, for a name that is not absolute on POSIX or Windows."""
    import ntpath

    if os.path.isabs(name) or ntpath.splitdrive(name)[0] or name.startswith("\\"):
        return None
    path = os.path.realpath(os.path.join(folder, name.replace("\\", "/")))
    base = os.path.realpath(folder)
    return path if path != base and os.path.commonpath([path, base]) == base else None


@pytest.mark.parametrize("name", NAMES)
def test_resolve_inside_agrees_with_the_file_system(tmp_path, name):
    folder = tmp_path / "export"
    (folder / "sub").mkdir(parents=True)
    expected = _inside_by_the_file_system(folder, name)
    if expected is None:
        with pytest.raises(IntegrityError) as err:
            resolve_inside(folder, name, "config.json: frozen_weights")
        message = str(err.value)
        assert message.startswith(f"config.json: frozen_weights={name!r}: ")  # field and value
        assert "\n" not in message and str(folder) in message
    else:
        assert os.path.realpath(resolve_inside(folder, name, "f")) == expected


@pytest.mark.parametrize("name", [3, None, "", "a\0b", ["a"]])
def test_resolve_inside_refuses_what_is_not_a_name(tmp_path, name):
    with pytest.raises(IntegrityError, match=r"^map\.json: files="):
        resolve_inside(tmp_path, name, "map.json: files")


def test_verify_digests_reads_no_file_outside_its_folder(tmp_path):
    """A record whose digests name a file outside (its digest recomputed, as anyone editing
    the record would) is refused before any file is hashed, naming the field."""
    folder, outside = tmp_path / "map", tmp_path / "secret.bin"
    folder.mkdir()
    (folder / "a.bin").write_bytes(b"a")
    outside.write_bytes(b"secret")
    for name in ("../secret.bin", str(outside)):
        recorded = {"a.bin": sha256_file(folder / "a.bin"), name: sha256_file(outside)}
        with pytest.raises(IntegrityError, match=rf"^saved map digests={name!r}: "):
            verify_digests(folder, recorded, "saved map")
        with pytest.raises(IntegrityError, match=rf"^map\.json: sha256={name!r}: "):
            verify_digests(folder, recorded, "saved map", "map.json: sha256")
    with pytest.raises(IntegrityError, match=r"expected \{file name: sha256\}"):
        verify_digests(folder, ["a.bin"], "saved map")
    with pytest.raises(IntegrityError, match=r"a\.bin=7: expected a SHA-256"):
        verify_digests(folder, {"a.bin": 7}, "saved map")


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
