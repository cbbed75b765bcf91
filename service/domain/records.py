"""Records: deduplicated by content, stored as .npy bytes, with the conditions they were acquired under."""

from __future__ import annotations

import datetime as dt
import hashlib
import io
import json
import math
from collections.abc import Iterable, Sequence

import numpy as np
from numpy.typing import ArrayLike
from sqlalchemy import insert, select
from sqlalchemy.orm import Session, selectinload

from models.errors import InputError
from models.signals import checked_record
from recordfiles.conditions import Condition, as_conditions
from service.config import Settings
from service.db import insert_unless_exists
from service.domain import fleet
from service.domain.errors import ConflictError
from service.domain.structures import get_owned
from service.security import Principal
from service.tables import Record, RecordCondition, Structure, utcnow

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


def acquisition_limit(settings: Settings, now: dt.datetime | None = None) -> dt.datetime:
    """The latest acquisition time a record may have: the server's clock (``now``) plus the skew
    allowed to the clocks that acquire records (``max_clock_skew_seconds``). No record acquired later
    is stored (:func:`checked_acquired_at`), and no verdict acquired later stands for its structure
    (``service.domain.fleet.count_verdict``)."""
    return (now or utcnow()) + dt.timedelta(seconds=settings.max_clock_skew_seconds)


def checked_acquired_at(acquired_at: dt.datetime | None, settings: Settings) -> dt.datetime | None:
    """An upload's acquisition time (UTC; None: now), refused when it lies beyond
    :func:`acquisition_limit`: a clock set wrong, or a typing error (9999 for 2025). Stored, such a
    record would be its structure's newest until the clock caught up with it, and the structure
    would read as it does on that date whatever was acquired in between."""
    now = utcnow()
    if acquired_at is not None and acquired_at > acquisition_limit(settings, now):
        raise InputError(
            f"acquired_at {_iso(acquired_at)} is later than the server's clock ({_iso(now)}) by more "
            f"than NARXWATCH_MAX_CLOCK_SKEW_SECONDS ({settings.max_clock_skew_seconds:g} s) allows: "
            "a record cannot be acquired in the future; check the clock of the system that acquired it"
        )
    return acquired_at


def _iso(moment: dt.datetime) -> str:
    return moment.astimezone(dt.UTC).isoformat(timespec="seconds").replace("+00:00", "Z")


def content_hash(x: np.ndarray, y: np.ndarray, fs: float, channels: Sequence[str] = ()) -> str:
    """What identifies a record's data; a record of several channels hashes their names too
    (the same numbers under other names are another record), one of one response as always."""
    digest = hashlib.sha256()
    digest.update(np.float64(fs).tobytes())
    digest.update(np.ascontiguousarray(x, dtype="<f8").tobytes())
    digest.update(np.ascontiguousarray(y, dtype="<f8").tobytes())
    if channels:
        digest.update(json.dumps(list(channels)).encode())
    return digest.hexdigest()


def store_record(
    session: Session,
    structure: Structure,
    x: ArrayLike,
    y: ArrayLike,
    rate: float,
    acquired_at: dt.datetime | None,
    conditions: Sequence[Condition] = (),
    channels: Sequence[str] = (),
) -> tuple[Record, bool]:
    """Store a record with its conditions, or return the stored one with the same data; True when new.

    The signals are stored as given: validate them first, with ``models.signals.checked_record``
    or through the inspection (``models.inspection.inspect`` checks what it inspects), the rate
    with :func:`checked_rate`, the conditions with ``recordfiles.conditions.checked_conditions`` and the
    channels, names of y's columns when it has several, with ``recordfiles.channels.checked_channels``.
    Checking here too would validate every upload twice.

    The data identify a record, its conditions do not: a record is the same record whatever an
    upload says of it, so an upload of stored data that states other conditions than the stored
    ones is a conflict (one that states none takes the record as it is).
    """
    xa, ya = np.asarray(x, dtype=np.float64), np.asarray(y, dtype=np.float64)
    sha = content_hash(xa, ya, rate, channels)
    values = {
        "structure_id": structure.id,
        "fs": rate,
        "n_samples": len(xa),
        "acquired_at": acquired_at or utcnow(),
        "sha256": sha,
        "x": _npy(xa),
        "y": _npy(ya),
        "channels": list(channels) or None,
    }
    # Inserted first, looked up only on conflict: a new record, the common case, costs one statement.
    inserted = insert_unless_exists(session, Record, values, ["structure_id", "sha256"])
    if inserted is None:  # uploaded before, or concurrently: keep the first
        found = _find_or_fail(session, structure.id, sha)
        _check_same_conditions(found, conditions)
        return found, False
    rows = [
        {
            "record_id": inserted.id,
            "structure_id": structure.id,
            "name": c.name,
            "value": c.value,
            "unit": c.unit,
        }
        for c in conditions
    ]
    if rows:
        session.execute(insert(RecordCondition.__table__), rows)
    fleet.count_record(session, structure.id)
    # Built from what was written rather than read back: the blobs need no second trip.
    stored = [RecordCondition(**row) for row in rows]
    return Record(id=inserted.id, created_at=inserted.created_at, conditions=stored, **values), True


