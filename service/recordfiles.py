"""Reading record files: excitation x and response y with their sampling rate, as CSV or NPZ.

CSV: an optional first comment line ``# fs=1500``, a header ``x,y``, then one ``x,y`` pair a
line. NPZ: arrays ``x`` and ``y`` and a scalar ``fs``, loaded without pickle. Parsing works on
bytes so that an upload and a file given to the command line go through the same checks; the
simulator writes these layouts (``simulator.recordfile``).

The Silverbox benchmark's CSV files (Wigren & Schoukens 2013) are read as they are published:
input ``V1`` as x, output ``V2`` as y, at fs = 10⁷/2¹⁴ Hz.
"""

from __future__ import annotations

import io
import math
import re
import struct
import tokenize
import zipfile
import zlib
from dataclasses import dataclass
from pathlib import Path

import numpy as np

from models.errors import InputError
from simulator.recordfile import FORMATS

SILVERBOX_FS = 1e7 / 2**14  # Hz: the benchmark's 10 MHz clock divided by 2¹⁴
ZIP_MAGIC = b"PK\x03\x04"
_FS_COMMENT = re.compile(r"^#\s*fs\s*=\s*(?P<fs>\S+)\s*$", re.IGNORECASE)

# An NPZ record holds these members and nothing else.
NPZ_MEMBERS = ("x.npy", "y.npy", "fs.npy")
# Room for a member's .npy header (numpy writes 128 bytes; version 2 allows more) over its data.
NPY_HEADER_BYTES = 4096
# ``fs`` is one number, possibly written as text: "1500" as a <U4 array takes 16 bytes.
FS_BYTES = 64
# numpy writes 46 bytes plus the name and a 20-byte ZIP64 field per member: three members take
# about 200 bytes. This leaves room for other writers' extra fields (and for naming a few
# members too many) while keeping zipfile from building a long member list.
CENTRAL_DIRECTORY_BYTES = 1024
# Lines a CSV may have beyond its rows (the fs comment, the header, blank lines), counted before
# it is split into lines.
CSV_SLACK_LINES = 64
_END_OF_CENTRAL_DIRECTORY = struct.Struct("<4s4H2LH")
_ZIP64_LOCATOR = b"PK\x06\x07"


@dataclass(frozen=True)
class RecordFile:
    """Signals read from a file; ``fs`` is None when the file does not state it."""

    x: np.ndarray
    y: np.ndarray
    fs: float | None


class RecordTooLargeError(InputError):
    """The record would unpack to more than the allowed number of bytes."""


def record_samples(max_bytes: int) -> int:
    """The most samples a record within ``max_bytes`` holds: x and y as float64, as an NPZ has them.

    Applied to every format, so that short numbers ("0,1" is 4 bytes a sample) cannot make a
    body within the limit unpack to many times its size in Python objects and arrays.
    """
    return max_bytes // (2 * np.float64().nbytes)


def too_many_samples(what: str, max_samples: int) -> RecordTooLargeError:
    return RecordTooLargeError(
        f"{what} more than {max_samples} samples; a record may hold at most {max_samples} samples "
        "(NARXWATCH_MAX_UPLOAD_BYTES / 16)"
    )


def read_record(path: str | Path) -> RecordFile:
    """Read a ``.csv`` or ``.npz`` record, with a message naming the file on any failure."""
    path = Path(path)
    suffix = path.suffix.lower()
    if suffix not in FORMATS:
        raise InputError(f"{path}: unknown record format {suffix or '(none)'}; use .csv or .npz")
    try:
        data = path.read_bytes()
    except OSError as exc:
        raise InputError(f"{path}: cannot read the file ({exc.strerror})") from None
    try:
        return parse_csv(data) if suffix == ".csv" else parse_npz(data)
    except InputError as exc:
        raise InputError(f"{path}: {exc}") from None


