"""Fuzzing the record parsers: any bytes give a record or a clear InputError, never a crash.

Hypothesis drives the CSV, NPZ, Silverbox and JSON-upload parsers with arbitrary bytes and with
mutations of valid files (so that the fuzz reaches past the first check). What counts as a crash:
any exception but InputError (the service answers that with a 4xx), or a parsed record whose
arrays are not float64 vectors of equal length.
"""

from __future__ import annotations

import io
import json
import zipfile

import numpy as np
from fastapi import HTTPException
from hypothesis import HealthCheck, given, settings
from hypothesis import strategies as st

from models.errors import InputError
from recordfiles.reader import RecordFile, parse_csv, parse_npz, parse_silverbox
from recordfiles.writer import dump_csv, dump_npz
from service.api.uploads import parse_upload

LIMIT = 1 << 20
FUZZ = settings(max_examples=300, deadline=None, suppress_health_check=[HealthCheck.too_slow])

rng = np.random.default_rng(0)
X, Y = rng.normal(size=40), rng.normal(size=40)
CONDITIONS = {"temperature": 12.5, "speed": 3.0}
VALID_CSV = dump_csv(X, Y, 1500.0, CONDITIONS).encode()
VALID_NPZ = dump_npz(X, Y, 1500.0, CONDITIONS)
VALID_SILVERBOX = ('"V1","V2",\n' + "".join(f"{a},{b},\n" for a, b in zip(X, Y, strict=True))).encode()
VALID_JSON = json.dumps(
    {
        "x": X.tolist(),
        "y": Y.tolist(),
        "fs": 1500.0,
        "conditions": [{"name": "t", "value": 1.0, "unit": "°C"}],
    }
).encode()


def mutated(valid: bytes) -> st.SearchStrategy[bytes]:
    """The valid bytes with a slice replaced, truncated, or extended by arbitrary bytes."""
    return st.one_of(
        st.binary(max_size=2048),
        st.tuples(st.integers(0, len(valid)), st.integers(0, 64), st.binary(max_size=64)).map(
            lambda edit: valid[: edit[0]] + edit[2] + valid[edit[0] + edit[1] :]
        ),
        st.integers(0, len(valid)).map(lambda cut: valid[:cut]),
    )


def check(parse, data: bytes) -> None:
    try:
        record = parse(data)
    except InputError:
        return
    assert isinstance(record, RecordFile)
    for signal in (record.x, record.y):
        assert signal.dtype == np.float64 and signal.ndim == 1
    assert record.x.shape == record.y.shape
    assert all(np.isfinite(condition.value) for condition in record.conditions)


@FUZZ
@given(mutated(VALID_CSV))
def test_csv_parser_never_crashes(data: bytes) -> None:
    check(parse_csv, data)


@FUZZ
@given(mutated(VALID_SILVERBOX))
def test_silverbox_parser_never_crashes(data: bytes) -> None:
    check(parse_silverbox, data)


@FUZZ
@given(mutated(VALID_NPZ))
def test_npz_parser_never_crashes(data: bytes) -> None:
    check(lambda raw: parse_npz(raw, LIMIT), data)


@FUZZ
@given(st.sampled_from(["x", "y", "fs", "temperature"]), st.binary(max_size=512))
def test_npz_with_an_arbitrary_member_never_crashes(name: str, member: bytes) -> None:
    """A well-formed archive whose member is arbitrary bytes: the .npy reader is fuzzed directly."""
    buffer = io.BytesIO()
    with zipfile.ZipFile(buffer, "w") as archive:
        for other in {"x", "y"} - {name}:
            archive.writestr(f"{other}.npy", _npy(X))
        archive.writestr(f"{name}.npy", member)
    check(lambda raw: parse_npz(raw, LIMIT), buffer.getvalue())


@FUZZ
@given(
    mutated(VALID_JSON),
    st.sampled_from(
        ["application/json", "text/csv", "application/x-npz", "application/x-matlab-data", "text/plain"]
    ),
)
def test_upload_parser_never_crashes(data: bytes, content_type: str) -> None:
    """The service's own entry: InputError becomes 422, HTTPException carries its own 4xx."""
    try:
        upload = parse_upload(data, content_type, None, LIMIT)
    except InputError:
        return
    except HTTPException as exc:
        assert 400 <= exc.status_code < 500
        return
    assert upload.x is not None and upload.y is not None


def _npy(values: np.ndarray) -> bytes:
    buffer = io.BytesIO()
    np.save(buffer, values, allow_pickle=False)
    return buffer.getvalue()