def checked_signals(
    x: ArrayLike, y: ArrayLike, channels: Sequence[str], min_samples: int, degree: int
) -> tuple[np.ndarray, np.ndarray]:
    """x and y checked as ``models.signals.checked_record`` checks a record of one response; with
    ``channels``, y (N, K) checked a channel at a time against x, each refusal naming its channel."""
    if not channels:
        return checked_record(x, y, min_samples, degree=degree)
    ya = np.asarray(y, dtype=np.float64)
    columns = [
        checked_record(x, ya[:, j], min_samples, label=f"channel {name!r} of the record", degree=degree)
        for j, name in enumerate(channels)
    ]
    return columns[0][0], np.column_stack([column for _, column in columns])


def stored_conditions(
    session: Session,
    structure: Structure,
    x: ArrayLike,
    y: ArrayLike,
    rate: float,
    channels: Sequence[str] = (),
) -> list[Condition]:
    """The conditions the same data were stored with, if the structure holds them (none if not)."""
    sha = content_hash(np.asarray(x, dtype=np.float64), np.asarray(y, dtype=np.float64), rate, channels)
    found = _find(session, structure.id, sha)
    return as_conditions(found.conditions) if found is not None else []


def condition_values(conditions: Iterable[Condition | RecordCondition]) -> dict[str, float]:
    """The values of conditions by name, as the models take them."""
    return {c.name: c.value for c in conditions}


def describe_conditions(conditions: Sequence[Condition]) -> str:
    """``temperature=12.5 °C, speed=3``; "none" for none."""
    listed = [f"{c.name}={c.value:g}" + (f" {c.unit}" if c.unit else "") for c in conditions]
    return ", ".join(listed) or "none"


def _check_same_conditions(record: Record, conditions: Sequence[Condition]) -> None:
    stored = as_conditions(record.conditions)
    if conditions and list(conditions) != stored:
        raise ConflictError(
            f"record {record.id} holds the same data and was stored with the conditions "
            f"{describe_conditions(stored)}; this upload states {describe_conditions(conditions)}. "
            "A record keeps the conditions of its first upload"
        )


def get_record(session: Session, principal: Principal, record_id: int) -> Record:
    return get_owned(session, principal, Record, record_id, "record")


def signals(record: Record) -> tuple[np.ndarray, np.ndarray]:
    """The record's x and y (N, K for a record of several channels, ``record.channels``); a conflict
    once the retention has pruned them."""
    if record.signals_pruned_at is not None:
        raise ConflictError(pruned_notice(record))
    return _load(record.x), _load(record.y)


def pruned_notice(record: Record) -> str:
    """What the API and the dashboard say of a record whose signals the retention pruned."""
    assert record.signals_pruned_at is not None
    return (
        f"the signals of record {record.id} were pruned on {record.signals_pruned_at:%Y-%m-%d} under the "
        "organisation's retention (GET /api/v1/retention); its verdicts and conditions are kept"
    )


def _find_or_fail(session: Session, structure_id: int, sha: str) -> Record:
    found = _find(session, structure_id, sha)
    if found is None:  # a conflict with a row that is not there: nothing sensible to answer
        raise RuntimeError(f"record {sha} conflicted but cannot be found")
    return found


def _find(session: Session, structure_id: int, sha: str) -> Record | None:
    query = select(Record).where(Record.structure_id == structure_id, Record.sha256 == sha)
    return session.scalar(query.options(selectinload(Record.conditions)))


def _npy(values: np.ndarray) -> bytes:
    buffer = io.BytesIO()
    np.save(buffer, values, allow_pickle=False)
    return buffer.getvalue()


def _load(data: bytes) -> np.ndarray:
    return np.load(io.BytesIO(data), allow_pickle=False)
