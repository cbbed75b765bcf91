"""Hostile NPZ archives, built byte by byte: a decompression bomb and a cut-off .npy header.

A bomb's member declares gigabytes of zeros that deflate compresses about a thousandfold. To build
one in milliseconds, a megabyte of zeros is deflated once, ending in a full flush (which resets
the compressor, so every block compresses alike), and the compressed block is repeated; the zip
headers are then written by hand with the sizes the member unpacks to.
"""

from __future__ import annotations

import io
import struct
import zlib

import numpy as np

BLOCK = 1 << 20  # bytes of zeros a repeated compressed block unpacks to


def npy_header(descr: str, shape: tuple[int, ...] | str) -> bytes:
    """A version 1.0 .npy header; ``shape`` as a string is written verbatim (e.g. cut off)."""
    text = (
        shape
        if isinstance(shape, str)
        else f"{{'descr': '{descr}', 'fortran_order': False, 'shape': {shape}, }}"
    )
    body = text.encode("latin1")
    padding = -(10 + len(body) + 1) % 64
    return b"\x93NUMPY\x01\x00" + struct.pack("<H", len(body) + padding + 1) + body + b" " * padding + b"\n"


def npy(array: np.ndarray) -> bytes:
    buffer = io.BytesIO()
    np.save(buffer, array, allow_pickle=False)
    return buffer.getvalue()


def bomb_member(items: int) -> tuple[bytes, int, int]:
    """Deflated .npy bytes declaring ``items`` float64 zeros: (compressed, unpacked size, CRC-32).

    The zeros run to a whole number of blocks; the CRC is that of the header alone, as no reader
    that refuses the member in time ever gets to check it.
    """
    header = npy_header("<f8", (items,))
    blocks = -(-items * 8 // BLOCK)
    compressor = zlib.compressobj(9, zlib.DEFLATED, -15)
    start = compressor.compress(header) + compressor.flush(zlib.Z_FULL_FLUSH)
    block = compressor.compress(bytes(BLOCK)) + compressor.flush(zlib.Z_FULL_FLUSH)
    end = compressor.flush()
    return start + block * blocks + end, len(header) + blocks * BLOCK, zlib.crc32(header)


def zip_archive(members: dict[str, tuple[bytes, int, int, int]]) -> bytes:
    """A zip of ``name: (stored bytes, method, unpacked size, CRC-32)``, method 0 stored, 8 deflated."""
    out, directory = io.BytesIO(), io.BytesIO()
    for name, (data, method, size, crc) in members.items():
        offset = out.tell()
        encoded = name.encode()
        out.write(
            struct.pack(
                "<4s5H3L2H", b"PK\x03\x04", 20, 0, method, 0, 0x21, crc, len(data), size, len(encoded), 0
            )
        )
        out.write(encoded + data)
        directory.write(
            struct.pack(
                "<4s6H3L5H2L",
                b"PK\x01\x02",
                20,
                20,
                0,
                method,
                0,
                0x21,
                crc,
                len(data),
                size,
                len(encoded),
                0,
                0,
                0,
                0,
                0,
                offset,
            )
            + encoded
        )
    start = out.tell()
    out.write(directory.getvalue())
    count = len(members)
    out.write(struct.pack("<4s4H2LH", b"PK\x05\x06", 0, 0, count, count, len(directory.getvalue()), start, 0))
    return out.getvalue()


def stored(data: bytes) -> tuple[bytes, int, int, int]:
    return data, 0, len(data), zlib.crc32(data)


def bomb_npz(x: np.ndarray, y: np.ndarray, bomb: str = "fs", items: int = 500_000_000) -> bytes:
    """An NPZ with valid ``x`` and ``y`` whose member ``bomb`` declares ``items`` float64 zeros."""
    compressed, size, crc = bomb_member(items)
    members = {"x.npy": stored(npy(x)), "y.npy": stored(npy(y)), f"{bomb}.npy": (compressed, 8, size, crc)}
    return zip_archive(members)


def cut_off_header_npz(x: np.ndarray) -> bytes:
    """An NPZ whose ``y`` member's header stops inside the shape: ``{'descr': '<f8', 'shape': (2,``."""
    broken = npy_header("<f8", "{'descr': '<f8', 'shape': (2,") + bytes(16)
    return zip_archive({"x.npy": stored(npy(x)), "y.npy": stored(broken)})
