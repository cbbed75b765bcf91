"""Reading and writing model documents and record sets for the command line."""

from __future__ import annotations

import csv
import json
from collections.abc import Sequence
from pathlib import Path
from typing import Annotated, Any

import typer

from models.errors import InputError
from models.fnarx import FNARX
from models.terms import Term, parse_terms
from recordfiles.reader import DEFAULT_LAYOUT, NAMING_HELP, Layout, RecordFile, read_record_set
from simulator.theory import EXACT_TERMS

_SIGNAL_HELP = "The CSV column or MAT variable that holds {role} (default: {role}); " + NAMING_HELP + "."
# For the commands that take several records: how a file of realisations side by side is read.
RECORD_SET_HELP = (
    "Where --x and --y name groups of as many signals (u and y of the Wiener–Hammerstein files, ten "
    "realisations side by side), each pair is a record."
)
XName = Annotated[str | None, typer.Option("--x", help=_SIGNAL_HELP.format(role="x"))]
YName = Annotated[str | None, typer.Option("--y", help=_SIGNAL_HELP.format(role="y"))]


def signal_layout(x: str | None, y: str | None, base: Layout = DEFAULT_LAYOUT) -> Layout:
    """The layout to read records with: ``base`` with the names given on the command line, the
    rate of a CSV that states none from its column of times."""
    return Layout(x if x is not None else base.x, y if y is not None else base.y, base.fs, times=True)


# Names the paper rig's exact structure (SPEC §2) where a command takes terms: asked for by name,
# never assumed.
RIG = "2dof"


def read_terms(spec: str) -> tuple[Term, ...]:
    """Terms from a comma-separated list, from a JSON file holding a ``terms`` list (a model
    document or the output of ``narxwatch select --json``), or SPEC §2's named ``RIG``."""
    if spec == RIG:
        return EXACT_TERMS
    path = Path(spec)
    if path.suffix.lower() == ".json":
        document = read_json(path)
        if not isinstance(document, dict) or not isinstance(document.get("terms"), list):
            raise InputError(f"{path}: no 'terms' list in this JSON document")
        return parse_terms(document["terms"])
    return parse_terms(name for name in spec.split(",") if name.strip())


def read_json(path: Path) -> Any:
    try:
        return json.loads(path.read_text())
    except OSError as exc:
        raise InputError(f"{path}: cannot read the file ({exc.strerror})") from None
    except (json.JSONDecodeError, UnicodeDecodeError) as exc:
        raise InputError(f"{path}: not valid JSON ({exc})") from None


def write_json(path: Path, document: Any) -> None:
    path.parent.mkdir(parents=True, exist_ok=True)
    path.write_text(json.dumps(document, indent=1) + "\n")


def read_fault_mode(path: Path) -> tuple[FNARX, float | None]:
    """A fault-mode model and the sampling rate it was trained at, if recorded."""
    document = read_json(path)
    try:
        model = FNARX.from_document(document)
    except (KeyError, TypeError, ValueError) as exc:
        raise InputError(f"{path}: not a usable fault-mode model ({exc})") from None
    return model, document.get("metadata", {}).get("fs")


def read_records(
    paths: Sequence[Path], layout: Layout = DEFAULT_LAYOUT
) -> tuple[list[RecordFile], float | None]:
    """The files' records and their common sampling rate (:func:`read_record_sets`), in order."""
    sets, fs = read_record_sets(paths, layout)
    return [record for found in sets for record in found], fs


def read_record_sets(
    paths: Sequence[Path], layout: Layout = DEFAULT_LAYOUT
) -> tuple[list[tuple[RecordFile, ...]], float | None]:
    """Each file's records — one, or one a pair of signals where x and y name groups of as many
    (:func:`recordfiles.reader.parse_record_set`) — and their common sampling rate; records
    stating different rates are refused."""
    sets = [tuple(record for _, record in read_record_set(path, layout)) for path in paths]
    rates = [(str(path), record.fs) for path, found in zip(paths, sets, strict=True) for record in found]
    return sets, common_rate(rates)


def common_rate(rates: Sequence[tuple[str, float | None]]) -> float | None:
    """The one sampling rate of the named records (None if none states one); records at
    different rates are refused, each named with its rate: a model's lags count samples, so a
    model fitted at one rate means another thing at another."""
    stated = {rate for _, rate in rates if rate is not None}
    if len(stated) > 1:
        listing = ", ".join(f"{name} at {rate:.15g} Hz" for name, rate in rates if rate is not None)
        raise InputError(
            f"the records are sampled at different rates ({listing}); resample them to one rate, "
            "or give only records of one rate together"
        )
    return stated.pop() if stated else None


def read_manifest(path: Path) -> list[tuple[Path, float]]:
    """Rows ``path,k`` of an experiment manifest; paths are relative to the manifest."""
    try:
        with path.open(newline="") as handle:
            reader = csv.DictReader(handle)
            if reader.fieldnames is None or not {"path", "k"} <= {f.strip() for f in reader.fieldnames}:
                raise InputError(f"{path}: the manifest needs the columns 'path,k'")
            rows = []
            for number, row in enumerate(reader, start=2):
                try:
                    k = float(row["k"])
                except (TypeError, ValueError):
                    raise InputError(f"{path}, line {number}: k = {row['k']!r} is not a number") from None
                rows.append((path.parent / row["path"].strip(), k))
    except OSError as exc:
        raise InputError(f"{path}: cannot read the manifest ({exc.strerror})") from None
    if not rows:
        raise InputError(f"{path}: the manifest lists no experiments")
    return rows
