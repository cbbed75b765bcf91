"""Writing record files: excitation x and the response(s) with their sampling rate, as CSV or NPZ.

The single-response layouts are the ones ``recordfiles.reader`` reads: CSV with a first comment
line ``# fs=1500``, a header ``x,y`` and one ``x,y`` pair a line; NPZ with arrays ``x`` and ``y``
and a scalar ``fs``. A record of several response channels (the chain's masses, the rig's two)
names them in place of ``y`` (columns or members ``y1,y2,…``), and a record's operating
conditions (its temperature in °C) follow the rate as comment lines ``# temperature=12.5 °C``
(the syntax of ``recordfiles.reader``, with the unit of :data:`UNITS`) or as scalar NPZ members
of that name, which the format gives no unit. The simulator writes records with it; the service
reads them (uploads, and files given to the command line) with :mod:`recordfiles.reader`.
"""

from __future__ import annotations

import io
from collections.abc import Mapping
from pathlib import Path

import numpy as np

from models.errors import InputError

FORMATS = (".csv", ".npz")
# The units of the conditions the simulator states.
UNITS = {"temperature": "°C"}
Responses = np.ndarray | Mapping[str, np.ndarray]


def write_record(
    path: str | Path, x: np.ndarray, y: Responses, fs: float, conditions: Mapping[str, float] | None = None
) -> Path:
    """Write a record as CSV or NPZ, chosen by the file's suffix. ``y`` is one response, or the
    response channels by name; ``conditions`` are operating variables by name."""
    path = Path(path)
    suffix = path.suffix.lower()
    if suffix not in FORMATS:
        raise InputError(f"{path}: unknown record format {suffix or '(none)'}; use .csv or .npz")
    path.parent.mkdir(parents=True, exist_ok=True)
    if suffix == ".csv":
        path.write_text(dump_csv(x, y, fs, conditions))
    else:
        path.write_bytes(dump_npz(x, y, fs, conditions))
    return path


def channels(y: Responses) -> dict[str, np.ndarray]:
    """The response channels by name: a single array is the channel ``y``."""
    return dict(y) if isinstance(y, Mapping) else {"y": y}


def dump_csv(x: np.ndarray, y: Responses, fs: float, conditions: Mapping[str, float] | None = None) -> str:
    responses = channels(y)
    buffer = io.StringIO()
    # 17 significant digits: a rate such as 1500.0000001 reads back as itself, not as 1500.
    buffer.write(f"# fs={fs:.17g}\n")
    for name, value in (conditions or {}).items():
        unit = UNITS.get(name)
        buffer.write(f"# {name}={value:.17g}" + (f" {unit}" if unit else "") + "\n")
    buffer.write(",".join(["x", *responses]) + "\n")
    np.savetxt(buffer, np.column_stack([x, *responses.values()]), delimiter=",", fmt="%.17g")
    return buffer.getvalue()


def dump_npz(x: np.ndarray, y: Responses, fs: float, conditions: Mapping[str, float] | None = None) -> bytes:
    members = {name: np.asarray(values, dtype=np.float64) for name, values in channels(y).items()}
    scalars = {name: np.float64(value) for name, value in (conditions or {}).items()}
    buffer = io.BytesIO()
    np.savez(buffer, x=np.asarray(x, dtype=np.float64), **members, fs=np.float64(fs), **scalars)
    return buffer.getvalue()