def parse_csv(data: bytes | str, max_samples: int | None = None) -> RecordFile:
    """Parse CSV text: optional ``# fs=…`` comment, header ``x,y``, numeric rows.

    With ``max_samples``, more rows than that are refused, grossly so before the text is split.
    """
    try:
        text = data.decode("utf-8-sig") if isinstance(data, bytes) else data
    except UnicodeDecodeError:
        raise InputError("the CSV is not UTF-8 text") from None
    if max_samples is not None and text.count("\n") > max_samples + CSV_SLACK_LINES:
        raise too_many_samples("the CSV has", max_samples)
    lines = text.splitlines()
    fs: float | None = None
    index = 0
    while index < len(lines) and (lines[index].startswith("#") or not lines[index].strip()):
        match = _FS_COMMENT.match(lines[index].strip())
        if match:
            fs = _sampling_rate(match["fs"])
        index += 1
    if index == len(lines):
        raise InputError("the CSV has no header line 'x,y'")
    header = [cell.strip().strip('"').lower() for cell in lines[index].split(",")]
    if header != ["x", "y"]:
        raise InputError(f"the CSV header must be 'x,y', found {lines[index].strip()!r}")
    rows = lines[index + 1 :]
    values = np.empty((len(rows), 2))
    count = 0
    for number, line in enumerate(rows, start=index + 2):
        if not line.strip():
            continue
        cells = line.split(",")
        if len(cells) != 2:
            raise InputError(f"CSV line {number}: expected 2 values 'x,y', found {len(cells)}")
        if count == max_samples:
            raise too_many_samples("the CSV has", max_samples)
        try:
            values[count] = float(cells[0]), float(cells[1])
        except ValueError:
            raise InputError(f"CSV line {number}: {line.strip()!r} is not two numbers") from None
        count += 1
    if count == 0:
        raise InputError("the CSV has a header but no data rows")
    return RecordFile(values[:count, 0].copy(), values[:count, 1].copy(), fs)


def parse_silverbox(data: bytes | str) -> RecordFile:
    """Parse a Silverbox CSV (``SNLS80mV.csv``, ``Schroeder80mV.csv``): columns ``V1`` and ``V2``.

    Other columns (the overload flags, the empty one a trailing comma makes) are ignored.
    """
    try:
        text = data.decode("utf-8-sig") if isinstance(data, bytes) else data
    except UnicodeDecodeError:
        raise InputError("the Silverbox file is not UTF-8 text") from None
    header, _, body = text.partition("\n")
    names = [cell.strip().strip('"') for cell in header.split(",")]
    if "V1" not in names or "V2" not in names:
        raise InputError(f"a Silverbox file has columns 'V1' and 'V2'; the header is {header.strip()!r}")
    if not body.strip():
        raise InputError("the Silverbox file has a header but no data rows")
    try:
        values = np.loadtxt(
            io.StringIO(body), delimiter=",", usecols=(names.index("V1"), names.index("V2")), ndmin=2
        )
    except ValueError as exc:
        raise InputError(f"the Silverbox file has a row that is not numbers ({exc})") from None
    return RecordFile(values[:, 0].copy(), values[:, 1].copy(), SILVERBOX_FS)


def parse_npz(data: bytes, max_bytes: int | None = None) -> RecordFile:
    """Parse an NPZ archive with arrays ``x``, ``y`` and optional scalar ``fs``.

    Never unpickles, and never unpacks more than it may keep: the archive may hold only the
    members ``x``, ``y`` and ``fs``, in a central directory of bounded size; each member's
    declared size, then its .npy header's shape × item size, is checked before any of its data
    is decompressed. ``x`` and ``y`` together may hold ``max_bytes``; ``fs`` one number.
    """
    # A bare .npy or arbitrary bytes would otherwise reach numpy's pickle path.
    if not data.startswith(ZIP_MAGIC):
        raise InputError("the file is not a readable NPZ archive")
    _check_central_directory(data)
    budget = max_bytes if max_bytes is not None else np.inf
    try:
        with zipfile.ZipFile(io.BytesIO(data)) as archive:
            members = _checked_members(archive, budget)
            x = _read_member(archive, "x", budget)
            y = _read_member(archive, "y", budget - x.nbytes)
            fs = _sampling_rate(_read_member(archive, "fs", FS_BYTES)) if "fs" in members else None
    except InputError:
        raise
    except zipfile.BadZipFile:
        raise InputError("the file is not a readable NPZ archive") from None
    except (OSError, EOFError, ValueError, KeyError, NotImplementedError, RuntimeError, zlib.error) as exc:
        raise InputError(f"the NPZ archive is damaged or not made by numpy ({exc})") from None
    for name, array in (("x", x), ("y", y)):
        if array.dtype.kind not in "iuf":
            raise InputError(f"NPZ array {name!r} must be numeric, got dtype {array.dtype}")
    return RecordFile(np.asarray(x, dtype=np.float64), np.asarray(y, dtype=np.float64), fs)


