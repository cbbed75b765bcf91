"""MAT v5 files built byte by byte (MathWorks' "MAT-File Format"), hostile ones included.

Independent of ``recordfiles.matfiles``: a 128-byte header, then tagged elements. A compressed
bomb holds a variable whose header declares hundreds of megabytes of zeros; as for the NPZ
bombs (``npz_bombs``), a megabyte of zeros is deflated once, ending in a full flush, and the
compressed block repeated, so that building one takes milliseconds.
"""

from __future__ import annotations

import struct
import zlib

import numpy as np

BLOCK = 1 << 20  # bytes of zeros a repeated compressed block inflates to
MI_INT8, MI_INT32, MI_UINT32, MI_DOUBLE, MI_MATRIX, MI_COMPRESSED = 1, 5, 6, 9, 14, 15
CELL, STRUCT, DOUBLE = 1, 2, 6


def header(version: int = 0x0100) -> bytes:
    text = b"MATLAB 5.0 MAT-file, written byte by byte by narxwatch's tests"
    return text.ljust(116, b" ") + bytes(8) + struct.pack("<H", version) + b"IM"


def tag(data_type: int, size: int) -> bytes:
    return struct.pack("<2I", data_type, size)


def padded(data: bytes) -> bytes:
    return data + bytes(-len(data) % 8)


def matrix_head(name: str, dims: tuple[int, ...], class_code: int = DOUBLE, flags: int = 0) -> bytes:
    """Array flags, dimensions and name: the subelements before a matrix's data."""
    shape = struct.pack(f"<{len(dims)}i", *dims)
    return (
        tag(MI_UINT32, 8)
        + struct.pack("<2I", class_code | flags, 0)
        + tag(MI_INT32, len(shape))
        + padded(shape)
        + tag(MI_INT8, len(name))
        + padded(name.encode())
    )


def matrix(name: str, values: np.ndarray) -> bytes:
    """An uncompressed double array element, stored column-major as MATLAB does."""
    data = np.asarray(values, dtype="<f8").tobytes(order="F")
    content = matrix_head(name, values.shape) + tag(MI_DOUBLE, len(data)) + padded(data)
    return tag(MI_MATRIX, len(content)) + content


def compressed(element: bytes) -> bytes:
    body = zlib.compress(element)
    return tag(MI_COMPRESSED, len(body)) + body


def zeros_bomb(name: str, dims: tuple[int, ...], data_bytes: int) -> bytes:
    """A compressed double matrix of ``dims`` whose data element declares ``data_bytes`` and
    inflates to that many zeros (rounded up to whole blocks); the declared sizes of the matrix
    element count them too."""
    head = matrix_head(name, dims) + tag(MI_DOUBLE, data_bytes)
    blocks = -(-data_bytes // BLOCK)
    compressor = zlib.compressobj(9)
    start = compressor.compress(tag(MI_MATRIX, len(head) + blocks * BLOCK) + head)
    start += compressor.flush(zlib.Z_FULL_FLUSH)
    block = compressor.compress(bytes(BLOCK)) + compressor.flush(zlib.Z_FULL_FLUSH)
    body = start + block * blocks + compressor.flush()
    return tag(MI_COMPRESSED, len(body)) + body


def huge_cell(name: str, cells: int) -> bytes:
    """An uncompressed cell array declaring ``cells`` cells and holding none: dimensions that
    make a reader which trusts them allocate an object array of ``8 · cells`` bytes."""
    content = matrix_head(name, (1, cells), class_code=CELL)
    return tag(MI_MATRIX, len(content)) + content


def mat_file(*elements: bytes) -> bytes:
    return header() + b"".join(elements)


def v73_file() -> bytes:
    """What MATLAB's save -v7.3 writes: the MAT header (version 0x0200) in a 512-byte user
    block, then an HDF5 file (only its signature here)."""
    return header(0x0200).ljust(512, b"\x00") + b"\x89HDF\r\n\x1a\n" + bytes(64)


def struct_head(name: str, fields: list[str]) -> bytes:
    """A scalar struct's subelements before its fields: flags, dimensions, name, field names."""
    width = max(len(field) for field in fields) + 1
    names = b"".join(field.encode().ljust(width, b"\x00") for field in fields)
    return (
        matrix_head(name, (1, 1), class_code=STRUCT)
        + tag(MI_INT32, 4)
        + padded(struct.pack("<i", width))
        + tag(MI_INT8, len(names))
        + padded(names)
    )


def struct_element(name: str, fields: dict[str, np.ndarray]) -> bytes:
    """An uncompressed scalar struct of double fields (each a matrix element without a name)."""
    content = struct_head(name, list(fields)) + b"".join(matrix("", values) for values in fields.values())
    return tag(MI_MATRIX, len(content)) + content


def struct_bomb(name: str, data_bytes: int, after: dict[str, np.ndarray]) -> bytes:
    """A compressed scalar struct whose first field, ``junk``, is a double row of ``data_bytes``
    of zeros (a whole number of blocks), followed by the fields ``after``: a few kilobytes that
    inflate to ``data_bytes`` before the fields after it can be read. Its blocks are deflated
    once and repeated, so its checksum is wrong: a reader that inflates it to the end fails."""
    assert data_bytes % BLOCK == 0
    junk_head = matrix_head("", (1, data_bytes // 8)) + tag(MI_DOUBLE, data_bytes)
    rest = b"".join(matrix("", values) for values in after.values())
    head = struct_head(name, ["junk", *after])
    size = len(head) + 8 + len(junk_head) + data_bytes + len(rest)
    compressor = zlib.compressobj(9)
    start = compressor.compress(tag(MI_MATRIX, size) + head + tag(MI_MATRIX, len(junk_head) + data_bytes))
    start += compressor.compress(junk_head) + compressor.flush(zlib.Z_FULL_FLUSH)
    block = compressor.compress(bytes(BLOCK)) + compressor.flush(zlib.Z_FULL_FLUSH)
    body = start + block * (data_bytes // BLOCK) + compressor.compress(rest) + compressor.flush()
    return tag(MI_COMPRESSED, len(body)) + body
