"""A saved map's tensor file: safetensors written in blocks and read memory-mapped.

:func:`write_tensors` writes the safetensors format (an 8-byte little-endian header length, the
JSON header of every tensor's dtype, shape and byte range, then the bytes) from tensors given
as lists of blocks, straight from each block's memory, hashing the bytes as they go: a map is
saved without a copy of itself (``safetensors.torch.save_file`` first serialises every tensor
to bytes, a second copy of the map) and without reading the file again for its digest.
:func:`read_tensors` maps the file (``numpy.memmap``, copy-on-write: the map may change its
rows, the file never changes) and returns tensors over the mapping, so a map of any size loads
in the time its digest takes. Both are written here, not taken from ``safetensors``, for
those two reasons; the files are plain safetensors files that ``safetensors.safe_open`` reads.
"""

from __future__ import annotations

import hashlib
import json
import os
import struct
from collections.abc import Mapping, Sequence
from pathlib import Path

import numpy as np
import torch
from torch import Tensor

from resireg.integrity import IntegrityError

__all__ = ["read_tensors", "write_tensors"]

# safetensors dtype names <-> torch dtypes; bfloat16 travels as its 16 bits (numpy has none).
_DTYPES = {
    "F64": torch.float64,
    "F32": torch.float32,
    "F16": torch.float16,
    "BF16": torch.bfloat16,
    "I64": torch.int64,
    "I32": torch.int32,
    "U8": torch.uint8,
    "BOOL": torch.bool,
}
_NAMES = {v: k for k, v in _DTYPES.items()}
_NUMPY = {
    "F64": np.float64,
    "F32": np.float32,
    "F16": np.float16,
    "BF16": np.uint16,
    "I64": np.int64,
    "I32": np.int32,
    "U8": np.uint8,
    "BOOL": np.bool_,
}
# Bytes per write call (a block's bytes go out in slices of this size).
_WRITE = 1 << 24


def _bytes(t: Tensor) -> memoryview:
    """The bytes of a CPU tensor, without a copy when it is contiguous."""
    t = t.detach().cpu().contiguous()
    if t.dtype == torch.bfloat16:
        t = t.view(torch.int16)
    if t.numel() == 0:
        return memoryview(b"")
    return memoryview(t.numpy().reshape(-1)).cast("B")


def write_tensors(path: str | os.PathLike, tensors: Mapping[str, Sequence[Tensor]]) -> str:
    """Write ``{name: [block, ...]}`` (each tensor the concatenation of its blocks along the
    first dimension) as a safetensors file at ``path``; returns the file's SHA-256."""
    header: dict[str, dict] = {}
    offset = 0
    for name, blocks in tensors.items():
        if not blocks:
            raise ValueError(f"tensor {name!r}: no block")
        first = blocks[0]
        rows = sum(int(b.shape[0]) for b in blocks) if first.ndim else 1
        for b in blocks:
            if b.dtype != first.dtype or tuple(b.shape[1:]) != tuple(first.shape[1:]):
                raise ValueError(f"tensor {name!r}: blocks of other dtypes or shapes")
        shape = [rows, *first.shape[1:]] if first.ndim else []
        size = int(np.prod(shape, dtype=np.int64)) * first.element_size()
        header[name] = {"dtype": _NAMES[first.dtype], "shape": shape,
                        "data_offsets": [offset, offset + size]}  # fmt: skip
        offset += size
    text = json.dumps(header, separators=(",", ":")).encode()
    text += b" " * (-len(text) % 8)  # the data starts 8-byte aligned
    digest = hashlib.sha256()
    with open(path, "wb") as f:

        def put(data: bytes | memoryview) -> None:
            for start in range(0, len(data), _WRITE):
                part = data[start : start + _WRITE]
                digest.update(part)
                f.write(part)

        put(struct.pack("<Q", len(text)) + text)
        for blocks in tensors.values():
            for b in blocks:
                put(_bytes(b))
    return digest.hexdigest()


def read_tensors(path: str | os.PathLike, what: str) -> dict[str, Tensor]:
    """The tensors of a safetensors file, memory-mapped copy-on-write (writes to them never
    reach the file). A file whose header does not describe its bytes is an
    :class:`~resireg.integrity.IntegrityError` naming it."""
    path = Path(path)
    if not path.is_file():
        raise IntegrityError(f"{path}: missing ({what})")
    size = path.stat().st_size

    def bad(why: str) -> IntegrityError:
        return IntegrityError(f"{path}: not a readable safetensors file ({what}): {why}")

    with open(path, "rb") as f:
        head = f.read(8)
        if len(head) < 8:
            raise bad("shorter than its header")
        (n,) = struct.unpack("<Q", head)
        if n > min(size - 8, 1 << 26):
            raise bad(f"a header of {n} bytes")
        try:
            header = json.loads(f.read(n))
        except (UnicodeDecodeError, json.JSONDecodeError) as err:
            raise bad(f"its header is no JSON ({err})") from err
    if not isinstance(header, dict):
        raise bad("its header is no JSON object")
    base = 8 + n
    out: dict[str, Tensor] = {}
    for name, spec in header.items():
        if name == "__metadata__":
            continue
        try:
            kind = spec["dtype"]
            shape = [int(s) for s in spec["shape"]]
            start, stop = (int(x) for x in spec["data_offsets"])
            dtype = _NUMPY[kind]
        except (KeyError, TypeError, ValueError) as err:
            raise bad(f"tensor {name!r}: {err!r}") from err
        count = int(np.prod(shape, dtype=np.int64))
        if (min(shape, default=0) < 0 or stop - start != count * np.dtype(dtype).itemsize
                or start < 0 or base + stop > size):  # fmt: skip
            raise bad(f"tensor {name!r}: bytes {start}..{stop} do not hold {kind} {shape}")
        if count == 0:
            array = np.zeros(shape, dtype=dtype)
        else:
            array = np.memmap(path, dtype=dtype, mode="c", offset=base + start, shape=tuple(shape))
        t = torch.from_numpy(array)
        out[name] = t.view(torch.bfloat16) if kind == "BF16" else t
    return out
