"""Reading record files: excitation x and response y with their sampling rate and operating
conditions, as CSV, NPZ or MAT.

CSV: optional comment lines (``# fs=1500``, conditions ``# temperature=12.5 °C``), a header
naming the columns, then one row of values a line; ``narxwatch simulate`` writes the header
``x,y``. NPZ: arrays ``x`` and ``y``, a scalar ``fs`` and a scalar member per condition (no
unit), loaded without pickle. MAT: variables of a MATLAB v4/v5 file
(:mod:`recordfiles.matfiles`), with the sampling rate in a variable ``fs`` or ``Fs``. Parsing works
on bytes so that an upload and a file given to the command line go through the same checks; the
simulator writes the CSV and NPZ layouts (``recordfiles.writer``).

Published files are read as they are (:class:`Layout` names the signals to take as x and y):
Silverbox's ``"V1","V2",`` (fs = 10⁷/2¹⁴ Hz), F-16's ``"Force",…,"Acceleration3","Fs",`` and
MAT variables ``Force``, ``Acceleration`` (3×N), ``Fs``, and Wiener–Hammerstein's grouped
columns ``"r",,,…,"u",,,…,"y",,,…,"fs",``. One naming rule for both formats: a name is a column
or a variable; where a name covers several signals (a header cell followed by empty ones, or a
matrix), ``NAMEk`` is its k-th, counted from 1. A CSV column named ``fs`` (any case) gives the
sampling rate in its first row; where a CSV states none, a column named ``t`` or ``time`` gives
it by its steps, when the layout asks (``Layout.times``: the command line does). The trailing
comma MATLAB's writers end each line with does not start a column (an empty last header cell
over an empty first-row cell).
"""

from __future__ import annotations

import array
import csv
import io
import itertools
import math
import re
import struct
import tokenize
import zipfile
import zlib
from collections.abc import Callable, Iterable, Iterator, Sequence
from dataclasses import dataclass, replace
from pathlib import Path
from typing import TypeVar

import numpy as np

from models.errors import InputError
from recordfiles import matfiles
from recordfiles.channels import checked_channels
from recordfiles.conditions import (
    MAX_CONDITIONS,
    Condition,
    check_name,
    checked_conditions,
    too_many_conditions,
)

SILVERBOX_FS = 1e7 / 2**14  # Hz: the benchmark's 10 MHz clock divided by 2¹⁴
ZIP_MAGIC = b"PK\x03\x04"
_FS_COMMENT = re.compile(r"^#\s*fs\s*=\s*(?P<fs>\S+)\s*$", re.IGNORECASE)
# A comment line whose first word is followed by "=" states a condition: "# NAME=VALUE [UNIT]".
# Any other comment line is prose, and ignored.
_CONDITION_COMMENT = re.compile(r"^#\s*(?P<name>[^\s=]+)\s*=\s*(?P<value>\S*)(?:\s+(?P<unit>.*?))?\s*$")
_NUMBERED = re.compile(r"(?P<base>.*?)(?P<k>\d+)")
# A CSV column of acquisition times [s] is named so (in any case); its steps give the rate of a
# file that states none (``Layout.times``).
TIME_COLUMNS = ("t", "time")
# Steps of a column of times may differ from their mean by this share: times written rounded (six
# significant digits over a long record) differ by far less, a record with gaps or a variable-step
# solver's log by more.
TIME_STEP_TOLERANCE = 0.01
READABLE = (".csv", ".npz", ".mat")
# A MAT struct is read in order up to its fields named, its other fields skipped but inflated: at
# most this many times the bytes the signals may take (a Simulink log with its time beside x and
# y takes one and a half).
STRUCT_BUDGET = 4

# An NPZ record holds these members and, beside them, a scalar member per condition.
NPZ_MEMBERS = ("x.npy", "y.npy", "fs.npy")
MAX_NPZ_MEMBERS = len(NPZ_MEMBERS) + MAX_CONDITIONS
# Room for a member's .npy header (numpy writes 128 bytes; version 2 allows more) over its data.
NPY_HEADER_BYTES = 4096
# ``fs`` and each condition are one number, ``fs`` possibly written as text: "1500" as a <U4
# array takes 16 bytes.
SCALAR_BYTES = 64
# numpy writes 46 bytes plus the name and a 20-byte ZIP64 field per member: the most members a
# record may have, with names of 36 characters, take about 2 kB. This leaves room for other
# writers' extra fields (and for naming a few members too many) while keeping zipfile from
# building a long member list.
CENTRAL_DIRECTORY_BYTES = 4096
# Lines a CSV may have beyond its rows (the fs comment, the header, blank lines), counted before
# it is split into lines.
CSV_SLACK_LINES = 64
# Columns a CSV may have, counted on a line's separators before anything is built per cell: a
# set of as many records as a refinement fits with a reference signal beside each x and y (as
# Wiener–Hammerstein's r, u, y groups), and room for a time column, fs and other channels.
MAX_CSV_COLUMNS = 512
# Characters a CSV line may have: that many cells of up to 64 characters (a float64 takes 24).
MAX_CSV_LINE = 64 * MAX_CSV_COLUMNS
# What str.splitlines ends a line at, besides "\n": counted with it, the lines of a text are
# known before it is split.
_LINE_BREAKS = ("\r", "\v", "\f", "\x1c", "\x1d", "\x1e", "\x85", "\u2028", "\u2029")
# A CSV is split into lines a block of about this many characters at a time.
_CSV_BLOCK = 1 << 16
# Why a member that is more than one number is refused, for a file of several channels (y1, y2, …).
_AS_CONDITION = "; every member beside x, y and fs is an operating condition"
_END_OF_CENTRAL_DIRECTORY = struct.Struct("<4s4H2LH")
_ZIP64_LOCATOR = b"PK\x06\x07"


