"""Writing record files: excitation x and response y with their sampling rate, as CSV or NPZ.

The layouts are the ones ``service.recordfiles`` reads: CSV with a first comment line
``# fs=1500``, a header ``x,y`` and one ``x,y`` pair a line; NPZ with arrays ``x`` and ``y``
and a scalar ``fs``. The simulator only writes records; reading them (from uploads and from
files given to the command line) belongs to the service.
"""

from __future__ import annotations

import io
from pathlib import Path

import numpy as np

from models.errors import InputError

FORMATS = (".csv", ".npz")


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
    # 17 significant digits: a rate such as 1500.0000001 reads back as itself, not as 1500.
    buffer.write(f"# fs={fs:.17g}\nx,y\n")
    np.savetxt(buffer, np.column_stack([x, y]), delimiter=",", fmt="%.17g")
    return buffer.getvalue()


def dump_npz(x: np.ndarray, y: np.ndarray, fs: float) -> bytes:
    buffer = io.BytesIO()
    np.savez(buffer, x=np.asarray(x, dtype=np.float64), y=np.asarray(y, dtype=np.float64), fs=np.float64(fs))
    return buffer.getvalue()
