"""Records: validated, deduplicated by content, stored as .npy bytes."""

from __future__ import annotations

import datetime as dt
import hashlib
import io

import numpy as np
from sqlalchemy import select
from sqlalchemy.orm import Session

from models.errors import InputError
from models.signals import checked_record
from service.db import insert_unless_exists
from service.domain.structures import get_owned
from service.security import Principal
from service.tables import Record, Structure, utcnow

# Samples per Ljung–Box lag, plus the longest NARX lag: a shorter record cannot be inspected.
SAMPLES_PER_LAG = 5
LONGEST_LAG = 8


def minimum_samples(lags: int) -> int:
    return SAMPLES_PER_LAG * lags + LONGEST_LAG


def content_hash(x: np.ndarray, y: np.ndarray, fs: float) -> str:
    digest = hashlib.sha256()
    digest.update(np.float64(fs).tobytes())
    digest.update(np.ascontiguousarray(x, dtype="<f8").tobytes())
    digest.update(np.ascontiguousarray(y, dtype="<f8").tobytes())
    return digest.hexdigest()


def store_record(
    session: Session,
    structure: Structure,
    x: object,
    y: object,
    fs: float | None,
    acquired_at: dt.datetime | None,
    min_samples: int,
) -> tuple[Record, bool]:
    """Store a record, or return the stored one with the same data; True when new."""
    xa, ya = checked_record(x, y, min_samples)
    rate = structure.fs if fs is None else float(fs)
    if rate != structure.fs:
        raise InputError(
            f"the record is sampled at {rate:g} Hz but structure {structure.name!r} is monitored at "
            f"{structure.fs:g} Hz; resample it or register a structure at that rate"
        )
    sha = content_hash(xa, ya, rate)
    values = {
        "structure_id": structure.id,
        "fs": rate,
        "n_samples": len(xa),
        "acquired_at": acquired_at or utcnow(),
        "sha256": sha,
        "x": _npy(xa),
        "y": _npy(ya),
    }
    # Inserted first, looked up only on conflict: a new record, the common case, costs one statement.
    inserted = insert_unless_exists(session, Record, values, ["structure_id", "sha256"])
    if inserted is None:  # uploaded before, or concurrently: keep the first
        return _find_or_fail(session, structure.id, sha), False
    # Built from what was written rather than read back: the blobs need no second trip.
    return Record(id=inserted.id, created_at=inserted.created_at, **values), True


def get_record(session: Session, principal: Principal, record_id: int) -> Record:
    return get_owned(session, principal, Record, record_id, "record")


def signals(record: Record) -> tuple[np.ndarray, np.ndarray]:
    return _load(record.x), _load(record.y)


def _find_or_fail(session: Session, structure_id: int, sha: str) -> Record:
    found = _find(session, structure_id, sha)
    if found is None:  # a conflict with a row that is not there: nothing sensible to answer
        raise RuntimeError(f"record {sha} conflicted but cannot be found")
    return found


def _find(session: Session, structure_id: int, sha: str) -> Record | None:
    return session.scalar(select(Record).where(Record.structure_id == structure_id, Record.sha256 == sha))


def _npy(values: np.ndarray) -> bytes:
    buffer = io.BytesIO()
    np.save(buffer, values, allow_pickle=False)
    return buffer.getvalue()


def _load(data: bytes) -> np.ndarray:
    return np.load(io.BytesIO(data), allow_pickle=False)