@dataclass(frozen=True)
class RecordFile:
    """Signals read from a file; ``fs`` is None when the file does not state it. ``conditions``
    are checked (:func:`recordfiles.conditions.checked_conditions`) and sorted by name. A record of
    several responses has y of shape (N, K), its columns named by ``channels``
    (:mod:`recordfiles.channels`); one of one response has y of shape (N,) and no channels."""

    x: np.ndarray
    y: np.ndarray
    fs: float | None
    conditions: tuple[Condition, ...] = ()
    channels: tuple[str, ...] = ()


@dataclass(frozen=True)
class Layout:
    """Which signals of a file are x and y (CSV column, NPZ member or MAT variable names, ``NAMEk``
    for the k-th of a group or matrix), and the sampling rate to take when the file states none.
    ``channels``, when given, name the responses of a record of several, read instead of ``y``
    and named as given; ``times``, that a CSV stating no rate gives it by a column of times."""

    x: str = "x"
    y: str = "y"
    fs: float | None = None
    channels: tuple[str, ...] = ()
    # Where a CSV states no rate, take it from its column of times (TIME_COLUMNS), if it has one.
    # The command line does; the service does not, whose structures state their rate.
    times: bool = False

    @property
    def responses(self) -> tuple[str, ...]:
        """The names of the signals read as responses."""
        return self.channels or (self.y,)


DEFAULT_LAYOUT = Layout()
NamedRecord = tuple[Layout, RecordFile]  # a record and the layout (signal names) it was read with
Parsed = TypeVar("Parsed", RecordFile, tuple[NamedRecord, ...])
# How a name selects a signal, for the command line's and the API's help.
NAMING_HELP = (
    "NAMEk is the k-th column of a group (a header cell followed by empty ones) or the k-th row or "
    "column of a matrix (whose longer dimension holds the samples), counted from 1"
)
SILVERBOX = Layout("V1", "V2", SILVERBOX_FS)


class RecordTooLargeError(InputError):
    """The record would unpack to more than the allowed number of bytes."""


def record_samples(max_bytes: int, channels: int = 1) -> int:
    """The most samples a record within ``max_bytes`` holds: x and its ``channels`` responses as
    float64, as an NPZ has them.

    Applied to every format, so that short numbers ("0,1" is 4 bytes a sample) cannot make a
    body within the limit unpack to many times its size in Python objects and arrays.
    """
    return max_bytes // ((1 + channels) * np.float64().nbytes)


def too_many_samples(what: str, max_samples: int, channels: int = 1) -> RecordTooLargeError:
    of = f" of {channels} channels" if channels > 1 else ""
    return RecordTooLargeError(
        f"{what} more than {max_samples} samples; a record{of} may hold at most {max_samples} samples "
        f"(NARXWATCH_MAX_UPLOAD_BYTES / {8 * (channels + 1)})"
    )


def read_record(path: str | Path, layout: Layout = DEFAULT_LAYOUT) -> RecordFile:
    """Read a ``.csv``, ``.npz`` or ``.mat`` record, with a message naming the file on any failure."""
    return _naming(Path(path), lambda data, suffix: parse_record(data, suffix, layout))


def read_record_set(path: str | Path, layout: Layout = DEFAULT_LAYOUT) -> tuple[NamedRecord, ...]:
    """The records a ``.csv``, ``.npz`` or ``.mat`` file holds (:func:`parse_record_set`), with a
    message naming the file on any failure."""
    return _naming(Path(path), lambda data, suffix: parse_record_set(data, suffix, layout))