def _check_central_directory(data: bytes) -> None:
    """Refuse an archive whose member list zipfile would have to build at length.

    zipfile reads the whole central directory, whatever its size, into a list of members
    before any can be refused by name; a body of nothing but entries would cost far more
    memory than its size. Its size is read here from the end record first.
    """
    end = data.rfind(b"PK\x05\x06", max(0, len(data) - _END_OF_CENTRAL_DIRECTORY.size - 0xFFFF))
    if end < 0 or len(data) - end < _END_OF_CENTRAL_DIRECTORY.size:
        raise InputError("the file is not a readable NPZ archive")
    fields = _END_OF_CENTRAL_DIRECTORY.unpack_from(data, end)
    entries, directory_size = fields[4], fields[5]
    if data[max(0, end - 20) : end].startswith(_ZIP64_LOCATOR):
        raise InputError("the NPZ is a ZIP64 archive; a record within the upload limit never needs one")
    if directory_size > CENTRAL_DIRECTORY_BYTES:
        raise InputError(
            f"the NPZ lists {entries} members in a {directory_size}-byte directory; "
            f"it may hold only the arrays x, y and fs"
        )


def _checked_members(archive: zipfile.ZipFile, budget: float) -> set[str]:
    """The names of the archive's arrays, after checking them against the declared sizes."""
    infos = archive.infolist()
    names = [info.filename for info in infos]
    unknown = sorted(set(names) - set(NPZ_MEMBERS))
    if unknown:
        raise InputError(f"the NPZ may hold only the arrays x, y and fs; it also holds {', '.join(unknown)}")
    if len(set(names)) != len(names):
        raise InputError("the NPZ holds the same array twice")
    members = {name.removesuffix(".npy") for name in names}
    missing = {"x", "y"} - members
    if missing:
        raise InputError(f"the NPZ lacks array(s) {', '.join(sorted(missing))}; it needs 'x' and 'y'")
    declared = {info.filename.removesuffix(".npy"): info.file_size for info in infos}
    if declared.get("fs", 0) > NPY_HEADER_BYTES + FS_BYTES:
        raise InputError(f"NPZ member 'fs' must be one number, but it unpacks to {declared['fs']} bytes")
    arrays = declared["x"] + declared["y"]
    if arrays > budget + 2 * NPY_HEADER_BYTES:
        raise RecordTooLargeError(f"the NPZ's arrays unpack to more than the upload limit ({arrays} bytes)")
    return members


def _read_member(archive: zipfile.ZipFile, name: str, limit: float) -> np.ndarray:
    """One .npy member, refused before allocation if it holds more than ``limit`` bytes."""
    with archive.open(f"{name}.npy") as stream:
        version = np.lib.format.read_magic(stream)
        read_header = {
            (1, 0): np.lib.format.read_array_header_1_0,
            (2, 0): np.lib.format.read_array_header_2_0,
        }
        if version not in read_header:
            raise InputError(f"NPZ member {name!r} has an unsupported .npy version {version}")
        try:
            shape, fortran_order, dtype = read_header[version](stream)
        except (ValueError, SyntaxError, tokenize.TokenError) as exc:
            # numpy reads the header as a Python literal: a cut-off one fails in its tokenizer.
            raise InputError(f"NPZ member {name!r} has a malformed .npy header ({exc})") from None
        if dtype.hasobject:
            raise InputError(f"NPZ member {name!r} holds Python objects, which are never unpickled")
        size = math.prod(shape) * dtype.itemsize  # exact: np.prod would wrap around
        if size > limit:
            if name == "fs":
                raise InputError(
                    f"NPZ member 'fs' must be one number, but its header declares shape {shape} of {dtype}"
                )
            raise RecordTooLargeError(
                f"the NPZ's arrays unpack to more than the upload limit ({name!r}: {size} bytes)"
            )
        raw = stream.read(size)
        if len(raw) != size:
            raise InputError(f"NPZ member {name!r} is shorter than its header says")
    return np.frombuffer(raw, dtype=dtype).reshape(shape, order="F" if fortran_order else "C")


def _sampling_rate(value: object) -> float:
    try:
        fs = float(np.asarray(value, dtype=np.float64).reshape(()))
    except (TypeError, ValueError):
        raise InputError(f"the sampling rate {value!r} is not a number") from None
    if not (np.isfinite(fs) and fs > 0):
        raise InputError(f"the sampling rate must be a positive number, got {fs}")
    return fs
