"""Record files: excitation x and response y with their sampling rate, as CSV or NPZ.

CSV: an optional first comment line ``# fs=1500``, a header ``x,y``, then one ``x,y`` pair a
line. NPZ: arrays ``x`` and ``y`` and a scalar ``fs``, loaded without pickle. Parsing works on
bytes so that an upload and a file on disk go through the same checks.
"""

from __future__ import annotations

import io
import re
import zipfile
from dataclasses import dataclass
from pathlib import Path

import numpy as np

from models.errors import InputError

FORMATS = (".csv", ".npz")
ZIP_MAGIC = b"PK\x03\x04"
_FS_COMMENT = re.compile(r"^#\s*fs\s*=\s*(?P<fs>\S+)\s*$", re.IGNORECASE)


@dataclass(frozen=True)
class RecordFile:
    """Signals read from a file; ``fs`` is None when the file does not state it."""

    x: np.ndarray
    y: np.ndarray
    fs: float | None


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


def write_record(path: str | Path, x: np.ndarray, y: np.ndarray, fs: float) -> Path:
    """Write a record as CSV or NPZ, chosen by the file's suffix."""
    path = Path(path)
    suffix = path.suffix.lower()
    if suffix not in FORMATS:
        raise InputError(f"{path}: unknown record format {suffix or '(none)'}; use .csv or .npz")
    path.parent.mkdir(parents=True, exist_ok=True)
    if suffix == ".csv":
        path.write_text(dump_csv(x, y, fs))
    else:
        path.write_bytes(dump_npz(x, y, fs))
    return path


def dump_csv(x: np.ndarray, y: np.ndarray, fs: float) -> str:
    buffer = io.StringIO()
    buffer.write(f"# fs={fs:g}\nx,y\n")
    # 17 significant digits round-trip every double exactly.
    np.savetxt(buffer, np.column_stack([x, y]), delimiter=",", fmt="%.17g")
    return buffer.getvalue()


def dump_npz(x: np.ndarray, y: np.ndarray, fs: float) -> bytes:
    buffer = io.BytesIO()
    np.savez(buffer, x=np.asarray(x, dtype=np.float64), y=np.asarray(y, dtype=np.float64), fs=np.float64(fs))
    return buffer.getvalue()


def parse_csv(data: bytes | str) -> RecordFile:
    """Parse CSV text: optional ``# fs=…`` comment, header ``x,y``, numeric rows."""
    try:
        text = data.decode("utf-8-sig") if isinstance(data, bytes) else data
    except UnicodeDecodeError:
        raise InputError("the CSV is not UTF-8 text") from None
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
        try:
            values[count] = float(cells[0]), float(cells[1])
        except ValueError:
            raise InputError(f"CSV line {number}: {line.strip()!r} is not two numbers") from None
        count += 1
    if count == 0:
        raise InputError("the CSV has a header but no data rows")
    return RecordFile(values[:count, 0].copy(), values[:count, 1].copy(), fs)


def parse_npz(data: bytes) -> RecordFile:
    """Parse an NPZ archive with arrays ``x``, ``y`` and optional scalar ``fs``; never unpickles."""
    # np.load would otherwise take a bare .npy or treat unknown bytes as a pickle.
    if not data.startswith(ZIP_MAGIC):
        raise InputError("the file is not a readable NPZ archive")
    try:
        with np.load(io.BytesIO(data), allow_pickle=False) as archive:
            missing = {"x", "y"} - set(archive.files)
            if missing:
                raise InputError(f"the NPZ lacks array(s) {', '.join(sorted(missing))}; it needs 'x' and 'y'")
            x, y = archive["x"], archive["y"]
            fs = _sampling_rate(archive["fs"]) if "fs" in archive.files else None
    except InputError:
        raise
    except (zipfile.BadZipFile, OSError, EOFError):
        raise InputError("the file is not a readable NPZ archive") from None
    except ValueError as exc:
        raise InputError(f"the NPZ holds data that cannot be loaded safely ({exc})") from None
    for name, array in (("x", x), ("y", y)):
        if not isinstance(array, np.ndarray):  # a zip member that is not a .npy file
            raise InputError(f"NPZ member {name!r} is not a numpy array")
        if array.dtype.kind not in "iuf":
            raise InputError(f"NPZ array {name!r} must be numeric, got dtype {array.dtype}")
    return RecordFile(np.asarray(x, dtype=np.float64), np.asarray(y, dtype=np.float64), fs)


def _sampling_rate(value: object) -> float:
    try:
        fs = float(np.asarray(value, dtype=np.float64).reshape(()))
    except (TypeError, ValueError):
        raise InputError(f"the sampling rate {value!r} is not a number") from None
    if not (np.isfinite(fs) and fs > 0):
        raise InputError(f"the sampling rate must be a positive number, got {fs}")
    return fs