def read_split_record(x_path: str | Path, y_path: str | Path, layout: Layout = DEFAULT_LAYOUT) -> RecordFile:
    """A record whose excitation and response are published in files of their own, as Bouc–Wen's
    test signals are (``uval_multisine.mat`` and ``yval_multisine.mat``, a 1×N variable each,
    named as its file): ``layout.x`` read from ``x_path``, ``layout.y`` from ``y_path``, each
    by the rules of :func:`read_record`. The rate is the one either file states (they must agree),
    else ``layout.fs``."""
    excitation = read_record(x_path, replace(layout, y=layout.x, channels=(), fs=None))
    response = read_record(y_path, replace(layout, x=layout.y, channels=(), fs=None))
    if excitation.x.size != response.y.size:
        raise InputError(
            f"{x_path} holds {excitation.x.size} samples of {layout.x!r} but {y_path} holds "
            f"{response.y.size} of {layout.y!r}; x and y must be sampled together"
        )
    stated = {record.fs for record in (excitation, response) if record.fs is not None}
    if len(stated) > 1:
        raise InputError(
            f"{x_path} states a sampling rate of {excitation.fs} Hz but {y_path} one of {response.fs} Hz"
        )
    rate = stated.pop() if stated else layout.fs
    return RecordFile(excitation.x, response.y, rate)


def _naming(path: Path, parse: Callable[[bytes, str], Parsed]) -> Parsed:
    """``parse`` of the file's bytes and its lower-case suffix; any InputError's message names the
    file (its type kept: the API answers a record too large with 413)."""
    suffix = path.suffix.lower()
    if suffix not in READABLE:
        raise InputError(f"{path}: unknown record format {suffix or '(none)'}; use .csv, .npz or .mat")
    try:
        data = path.read_bytes()
    except OSError as exc:
        raise InputError(f"{path}: cannot read the file ({exc.strerror})") from None
    try:
        return parse(data, suffix)
    except InputError as exc:
        raise type(exc)(f"{path}: {exc}") from None


def parse_record(
    data: bytes, suffix: str, layout: Layout = DEFAULT_LAYOUT, max_bytes: int | None = None
) -> RecordFile:
    """A record in the format of ``suffix`` (``.csv``, ``.npz`` or ``.mat``).

    With ``max_bytes``, its arrays may take at most that many bytes (an upload's limit), and so
    at most :func:`record_samples` samples.
    """
    if layout.channels:
        layout = replace(layout, channels=checked_channels(layout.channels))
    if suffix == ".csv":
        samples = None if max_bytes is None else record_samples(max_bytes, len(layout.responses))
        return parse_csv(data, samples, layout)
    if suffix == ".mat":
        return parse_mat(data, max_bytes, layout)
    if (layout.x, layout.y) != ("x", "y"):
        raise InputError(
            f"an NPZ record holds the arrays x and y (or the channels the parameters y name); the names "
            f"{layout.x!r} and {layout.y!r} select columns of a CSV or variables of a MAT file"
        )
    record = parse_npz(data, max_bytes, layout.channels)
    return record if record.fs is not None else replace(record, fs=layout.fs)


def parse_record_set(
    data: bytes, suffix: str, layout: Layout = DEFAULT_LAYOUT, max_bytes: int | None = None
) -> tuple[NamedRecord, ...]:
    """The records a file holds, each with the layout that reads it: one, or k when ``layout.x``
    and ``layout.y`` each name a whole group of k signals (CSV columns under one header cell, a
    MAT matrix), the pairs (x1, y1) … (xk, yk) — a benchmark's realisations side by side, as the
    Wiener–Hammerstein estimation file's ten and its test file's two.

    A group for one of x and y and a single signal (or a group of another size) for the other is
    refused: which signal goes with which would be a guess. The file is read once, whatever k.
    ``max_bytes`` bounds each record as for :func:`parse_record`, and a MAT file's variables
    together.
    """
    # Only CSV columns and MAT variables come in groups; a record of several channels reads its
    # responses as one record.
    if layout.channels or suffix not in (".csv", ".mat"):
        return ((layout, parse_record(data, suffix, layout, max_bytes)),)
    if suffix == ".csv":
        samples = None if max_bytes is None else record_samples(max_bytes)
        return tuple(_parse_csv(data, samples, layout, paired=True))
    return tuple(_parse_mat(data, max_bytes, layout, paired=True))


def _pairs(layout: Layout, counts: dict[str, int | None]) -> list[Layout]:
    """The layouts of the records :func:`parse_record_set` reads, from the signals each name
    of the file holds (``counts``): ``layout`` itself unless x or y names a whole group."""

    def group(name: str) -> tuple[str, int] | None:
        own = _named(name, counts)
        count = None if own is None else counts[own]
        return (own, count) if own is not None and count is not None and count > 1 else None

    inputs, outputs = group(layout.x), group(layout.y)
    if inputs is None and outputs is None:
        return [layout]
    if inputs is None or outputs is None:
        whole = inputs if outputs is None else outputs
        assert whole is not None  # not both None, as returned above
        raise InputError(
            _whole_group(*whole) + "; or, to read a record from each pair, name two groups of as many "
            "signals as x and y"
        )
    (x, k), (y, m) = inputs, outputs
    if k != m:
        raise InputError(
            f"{x!r} holds {k} signals and {y!r} {m}: as records, x and y must pair one to one (or name "
            f"one of each, such as {x}1 and {y}1)"
        )
    return [replace(layout, x=f"{x}{i}", y=f"{y}{i}") for i in range(1, k + 1)]


