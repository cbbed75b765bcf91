"""Validation of excitation/response pairs before any estimation touches them."""

from __future__ import annotations

from collections.abc import Iterable, Sequence

import numpy as np
from numpy.typing import ArrayLike

from models.errors import InputError

Record = tuple[np.ndarray, np.ndarray]


def checked_record(x: ArrayLike, y: ArrayLike, min_samples: int = 1, label: str = "record") -> Record:
    """Return (x, y) as float64 vectors, or raise :class:`InputError` saying what is wrong.

    A record must hold two one-dimensional signals of equal length, at least ``min_samples``
    long, all finite, and neither signal constant (a constant carries no information about
    the dynamics and makes every regression singular).
    """
    try:
        xa = np.asarray(x, dtype=np.float64)
        ya = np.asarray(y, dtype=np.float64)
    except (TypeError, ValueError) as exc:
        raise InputError(f"{label}: signals must be numbers ({exc})") from None
    if xa.ndim != 1 or ya.ndim != 1:
        raise InputError(f"{label}: x and y must be one-dimensional, got shapes {xa.shape} and {ya.shape}")
    if xa.size != ya.size:
        raise InputError(f"{label}: x has {xa.size} samples but y has {ya.size}; they must be equal")
    if xa.size < min_samples:
        raise InputError(f"{label}: {xa.size} samples is too short; this needs at least {min_samples}")
    for name, values in (("x", xa), ("y", ya)):
        bad = np.flatnonzero(~np.isfinite(values))
        if bad.size:
            raise InputError(
                f"{label}: {name} has {bad.size} NaN or infinite value(s), first at sample {bad[0]}"
            )
        if values.size and np.ptp(values) == 0.0:
            raise InputError(f"{label}: {name} is constant; a record needs a varying signal")
    return xa, ya


def checked_records(records: Iterable[tuple[ArrayLike, ArrayLike]], min_samples: int) -> Sequence[Record]:
    """Validate several records, naming the offending one by its position."""
    checked = [checked_record(x, y, min_samples, label=f"record {i + 1}") for i, (x, y) in enumerate(records)]
    if not checked:
        raise InputError("at least one record is needed")
    return checked
