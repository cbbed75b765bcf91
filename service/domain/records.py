"""Records: deduplicated by content, stored as .npy bytes."""

from __future__ import annotations

import datetime as dt
import hashlib
import io
import math

import numpy as np
from numpy.typing import ArrayLike
from sqlalchemy import select
from sqlalchemy.orm import Session

from models.errors import InputError
from service.db import insert_unless_exists
from service.domain import fleet
from service.domain.structures import get_owned
from service.security import Principal
from service.tables import Record, Structure, utcnow

# Rates that differ by less than this share are one rate written two ways (1500 and
# 1500.0000001 from a float32 clock or a division): far below any real difference of clocks.
RATE_TOLERANCE = 1e-9


def checked_rate(structure: Structure, fs: float | None) -> float:
    """The record's sampling rate: the structure's, which it must match; None stands for it.

    A rate within :data:`RATE_TOLERANCE` of the structure's is taken as the structure's, so that
    the same data hashes alike. Printed with 15 digits, two refused rates always look different.
    """
    if fs is None or math.isclose(fs, structure.fs, rel_tol=RATE_TOLERANCE):
        return structure.fs
    raise InputError(
        f"the record is sampled at {fs:.15g} Hz but structure {structure.name!r} is monitored at "
        f"{structure.fs:.15g} Hz; resample it or register a structure at that rate"
    )


def content_hash(x: np.ndarray, y: np.ndarray, fs: float) -> str:
    digest = hashlib.sha256()
    digest.update(np.float64(fs).tobytes())
    digest.update(np.ascontiguousarray(x, dtype="<f8").tobytes())
    digest.update(np.ascontiguousarray(y, dtype="<f8").tobytes())
    return digest.hexdigest()


def store_record(
    session: Session,
    structure: Structure,
    x: ArrayLike,
    y: ArrayLike,
    rate: float,
    acquired_at: dt.datetime | None,
) -> tuple[Record, bool]:
    """Store a record, or return the stored one with the same data; True when new.

    The signals are stored as given: validate them first, with ``models.signals.checked_record``
    or through the inspection (``models.inspection.inspect`` checks what it inspects), and the
    rate with :func:`checked_rate`. Checking here too would validate every upload twice.
    """
    xa, ya = np.asarray(x, dtype=np.float64), np.asarray(y, dtype=np.float64)
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
    fleet.count_record(session, structure.id)
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