def _whole_group(group: str, count: int) -> str:
    """The refusal of a name that covers a whole group where one signal was wanted."""
    return f"{group!r} holds {count} signals: name one of them, {group}1 … {group}{count}"


def parse_csv(
    data: bytes | str, max_samples: int | None = None, layout: Layout = DEFAULT_LAYOUT
) -> RecordFile:
    """Parse CSV text: optional comment lines (``# fs=…``, ``# NAME=VALUE [UNIT]``), a header
    naming the columns, rows.

    The columns ``layout.x`` and ``layout.y`` are read, the rate from a ``# fs=`` comment or the
    first row of a column ``fs``, and a condition from each other comment line whose first word
    is followed by ``=``. A column ends at its first empty cell (``fs`` after one row),
    so that x and y of different lengths are told as such. With ``max_samples``, more rows than
    that are refused, grossly so before the text is split.
    """
    ((_, record),) = _parse_csv(data, max_samples, layout)
    return record


def _parse_csv(
    data: bytes | str, max_samples: int | None, layout: Layout, paired: bool = False
) -> list[NamedRecord]:
    """:func:`parse_csv`; ``paired``, the records of :func:`parse_record_set`, the text split and
    their columns read once."""
    try:
        text = data.decode("utf-8-sig") if isinstance(data, bytes) else data
    except UnicodeDecodeError:
        raise InputError("the CSV is not UTF-8 text") from None
    if max_samples is not None and _line_count(text) > max_samples + CSV_SLACK_LINES:
        raise too_many_samples("the CSV has", max_samples, len(layout.responses))
    lines = _csv_lines(text)
    comment_fs: float | None = None
    stated: list[Condition] = []
    for number, header in lines:
        if not (header.startswith("#") or not header.strip()):
            break
        line = header.strip()
        match = _FS_COMMENT.match(line)
        if match:
            comment_fs = _sampling_rate(match["fs"])
        elif match := _CONDITION_COMMENT.match(line):
            if len(stated) == MAX_CONDITIONS:  # a million such lines cost no more than seventeen
                raise too_many_conditions()
            stated.append(_condition_comment(match, number))
    else:
        raise InputError(f"the CSV has no header line naming its columns (such as '{layout.x},{layout.y}')")
    conditions = checked_conditions(stated)
    groups, count = header_groups(header)
    if count == 1 and (separator := next((s for s in ";\t" if s in header), None)):
        # What a spreadsheet set to a decimal comma exports; tab-separated text reads the same.
        raise InputError(
            f"the header {header[:80]!r} is one column: its values are separated by {separator!r}, "
            "where a CSV's are by ','; export the file comma-separated, with '.' as the decimal mark"
        )
    first = next(((number, line) for number, line in lines if line.strip()), None)
    if first is None:
        raise InputError("the CSV has a header but no data rows")
    first_row = first[1].split(",", count)
    _drop_trailing_comma(groups, count, first_row)
    widths = {name: len(columns) for name, columns in groups.items()}
    listing = "its columns are " + ", ".join(
        name if width == 1 else f"{name} ({width} columns, {name}1 … {name}{width})"
        for name, width in widths.items()
    )
    layouts = _pairs(layout, widths) if paired else [layout]
    wanted = []
    for each in layouts:
        for name in (each.x, *each.responses):
            group, k = _resolve(name, widths, f"the CSV has no column {name!r}; {listing}")
            wanted.append((name, groups[group][k]))
    rate_name = next((name for name in groups if name.lower() == "fs" and widths[name] == 1), None)
    fs = comment_fs
    if rate_name is not None:
        column = groups[rate_name][0]
        cell = first_row[column].strip() if column < len(first_row) else ""
        if cell:
            fs = _agreed_rate(comment_fs, _sampling_rate(cell), f"the column {rate_name!r}")
    signals = {name for name, _ in wanted}
    time_name = next(
        (
            name
            for name in groups
            if name.lower() in TIME_COLUMNS and widths[name] == 1 and name not in signals
        ),
        None,
    )
    timed = fs is None and layout.times and time_name is not None
    if timed:
        wanted.append((time_name, groups[time_name][0]))
    rows = itertools.chain([first], lines)
    read = _read_columns(rows, count, wanted, max_samples, len(layout.responses))
    if timed:
        fs = rate_of_times(read.pop(), f"the column {time_name!r}")
    columns = iter(read)
    return [
        (each, RecordFile(x, y, fs if fs is not None else each.fs, conditions, each.channels))
        for each, x, y in _signals_of(layouts, columns)
    ]


