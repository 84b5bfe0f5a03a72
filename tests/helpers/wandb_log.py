"""W&B's offline run file (``run-<id>.wandb``) read by hand, for the tracker tests:
:func:`records` yields its protobuf ``Record`` messages."""

import struct

import pytest

pytest.importorskip("wandb")
from wandb.proto import wandb_internal_pb2  # noqa: E402

_HEADER = b":W&B\xe1\xbe\x00"  # W&B's transaction log: ident, magic 0xBEE1, version 0
_BLOCK = 32768


def records(path):
    """The protobuf ``Record`` messages of a ``run-<id>.wandb`` file, read by hand: the file
    is LevelDB's log format (32 KiB blocks of chunks: crc32 u32, length u16, type u8 with
    1 full, 2 first, 3 middle, 4 last) after a 7-byte header."""
    data = path.read_bytes()
    assert data[:7] == _HEADER
    pos, pending = 7, b""
    while pos + 7 <= len(data):
        left = _BLOCK - pos % _BLOCK
        if left < 7:  # a block's tail too short for a chunk header is padding
            pos += left
            continue
        _, length, kind = struct.unpack("<IHB", data[pos : pos + 7])
        if kind == 0:  # zero padding to the block's end
            pos += left
            continue
        chunk, pos = data[pos + 7 : pos + 7 + length], pos + 7 + length
        pending = chunk if kind in (1, 2) else pending + chunk
        if kind in (1, 4):
            record = wandb_internal_pb2.Record()
            record.ParseFromString(pending)
            yield record