def _condition_comment(match: re.Match[str], number: int) -> Condition:
    """The condition a ``# NAME=VALUE [UNIT]`` comment on line ``number`` states."""
    name, value = match["name"], match["value"]
    if name.lower() == "fs":
        raise InputError(
            f"CSV line {number}: the '# fs=' comment holds the sampling rate in Hz, one number without "
            f"a unit; found {match.group(0)[:80]!r}"
        )
    try:
        number_value = float(value)
    except ValueError:
        raise InputError(
            f"CSV line {number}: the condition {name[:64]!r} has the value {value[:80]!r}, which is not a "
            "number; write a condition as '# NAME=VALUE' or '# NAME=VALUE UNIT', e.g. '# temperature=12.5 °C'"
        ) from None
    return Condition(name, number_value, match["unit"] or None)


def header_groups(line: str) -> tuple[dict[str, list[int]], int]:
    """The column groups a CSV header names (name → column indices) and its number of columns.

    An empty cell continues the group named to its left (cells before the first name belong to
    none). A header of more than :data:`MAX_CSV_COLUMNS` is refused on its separators, before
    any cell is built (the rows are split into at most as many cells as it has).
    """
    _check_columns(line, "the CSV header")
    try:
        cells = [cell.strip().strip('"').strip() for cell in next(csv.reader([line]), [])]
    except csv.Error as exc:
        raise InputError(f"the CSV header cannot be read ({exc})") from None
    groups: dict[str, list[int]] = {}
    current = None
    for column, cell in enumerate(cells):
        if cell:
            if cell in groups:
                raise InputError(f"the CSV header names the column {cell!r} twice")
            groups[cell] = [column]
            current = cell
        elif current is not None:
            groups[current].append(column)
    if not groups:
        raise InputError(f"the CSV header {line.strip()!r} names no column")
    return groups, len(cells)


def _check_columns(line: str, where: str) -> None:
    """Refuse a CSV line of more than :data:`MAX_CSV_COLUMNS` columns on its separators alone:
    splitting it would build an object a cell."""
    if (separators := line.count(",")) >= MAX_CSV_COLUMNS:
        raise InputError(
            f"{where} has {separators + 1} columns; a record file may have at most {MAX_CSV_COLUMNS} "
            "(x and y or channels, the column groups of a record set, time, fs)"
        )


def _drop_trailing_comma(groups: dict[str, list[int]], count: int, first_row: list[str]) -> None:
    """An empty last header cell over an empty cell in the first row is a trailing comma (as
    MATLAB's writers end every line), not a further column of the group to its left."""
    last = count - 1
    owner = next((name for name, columns in groups.items() if columns[-1] == last), None)
    if owner is None or len(groups[owner]) == 1:
        return
    if last >= len(first_row) or not first_row[last].strip():
        groups[owner].pop()


def _read_columns(
    rows: Iterable[tuple[int, str]],
    count: int,
    wanted: list[tuple[str, int]],
    max_samples: int | None,
    channels: int,
) -> list[np.ndarray]:
    """The numbers of each wanted (name, column), each down to its first empty cell, from the
    non-blank ``rows`` (line number, line). Cells past the header's ``count`` may only be empty
    (trailing commas); a line is split into at most ``count`` cells and the rest, so that no
    line costs more than its header's columns. Only the wanted cells' numbers are kept, 8 bytes
    each. ``max_samples`` bounds each record, of ``channels`` responses (the pairs of a set are
    records apart)."""
    values = [array.array("d") for _ in wanted]
    ends: list[int | None] = [None] * len(wanted)  # the line of a column's first empty cell
    columns = list(enumerate(wanted))
    read = 0
    for number, line in rows:
        if not line.strip():
            continue
        cells = line.split(",", count)
        if len(cells) > count and cells[count].replace(",", "").strip():
            raise InputError(f"CSV line {number}: expected {count} values, found {line.count(',') + 1}")
        if read == max_samples:
            raise too_many_samples("the CSV has", max_samples, channels)
        read += 1
        for index, (name, column) in columns:
            cell = cells[column] if column < len(cells) else ""
            try:
                value = float(cell)
            except ValueError:
                if cell.strip():
                    raise InputError(
                        f"CSV line {number}: {cell.strip()!r} in column {name!r} is not a number"
                    ) from None
                ends[index] = ends[index] or number
                continue
            if ends[index] is not None:
                raise InputError(
                    f"CSV line {number}: column {name!r} has a value after its empty cell "
                    f"on line {ends[index]}"
                )
            values[index].append(value)
    arrays = []
    for index, column in enumerate(values):  # each let go once copied: one column's copy at a time
        arrays.append(np.frombuffer(column, dtype=np.float64).copy())
        values[index] = array.array("d")
    return arrays


def _line_count(text: str) -> int:
    """The lines ``text.splitlines()`` would make, counted without making them."""
    breaks = text.count("\n") + sum(text.count(mark) for mark in _LINE_BREAKS) - text.count("\r\n")
    return breaks + (not text.endswith(("\n", *_LINE_BREAKS)))


def _csv_lines(text: str) -> Iterator[tuple[int, str]]:
    """The lines of a CSV (as ``str.splitlines`` ends them) with their numbers, from 1, split a
    block at a time so that they are never all held at once; a line longer than
    :data:`MAX_CSV_LINE` is refused on its length."""
    number = 0
    start = 0
    while start < len(text):
        # A block ends after a "\n", where a line ends whatever precedes it ("\r\n" included).
        newline = text.find("\n", start + _CSV_BLOCK)
        end = len(text) if newline < 0 else newline + 1
        for line in text[start:end].splitlines():
            number += 1
            if len(line) > MAX_CSV_LINE:
                _check_columns(line, f"CSV line {number}")  # the bound a wide header passes first
                raise InputError(
                    f"CSV line {number} has {len(line)} characters; a line of a record file may have at "
                    f"most {MAX_CSV_LINE} ({MAX_CSV_COLUMNS} columns of up to 64 characters)"
                )
            yield number, line
        start = end


def parse_mat(data: bytes, max_bytes: int | None = None, layout: Layout = DEFAULT_LAYOUT) -> RecordFile:
    """Read ``layout.x`` and ``layout.y`` from a MAT file, and the rate from a variable ``fs``/``Fs``.

    Only the variables these name are loaded (as a whole: ``Acceleration2`` loads the 3×N
    ``Acceleration``); with ``max_bytes`` they may take at most that many bytes as float64, and
    hold at most :func:`record_samples` samples, checked on their declared dimensions before
    any of their data is inflated.
    """
    ((_, record),) = _parse_mat(data, max_bytes, layout)
    return record


def _parse_mat(data: bytes, max_bytes: int | None, layout: Layout, paired: bool = False) -> list[NamedRecord]:
    """:func:`parse_mat`; ``paired``, the records of :func:`parse_record_set`, each variable
    loaded once."""
    mat = matfiles.list_mat(data)
    # A struct walked for its fields may be read to a few times what the signals may take.
    budget = None if max_bytes is None else STRUCT_BUDGET * max_bytes
    mat = matfiles.with_fields(mat, [layout.x, *layout.responses], budget)
    counts = {name: _signal_count(variable.shape) for name, variable in mat.variables.items()}
    layouts = _pairs(layout, counts) if paired else [layout]
    structs = [v.name for v in mat.variables.values() if v.class_name == "struct"]
    fields = f"; a struct's fields are named as {structs[0]}.FIELD" if structs else ""
    wanted = []
    for name in (name for each in layouts for name in (each.x, *each.responses)):
        variable, k = _resolve(
            name, counts, f"the MAT file has no variable {name!r}; it holds {mat.describe()}{fields}"
        )
        if counts[variable] is None:
            raise InputError(
                f"MAT variable {mat.variables[variable].describe()} is not a vector, nor a matrix whose "
                "longer dimension holds the samples"
            )
        wanted.append((mat.variables[variable], k))
    rate = next((v for name, v in mat.variables.items() if name.lower() == "fs"), None)
    if rate is not None and math.prod(rate.shape) != 1:
        raise InputError(f"MAT variable {rate.describe()} must be one number, the sampling rate")
    chosen = {variable.name: variable for variable, _ in wanted} | ({rate.name: rate} if rate else {})
    declared = matfiles.declared_bytes(list(chosen.values()))
    if max_bytes is not None and declared > max_bytes:
        raise RecordTooLargeError(
            f"the MAT variables {', '.join(chosen)} unpack to more than the upload limit "
            f"({declared} bytes as float64)"
        )
    arrays = matfiles.load_variables(mat, list(chosen.values()))
    records = []
    signals = (_signal(arrays[variable.name], k) for variable, k in wanted)
    for each, x, y in _signals_of(layouts, signals):
        channels = len(each.responses)
        if max_bytes is not None and x.size > record_samples(max_bytes, channels):
            raise too_many_samples(
                "the MAT file's signals have", record_samples(max_bytes, channels), channels
            )
        fs = _sampling_rate(arrays[rate.name]) if rate is not None else each.fs
        records.append((each, RecordFile(x, y, fs, channels=each.channels)))
    return records


def _signal_count(shape: tuple[int, ...]) -> int | None:
    """Signals a MAT variable holds: 1 for a vector, the shorter dimension of a matrix whose
    longer one holds the samples; None for a square matrix or more dimensions."""
    sizes = [size for size in shape if size != 1]
    if len(sizes) <= 1 or 0 in sizes:  # an empty one is refused for holding no values
        return 1
    if len(sizes) == 2 and sizes[0] != sizes[1]:
        return min(sizes)
    return None


def _signal(array: np.ndarray, k: int) -> np.ndarray:
    """The k-th signal (0-based) of a MAT variable of a shape :func:`_signal_count` accepts."""
    values = np.squeeze(array)
    if values.ndim == 2 and values.size:
        values = values[k] if values.shape[0] < values.shape[1] else values[:, k]
    return np.ascontiguousarray(values.reshape(-1), dtype=np.float64)


def _resolve(name: str, counts: dict[str, int | None], missing: str) -> tuple[str, int]:
    """The signal ``name`` denotes: (column group or variable, 0-based index of its signal).

    A name is a group's or variable's own; ``NAMEk`` is the k-th signal of NAME. A name matches
    in any case when no other does (a header ``X,Y`` is read as x and y).
    """
    own = _named(name, counts)
    if own is not None:
        count = counts[own]
        if count is None or count == 1:
            return own, 0
        raise InputError(_whole_group(own, count))
    match = _NUMBERED.fullmatch(name)
    base = _named(match["base"], counts) if match else None
    if match and base is not None:
        k, count = int(match["k"]), counts[base]
        if count is None or 1 <= k <= count:
            return base, k - 1  # a variable that is no signal is refused by the caller, with its shape
        raise InputError(
            f"{name!r} is out of range: {base!r} holds {count} signal(s), {base}1 … {base}{count}"
        )
    raise InputError(missing)


def _named(name: str, counts: dict[str, int | None]) -> str | None:
    """The group or variable called ``name``, or else the only one called so in another case."""
    if name in counts:
        return name
    alike = [other for other in counts if other.lower() == name.lower()]
    return alike[0] if len(alike) == 1 else None


def _signals_of(
    layouts: Sequence[Layout], signals: Iterable[np.ndarray]
) -> Iterator[tuple[Layout, np.ndarray, np.ndarray]]:
    """Each layout with its x and y (:func:`_check_lengths`), from the ``signals`` read for the
    layouts in turn: x, then its responses."""
    signals = iter(signals)
    for each in layouts:
        x, *responses = (next(signals) for _ in range(1 + len(each.responses)))
        yield each, x, _check_lengths(each, x, responses)


def _check_lengths(layout: Layout, x: np.ndarray, responses: list[np.ndarray]) -> np.ndarray:
    """y, after checking that x and every response hold values and as many as one another:
    the one response, or the channels as the columns of an (N, K) array."""
    if x.size == 0:
        raise InputError(f"x ({layout.x!r}) holds no values")
    role = "y" if not layout.channels else "the channel"
    for name, values in zip(layout.responses, responses, strict=True):
        if values.size == 0:
            raise InputError(f"{role} ({name!r}) holds no values")
        if values.size != x.size:
            raise InputError(
                f"x ({layout.x!r}) has {x.size} samples but {role} ({name!r}) has {values.size}; "
                f"x and {'y' if not layout.channels else 'every channel'} must be sampled together"
            )
    return np.column_stack(responses) if layout.channels else responses[0]


def rate_of_times(t: np.ndarray, where: str) -> float:
    """The sampling rate [Hz] of uniformly spaced times ``t`` [s]: (N − 1)/(t_N − t_1), from the
    span rather than a step, so that times written rounded give the rate all but exactly.
    ``where`` names the times in the message refusing any not uniformly spaced."""
    if t.size < 2:
        raise InputError(f"{where} holds {t.size} time(s); a sampling rate needs two or more")
    mean = (t[-1] - t[0]) / (t.size - 1)
    steps = np.diff(t)
    if not (np.isfinite(mean) and mean > 0) or np.max(np.abs(steps - mean)) > TIME_STEP_TOLERANCE * mean:
        raise InputError(
            f"{where} does not step uniformly forward (steps from {steps.min():.6g} s to "
            f"{steps.max():.6g} s), so it gives no sampling rate; state it with '# fs=' or --fs"
        )
    return _sampling_rate(1.0 / mean)


def _agreed_rate(stated: float | None, found: float, where: str) -> float:
    if stated is not None and stated != found:
        raise InputError(f"the '# fs=' comment says {stated:g} Hz but {where} says {found:g} Hz")
    return found


def parse_silverbox(data: bytes | str) -> RecordFile:
    """Parse a Silverbox CSV (``SNLS80mV.csv``, ``Schroeder80mV.csv``): columns ``V1`` and ``V2``.

    Other columns (the overload flags, filled in the first row only) are ignored.
    """
    return parse_csv(data, layout=SILVERBOX)


def parse_npz(data: bytes, max_bytes: int | None = None, channels: tuple[str, ...] = ()) -> RecordFile:
    """Parse an NPZ archive with arrays ``x``, ``y`` (or one array per channel, named as it, when
    ``channels`` are given), an optional scalar ``fs`` and a scalar member per condition, named as
    the condition (NPZ gives a condition no unit).

    Never unpickles, and never unpacks more than it may keep: the archive may hold only ``x``,
    ``y``, ``fs`` and at most :data:`MAX_CONDITIONS` conditions, in a central directory of
    bounded size; each member's declared size, then its .npy header's shape × item size, is
    checked before any of its data is decompressed. ``x`` and ``y`` together may hold
    ``max_bytes``, and x and the channels of a record of several; ``fs`` and each condition one
    number.
    """
    # A bare .npy or arbitrary bytes would otherwise reach numpy's pickle path.
    if not data.startswith(ZIP_MAGIC):
        raise InputError("the file is not a readable NPZ archive")
    _check_central_directory(data)
    budget = max_bytes if max_bytes is not None else np.inf
    signals = ("x", *(channels or ("y",)))
    try:
        with zipfile.ZipFile(io.BytesIO(data)) as archive:
            members = _checked_members(archive, budget, signals)
            arrays: list[np.ndarray] = []
            for name in signals:
                arrays.append(_read_member(archive, name, budget - sum(a.nbytes for a in arrays), signals))
            fs = (
                _sampling_rate(_read_member(archive, "fs", SCALAR_BYTES, signals))
                if "fs" in members
                else None
            )
            stated = [
                Condition(name, _condition_value(name, _read_member(archive, name, SCALAR_BYTES, signals)))
                for name in members
                if name not in (*signals, "fs")
            ]
    except InputError:
        raise
    except zipfile.BadZipFile:
        raise InputError("the file is not a readable NPZ archive") from None
    except (OSError, EOFError, ValueError, KeyError, NotImplementedError, RuntimeError, zlib.error) as exc:
        raise InputError(f"the NPZ archive is damaged or not made by numpy ({exc})") from None
    for name, member in zip(signals, arrays, strict=True):
        if member.dtype.kind not in "iuf":
            raise InputError(f"NPZ array {name!r} must be numeric, got dtype {member.dtype}")
    conditions = checked_conditions(stated)
    x, *responses = (np.asarray(member, dtype=np.float64) for member in arrays)
    if not channels:  # x and y as stored, whatever their shapes: the record's check judges them
        return RecordFile(x, responses[0], fs, conditions)
    y = _check_lengths(Layout(channels=channels), x.reshape(-1), [r.reshape(-1) for r in responses])
    return RecordFile(x.reshape(-1), y, fs, conditions, channels)


def _condition_value(name: str, member: np.ndarray) -> float:
    """The number an NPZ member holding a condition holds."""
    if member.dtype.kind not in "iuf":
        raise InputError(
            f"NPZ member {name!r} holds a condition, which must be a number; got dtype {member.dtype}"
        )
    if member.size != 1:
        raise InputError(
            f"NPZ member {name!r} holds {member.size} values (shape {member.shape}); "
            "a condition is one number" + _AS_CONDITION
        )
    return float(member.reshape(()))


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
            f"it may hold only the arrays x, y and fs and at most {MAX_CONDITIONS} conditions"
        )


def _checked_members(archive: zipfile.ZipFile, budget: float, signals: tuple[str, ...]) -> list[str]:
    """The names of the archive's arrays, after checking them and their declared sizes
    (``signals``: x and the responses)."""
    infos = archive.infolist()
    names = [info.filename for info in infos]
    if len(names) > MAX_NPZ_MEMBERS + len(signals) - 2:
        raise InputError(
            f"the NPZ holds {len(names)} members; a record holds the arrays x, y and fs and at most "
            f"{MAX_CONDITIONS} conditions"
        )
    unknown = sorted(name for name in names if not name.endswith(".npy"))
    if unknown:
        raise InputError(
            "the NPZ may hold only .npy arrays (x, y, fs and one number per condition); it also holds "
            + ", ".join(unknown)
        )
    if len(set(names)) != len(names):
        raise InputError("the NPZ holds the same array twice")
    members = [name.removesuffix(".npy") for name in names]
    missing = [name for name in signals if name not in members]
    if missing:
        needs = " and ".join(map(repr, signals)) if len(signals) == 2 else ", ".join(signals)
        raise InputError(
            f"the NPZ lacks array(s) {', '.join(missing)}; it needs {needs}"
            + (f"; it holds {', '.join(members)}" if len(signals) > 2 else "")
        )
    declared = dict(zip(members, (info.file_size for info in infos), strict=True))
    for name in members:
        if name in signals:
            continue
        if name != "fs":
            try:
                check_name(name)
            except InputError as exc:
                raise InputError(f"NPZ member {name!r}: {exc}") from None
        if declared[name] > NPY_HEADER_BYTES + SCALAR_BYTES:
            raise InputError(
                f"NPZ member {name!r} must be one number, but it unpacks to {declared[name]} bytes"
                + _AS_CONDITION * (name != "fs")
            )
    arrays = sum(declared[name] for name in signals)
    if arrays > budget + len(signals) * NPY_HEADER_BYTES:
        raise RecordTooLargeError(f"the NPZ's arrays unpack to more than the upload limit ({arrays} bytes)")
    return members


def _read_member(archive: zipfile.ZipFile, name: str, limit: float, signals: tuple[str, ...]) -> np.ndarray:
    """One .npy member, refused before allocation if it holds more than ``limit`` bytes
    (``signals``: the members that are x and the responses)."""
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
            if name not in signals:
                raise InputError(
                    f"NPZ member {name!r} must be one number, but its header declares shape {shape} "
                    f"of {dtype}" + _AS_CONDITION * (name != "fs")
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
