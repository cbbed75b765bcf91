"""Every bad request gets a 4xx whose ``detail`` a person can act on, and leaves nothing behind.

Through HTTP against the real app on SQLite (plus, for the upload limit, a server of its own
with a small limit); what the database decides (the ids, times and text it can hold, a refused
request's writes undone, names unique) on PostgreSQL too: the tests that take
``database_site``. After each refused request the listings of structures, models and verdicts
are unchanged and no record id was stored (``api_helpers.nothing_written``).
"""

from __future__ import annotations

import base64
import io
import os
import socket
import time
import zipfile
from dataclasses import dataclass

import httpx
import numpy as np
import pytest

from harness.api_helpers import (
    API,
    FS,
    RIG_TERMS,
    Org,
    clients,
    create_structure,
    csv_text,
    detail,
    experiments,
    json_body,
    noise,
    nothing_written,
    npz_bytes,
    post_record,
    raw_json,
    records_url,
    train_fault_mode,
)
from harness.live import DATABASES, LiveServer, http_client, on_each_database
from models.signals import minimum_samples
from service.config import Settings
from simulator.theory import EXACT_TERMS

UNKNOWN = 10**6


@dataclass
class Site:
    org: Org
    rig: int  # no models; holds three k2 training records
    training: list[dict]
    other: int  # a second structure of the same organisation, with one record
    other_record: int
    long_lag: int  # its k2 model has a term lagged 60 samples: inspection needs 260 samples
    min_samples: int


@pytest.fixture(scope="module")
def api_server(sqlite_api_server: LiveServer) -> LiveServer:
    """SQLite: most refusals are made before the database is reached (``database_site``)."""
    return sqlite_api_server


def build_site(api_server: LiveServer) -> Site:
    org = Org.create(api_server)
    with clients(org) as (admin, ingest, _):
        rig = create_structure(admin, "rig")["id"]
        training = experiments(ingest, rig, "k2", seed=11)
        other = create_structure(admin, "other")["id"]
        other_record = post_record(ingest, other, json_body(300)).json()["id"]
        long_lag = create_structure(admin, "long-lag")["id"]
        terms = [t.name for t in EXACT_TERMS] + ["x[t-60]"]
        train_fault_mode(admin, ingest, long_lag, "k2", seed=12, terms=terms)
    return Site(org, rig, training, other, other_record, long_lag, minimum_samples(api_server.settings.lags))


@pytest.fixture(scope="module")
def site(api_server: LiveServer) -> Site:
    return build_site(api_server)


@pytest.fixture(scope="module", params=DATABASES)
def database_site(request: pytest.FixtureRequest) -> Site:
    """The site on each database, for the refusals the database's types, transactions and
    constraints take part in."""
    return on_each_database(request, "site", build_site)


@pytest.fixture
def admin(site: Site):
    with site.org.client("admin") as client:
        yield client


@pytest.fixture
def ingest(site: Site):
    with site.org.client("ingest") as client:
        yield client


def assert_refused(response: httpx.Response, status: int, *fragments: str) -> None:
    assert response.status_code == status, response.text
    text = detail(response)
    for fragment in fragments:
        assert fragment in text, f"{fragment!r} not in {text!r}"


# --- record uploads: the signals ------------------------------------------------------------


def test_x_and_y_of_different_lengths(site: Site, ingest):
    body = json_body(300)
    body["y"] = body["y"][:-1]
    with nothing_written(site.org, site.rig):
        assert_refused(post_record(ingest, site.rig, body), 422, "x has 300 samples but y has 299")


MARKER = 4242.4242


def _with_token(signal: str, token: bytes) -> bytes:
    """A JSON record whose sample 3 of ``signal`` is the raw ``token``."""
    body = json_body(300)
    body[signal][3] = MARKER
    return raw_json(body).replace(repr(MARKER).encode(), token, 1)


@pytest.mark.parametrize(
    ("signal", "token"),
    [("x", b"NaN"), ("y", b"Infinity"), ("x", b"-Infinity"), ("y", b"1e999")],
    ids=["NaN", "Infinity", "-Infinity", "overflowing-1e999"],
)
def test_non_finite_values_in_json(site: Site, ingest, signal, token):
    with nothing_written(site.org, site.rig):
        response = post_record(ingest, site.rig, _with_token(signal, token), "application/json")
        assert_refused(response, 422, f"invalid record: {signal}.3: Input should be a finite number")


def test_non_finite_values_as_python_json_writes_them(site: Site, ingest):
    """json.dumps writes float('nan') as the bare token NaN, which strict JSON does not have."""
    body = json_body(300)
    body["x"][0] = float("nan")
    content = raw_json(body)
    assert content.startswith(b'{"x": [NaN, ')
    with nothing_written(site.org, site.rig):
        response = post_record(ingest, site.rig, content, "application/json")
        assert_refused(response, 422, "x.0: Input should be a finite number")


def test_non_finite_values_in_csv_and_npz(site: Site, ingest):
    x, y = noise(300)
    x[5] = np.nan
    y[9] = np.inf
    with nothing_written(site.org, site.rig):
        response = post_record(ingest, site.rig, csv_text(x, y), "text/csv")
        assert_refused(response, 422, "x has 1 NaN or infinite value(s), first at sample 5")
        x[5] = 0.5
        response = post_record(ingest, site.rig, npz_bytes(x=x, y=y, fs=FS), "application/x-npz")
        assert_refused(response, 422, "y has 1 NaN or infinite value(s), first at sample 9")


def test_records_shorter_than_inspection_needs(site: Site, ingest):
    shortest = site.min_samples
    assert shortest == 5 * 40 + 8
    with nothing_written(site.org, site.rig):
        response = post_record(ingest, site.rig, json_body(shortest - 1))
        assert_refused(response, 422, f"{shortest - 1} samples is too short; this needs at least {shortest}")
        x, y = noise(10)
        response = post_record(ingest, site.rig, csv_text(x, y), "text/csv")
        assert_refused(response, 422, f"10 samples is too short; this needs at least {shortest}")
    response = post_record(ingest, site.rig, json_body(shortest))
    assert response.status_code == 201, response.text
    assert response.json()["n_samples"] == shortest


def test_sampling_rate_other_than_the_structures(site: Site, ingest):
    x, y = noise(300)
    message = "sampled at 1000 Hz but structure 'rig' is monitored at 1500 Hz"
    with nothing_written(site.org, site.rig):
        assert_refused(post_record(ingest, site.rig, json_body(300, fs=1000.0)), 422, message)
        assert_refused(post_record(ingest, site.rig, csv_text(x, y, fs=1000.0), "text/csv"), 422, message)
        response = post_record(ingest, site.rig, npz_bytes(x=x, y=y, fs=1000.0), "application/x-npz")
        assert_refused(response, 422, message)


MALFORMED_JSON = {
    "truncated": (b'{"x": [1, 2', "Invalid JSON"),
    "empty": (b"", "Invalid JSON"),
    "not-an-object": (b"[1, 2]", "Input should be an object"),
    "no-fs": (b'{"x": [1, 2], "y": [3, 4]}', "fs: Field required"),
    "unknown-field": (b'{"x": [1], "y": [1], "fs": 1500, "z": 1}', "z: Extra inputs are not permitted"),
    "numbers-as-strings": (b'{"x": ["1"], "y": [1], "fs": 1500}', "x.0: Input should be a valid number"),
    "negative-fs": (b'{"x": [1], "y": [1], "fs": -1500}', "fs: Input should be greater than 0"),
    "empty-signals": (b'{"x": [], "y": [], "fs": 1500}', "x: List should have at least 1 item"),
}


@pytest.mark.parametrize(("content", "fragment"), MALFORMED_JSON.values(), ids=MALFORMED_JSON.keys())
def test_malformed_json(site: Site, ingest, content, fragment):
    with nothing_written(site.org, site.rig):
        response = post_record(ingest, site.rig, content, "application/json")
        assert_refused(response, 422, "invalid record", fragment)


def _csv_rows(n: int = 300) -> list[str]:
    x, y = noise(n)
    return [f"{a:.17g},{b:.17g}" for a, b in zip(x, y, strict=True)]


MALFORMED_CSV = {
    "bad-header": (lambda rows: "a,b\n" + "\n".join(rows), "the CSV has no column 'x'; its columns are a, b"),
    "no-header": (lambda rows: "# fs=1500\n", "the CSV has no header line naming its columns"),
    "semicolons": (
        lambda rows: "x;y\n" + "\n".join(row.replace(",", ";") for row in rows),
        "its values are separated by ';', where a CSV's are by ','",
    ),
    "header-only": (lambda rows: "x,y\n", "the CSV has a header but no data rows"),
    "non-numeric-line": (
        lambda rows: "x,y\n" + "\n".join([*rows[:3], "1.0,abc", *rows[3:]]),
        "CSV line 5: 'abc' in column 'y' is not a number",
    ),
    "three-columns": (
        lambda rows: "x,y\n" + "\n".join([rows[0], rows[1] + ",7", *rows[2:]]),
        "CSV line 3: expected 2 values, found 3",
    ),
    "bad-fs-comment": (lambda rows: "# fs=-5\nx,y\n" + "\n".join(rows), "sampling rate must be a positive"),
    "not-utf8": (lambda rows: b"x,y\n\xff\xfe,1\n", "the CSV is not UTF-8 text"),
}


@pytest.mark.parametrize(("make", "fragment"), MALFORMED_CSV.values(), ids=MALFORMED_CSV.keys())
def test_malformed_csv(site: Site, ingest, make, fragment):
    with nothing_written(site.org, site.rig):
        assert_refused(post_record(ingest, site.rig, make(_csv_rows()), "text/csv"), 422, fragment)


class Tripwire:
    """Unpickling this creates a directory: proof that a pickle in an upload was executed."""

    def __init__(self, path: str) -> None:
        self.path = path

    def __reduce__(self):
        return (os.mkdir, (self.path,))


def _zip_of(**members: bytes) -> bytes:
    buffer = io.BytesIO()
    with zipfile.ZipFile(buffer, "w") as archive:
        for name, data in members.items():
            archive.writestr(name, data)
    return buffer.getvalue()


def test_malformed_npz(site: Site, ingest, tmp_path):
    x, y = noise(300)
    npy = io.BytesIO()
    np.save(npy, x)
    tripwire = str(tmp_path / "unpickled")
    pickled = np.array([Tripwire(tripwire)] * 300, dtype=object)
    cases = {
        "not a zip": (b"this is not an archive", "the file is not a readable NPZ archive"),
        "a bare .npy": (npy.getvalue(), "the file is not a readable NPZ archive"),
        "zip magic, garbage": (b"PK\x03\x04" + b"\x00" * 64, "the file is not a readable NPZ archive"),
        "no y": (npz_bytes(x=x, fs=FS), "the NPZ lacks array(s) y; it needs 'x' and 'y'"),
        "pickled x": (npz_bytes(x=pickled, y=y), "never unpickled"),
        "pickled fs": (
            npz_bytes(x=x, y=y, fs=np.array([Tripwire(tripwire)], dtype=object)),
            "never unpickled",
        ),
        "text x": (npz_bytes(x=np.array(["1.0"] * 300), y=y), "NPZ array 'x' must be numeric"),
        "two-dimensional x": (npz_bytes(x=np.stack([x, x]), y=y), "x and y must be one-dimensional"),
    }
    with nothing_written(site.org, site.rig):
        for name, (content, fragment) in cases.items():
            response = post_record(ingest, site.rig, content, "application/x-npz")
            assert response.status_code == 422, (name, response.text)
            assert fragment in detail(response), (name, response.text)
    assert not os.path.exists(tripwire), "the service unpickled an uploaded object array"


def test_npz_members_that_are_not_arrays(site: Site, ingest):
    """A zip whose x.npy and y.npy hold no .npy data: numpy hands back raw bytes, not arrays."""
    content = _zip_of(**{"x.npy": b"hello", "y.npy": b"world"})
    with nothing_written(site.org, site.rig):
        response = post_record(ingest, site.rig, content, "application/x-npz")
        assert_refused(response, 422, "NPZ")


@pytest.mark.parametrize("content_type", ["text/plain", "application/xml", "multipart/form-data", None])
def test_unsupported_content_type(site: Site, ingest, content_type):
    with nothing_written(site.org, site.rig):
        response = post_record(ingest, site.rig, raw_json(json_body(300)), content_type)
        assert_refused(
            response,
            415,
            f"unsupported Content-Type {content_type or '(none)'!r}",
            "application/json, text/csv, application/x-npz or application/x-matlab-data",
        )


def test_naive_acquisition_time(site: Site, ingest):
    x, y = noise(300)
    with nothing_written(site.org, site.rig):
        response = post_record(ingest, site.rig, json_body(300, acquired_at="2026-03-01T10:00:00"))
        assert_refused(response, 422, "acquired_at", "give a timezone")
        response = post_record(
            ingest, site.rig, csv_text(x, y), "text/csv", acquired_at="2026-03-01T10:00:00"
        )
        assert_refused(response, 422, "acquired_at needs a timezone")
        response = post_record(ingest, site.rig, csv_text(x, y), "text/csv", acquired_at="yesterday")
        assert_refused(response, 422, "acquired_at")


@pytest.mark.parametrize(
    "moment",
    ["0001-01-01T00:00:00+05:00", "9999-12-31T23:00:00-05:00"],
    ids=["year-1-east", "year-9999-west"],
)
def test_acquisition_time_outside_the_representable_range(database_site: Site, moment):
    """A zoned time whose UTC equivalent falls outside years 1-9999 cannot be stored: a 4xx."""
    site = database_site
    with nothing_written(site.org, site.rig):
        with site.org.client("ingest") as ingest:
            response = post_record(ingest, site.rig, json_body(300, acquired_at=moment))
            assert_refused(response, 422, "acquired_at")
        with site.org.client("ingest") as ingest:
            x, y = noise(300)
            response = post_record(ingest, site.rig, csv_text(x, y), "text/csv", acquired_at=moment)
            assert_refused(response, 422, "acquired_at")


# --- the upload size limit, on a server of its own --------------------------------------------

LIMIT = 64 * 1024


@dataclass
class Small:
    server: LiveServer
    org: Org
    structure_id: int


@pytest.fixture(scope="module")
def small(tmp_path_factory) -> Small:
    folder = tmp_path_factory.mktemp("small-limit")
    settings = Settings(database_url=f"sqlite:///{folder / 'narxwatch.db'}", max_upload_bytes=LIMIT)
    with LiveServer(settings) as server:
        org = Org.create(server)
        with org.client("admin") as admin:
            structure_id = create_structure(admin, "rig")["id"]
        yield Small(server, org, structure_id)


def _padded(body: dict, size: int) -> bytes:
    """``body`` as JSON padded with trailing whitespace to exactly ``size`` bytes."""
    content = raw_json(body)
    assert len(content) <= size
    return content + b" " * (size - len(content))


def _stored_before(small: Small, body: dict) -> bool:
    """Upload the compact JSON of ``body``; True when the same data had been stored already."""
    with small.org.client("ingest") as ingest:
        response = post_record(ingest, small.structure_id, body)
    assert response.status_code in (200, 201), response.text
    return not response.json()["created"]


def test_upload_over_the_limit_with_content_length(small: Small):
    body = json_body(300)
    with small.org.client("ingest") as ingest:
        response = post_record(ingest, small.structure_id, _padded(body, LIMIT + 1), "application/json")
    assert_refused(response, 413, f"exceeds the limit of {LIMIT} bytes", "NARXWATCH_MAX_UPLOAD_BYTES")
    assert not _stored_before(small, body)


def test_upload_of_exactly_the_limit_is_accepted(small: Small):
    with small.org.client("ingest") as ingest:
        response = post_record(ingest, small.structure_id, _padded(json_body(300), LIMIT), "application/json")
    assert response.status_code == 201, response.text


def test_upload_over_the_limit_without_content_length(small: Small):
    """A chunked body declares no size: the limit must hold while the body streams in."""
    body = json_body(300)
    content = _padded(body, 3 * LIMIT)

    def chunks():
        for start in range(0, len(content), 4096):
            yield content[start : start + 4096]

    with small.org.client("ingest") as ingest:
        request = ingest.build_request(
            "POST",
            records_url(small.structure_id),
            content=chunks(),
            headers={"Content-Type": "application/json"},
        )
        assert "content-length" not in request.headers and request.headers["transfer-encoding"] == "chunked"
        response = ingest.send(request)
    assert_refused(response, 413, f"exceeds the limit of {LIMIT} bytes")
    assert not _stored_before(small, body)


def test_upload_limit_answers_before_the_body_ends(small: Small):
    """The server refuses as soon as the limit is passed, without waiting for the rest."""
    key = small.org.keys["ingest"]
    head = (
        f"POST {records_url(small.structure_id)} HTTP/1.1\r\nHost: 127.0.0.1\r\n"
        f"Authorization: Bearer {key}\r\nContent-Type: application/json\r\n"
        "Transfer-Encoding: chunked\r\n\r\n"
    ).encode()
    chunk = b" " * 8192
    with socket.create_connection(("127.0.0.1", small.server.port), timeout=10) as connection:
        connection.sendall(head)
        try:
            for _ in range(LIMIT // len(chunk) + 2):
                connection.sendall(f"{len(chunk):x}\r\n".encode() + chunk + b"\r\n")
        except (BrokenPipeError, ConnectionResetError):
            pass  # the server may close its side once it has answered
        # No terminating chunk: a server that buffered the whole body would never answer.
        answer = connection.recv(65536)
    assert answer.startswith(b"HTTP/1.1 413"), answer[:200]
    assert b"exceeds the limit" in answer


def test_npz_that_inflates_beyond_the_limit(small: Small):
    """The limit bounds what an upload costs the server; a compressed NPZ must not escape it.

    1 000 000 samples of a repeating pattern compress to ~40 KB, under the 64 KiB limit, but
    load as 16 MB of arrays; the ratio of deflate reaches ~1000, so a 16 MiB upload could
    demand ~16 GiB.
    """
    pattern = np.tile([0.0, 1.0, 2.0, 1.0], 250_000)
    buffer = io.BytesIO()
    np.savez_compressed(buffer, x=pattern, y=pattern[::-1].copy(), fs=FS)
    assert len(buffer.getvalue()) < LIMIT
    with small.org.client("ingest") as ingest:
        response = post_record(ingest, small.structure_id, buffer.getvalue(), "application/x-npz")
    assert_refused(response, 413, "limit")


# --- unknown and out-of-range ids ----------------------------------------------------------


def _id_requests(site: Site, unknown: int) -> list[tuple[str, str, dict | None, str]]:
    """(method, path, JSON body, what is not found) for every route that takes an id."""
    record = site.training[0]["record_id"]
    fault_mode = {"name": "k2", "k_min": -32.0, "k_max": 32.0, "experiments": site.training}
    return [
        ("GET", f"/structures/{unknown}", None, f"structure {unknown} not found"),
        ("GET", f"/structures/{unknown}/verdicts", None, f"structure {unknown} not found"),
        ("GET", f"/structures/{unknown}/summary", None, f"structure {unknown} not found"),
        ("GET", f"/structures/{unknown}/models", None, f"structure {unknown} not found"),
        ("POST", f"/structures/{unknown}/records", json_body(300), f"structure {unknown} not found"),
        ("POST", f"/structures/{unknown}/models/baseline", {"record_ids": [record]}, f"structure {unknown}"),
        ("POST", f"/structures/{unknown}/models/fault-modes", fault_mode, f"structure {unknown} not found"),
        ("POST", f"/structures/{site.rig}/models/baseline", {"record_ids": [unknown]}, f"record {unknown}"),
        (
            "POST",
            f"/structures/{site.rig}/models/fault-modes",
            {**fault_mode, "experiments": [*site.training[:2], {"record_id": unknown, "k": 30.0}]},
            f"record {unknown} not found",
        ),
        ("POST", f"/structures/{unknown}/models/1/activate", None, f"structure {unknown} not found"),
        (
            "POST",
            f"/structures/{site.rig}/models/{unknown}/activate",
            None,
            f"model version {unknown} not found",
        ),
        ("POST", f"/records/{unknown}/inspect", None, f"record {unknown} not found"),
        ("GET", f"/verdicts/{unknown}", None, f"verdict {unknown} not found"),
    ]


# 2**31 − 1 is the largest id the API admits: ids are 32-bit integers in both databases.
@pytest.mark.parametrize("unknown", [UNKNOWN, 2**31 - 1], ids=["1e6", "2^31-1"])
def test_unknown_ids_are_not_found(database_site: Site, unknown):
    site = database_site
    failures = []
    with nothing_written(site.org, site.rig):
        for method, path, body, message in _id_requests(site, unknown):
            # A fresh connection each time: a server error must not break the next request.
            with site.org.client("admin") as admin:
                response = admin.request(
                    method,
                    API + path,
                    content=raw_json(body) if body else None,
                    headers={"Content-Type": "application/json"} if body else {},
                )
            if response.status_code != 404 or message not in detail(response):
                failures.append(f"{method} {path} -> {response.status_code} {response.text[:150]}")
    assert not failures, "\n".join(failures)


@pytest.mark.parametrize("bad", [2**63, 2**31, 0, -1, "abc", "1.5"])
def test_ids_outside_the_admitted_range_are_refused(database_site: Site, bad):
    site = database_site
    requests = [
        ("GET", f"/structures/{bad}"),
        ("GET", f"/structures/{bad}/verdicts"),
        ("GET", f"/structures/{bad}/summary"),
        ("GET", f"/structures/{bad}/models"),
        ("POST", f"/structures/{bad}/records"),
        ("POST", f"/structures/{site.rig}/models/{bad}/activate"),
        ("POST", f"/records/{bad}/inspect"),
        ("GET", f"/verdicts/{bad}"),
    ]
    with nothing_written(site.org, site.rig), site.org.client("admin") as admin:
        for method, path in requests:
            content = raw_json(json_body(300)) if path.endswith("records") else None
            response = admin.request(
                method, API + path, content=content, headers={"Content-Type": "application/json"}
            )
            assert response.status_code == 422, (path, response.text)
            errors = response.json()["detail"]
            assert [error["loc"][0] for error in errors] == ["path"], errors
            assert errors[0]["loc"][1].endswith("_id"), errors


@pytest.mark.parametrize("bad", [2**63, 2**31, 0, -1, "abc", "1.5"])
def test_ids_in_queries_outside_the_admitted_range_are_refused(database_site: Site, bad):
    site = database_site
    queries = [
        ("/alarms", "structure_id"),
        ("/alarms", "cursor"),
        ("/jobs", "cursor"),
        ("/webhooks/1/deliveries", "cursor"),
        ("/email-subscriptions/1/deliveries", "cursor"),
    ]
    with nothing_written(site.org, site.rig), site.org.client("admin") as admin:
        for path, name in queries:
            response = admin.get(API + path, params={name: bad})
            assert response.status_code == 422, (path, name, response.text)
            assert [error["loc"] for error in response.json()["detail"]] == [["query", name]]


@pytest.mark.parametrize("bad", [2**63, 0, -1, "1", 1.0])
def test_ids_in_bodies_outside_the_admitted_range_are_refused(database_site: Site, bad):
    site = database_site
    with nothing_written(site.org, site.rig), site.org.client("admin") as admin:
        response = admin.post(f"{API}/structures/{site.rig}/models/baseline", json={"record_ids": [bad]})
        assert response.status_code == 422, response.text
        assert response.json()["detail"][0]["loc"] == ["body", "record_ids", 0]


# --- inspection -------------------------------------------------------------------------------


def test_inspection_without_a_fault_mode_model(site: Site, ingest):
    record = site.training[0]["record_id"]
    advice = f"train one with POST /api/v1/structures/{site.rig}/models/fault-modes"
    body = json_body(300)
    with nothing_written(site.org, site.rig):
        assert_refused(
            ingest.post(f"{API}/records/{record}/inspect"), 409, "no active fault-mode model", advice
        )
        # Upload and inspection are one transaction: the refused inspection stores no record.
        assert_refused(post_record(ingest, site.rig, body, inspect="true"), 409, advice)
    response = post_record(ingest, site.rig, body)
    assert (response.status_code, response.json()["created"]) == (201, True)


def test_a_baseline_is_not_a_fault_mode_model(site: Site, admin, ingest):
    structure = create_structure(admin, "baseline-only")["id"]
    record = post_record(ingest, structure, json_body(2000)).json()["id"]
    response = admin.post(
        f"{API}/structures/{structure}/models/baseline", json={"record_ids": [record], "terms": RIG_TERMS}
    )
    assert response.status_code == 201, response.text
    assert_refused(ingest.post(f"{API}/records/{record}/inspect"), 409, "no active fault-mode model")


def test_inspect_on_upload_is_all_or_nothing(database_site: Site):
    """A record long enough to store but too short for the model's lags: refused whole."""
    site = database_site
    needed = 60 + 5 * 40 + 8
    body = json_body(needed - 40)
    with site.org.client("ingest") as ingest:
        with nothing_written(site.org, site.long_lag):
            response = post_record(ingest, site.long_lag, body, inspect="true")
            assert_refused(response, 422, f"{needed - 40} samples is too short; this needs at least {needed}")
        response = post_record(ingest, site.long_lag, body)
        assert (response.status_code, response.json()["created"]) == (201, True)
        record = response.json()["id"]
        assert_refused(ingest.post(f"{API}/records/{record}/inspect"), 422, "too short")


# --- training ---------------------------------------------------------------------------------


def _fault_mode(site: Site, **changes) -> dict:
    body = {"name": "k2", "k_min": -32.0, "k_max": 32.0, "experiments": site.training, "terms": RIG_TERMS}
    return body | changes


TRAINING_ERRORS = {
    "record-of-another-structure": (
        "fault-modes",
        lambda s: _fault_mode(s, experiments=[*s.training[:2], {"record_id": s.other_record, "k": 30.0}]),
        lambda s: f"record {s.other_record} belongs to another structure, not 'rig'",
    ),
    "baseline-record-of-another-structure": (
        "baseline",
        lambda s: {"record_ids": [s.training[0]["record_id"], s.other_record]},
        lambda s: f"record {s.other_record} belongs to another structure, not 'rig'",
    ),
    "fewer-magnitudes-than-basis-functions": (
        "fault-modes",
        lambda s: _fault_mode(s, degree=2, experiments=s.training[:2]),
        lambda s: "a basis of 3 functions needs experiments at 3 or more distinct magnitudes, got 2",
    ),
    "repeated-magnitude": (
        "fault-modes",
        lambda s: _fault_mode(s, experiments=[{**e, "k": 0.0} for e in s.training]),
        lambda s: "a basis of 2 functions needs experiments at 2 or more distinct magnitudes, got 1",
    ),
    "one-experiment": (
        "fault-modes",
        lambda s: _fault_mode(s, experiments=s.training[:1]),
        lambda s: "List should have at least 2 items",
    ),
    "k_min-equal-k_max": (
        "fault-modes",
        lambda s: _fault_mode(s, k_min=10.0, k_max=10.0),
        lambda s: "k_min (10.0) must be below k_max (10.0)",
    ),
    "k_min-above-k_max": (
        "fault-modes",
        lambda s: _fault_mode(s, k_min=32.0, k_max=-32.0),
        lambda s: "k_min (32.0) must be below k_max (-32.0)",
    ),
    "magnitude-outside-range": (
        "fault-modes",
        lambda s: _fault_mode(s, k_min=-10.0, k_max=10.0),
        lambda s: "lies outside [-10.0, 10.0]",
    ),
    "unknown-term": (
        "fault-modes",
        lambda s: _fault_mode(s, terms=["y[t-1]", "z[t-1]"]),
        lambda s: "cannot read term 'z[t-1]'",
    ),
    "baseline-unknown-term": (
        "baseline",
        lambda s: {"record_ids": [s.training[0]["record_id"]], "terms": ["y[t-1]", "sin(x)"]},
        lambda s: "cannot read term 'sin(x)'",
    ),
    "current-output-term": (
        "baseline",
        lambda s: {"record_ids": [s.training[0]["record_id"]], "terms": ["y[t]"]},
        lambda s: "lag 0 of y is not allowed",
    ),
    "duplicate-term": (
        "fault-modes",
        lambda s: _fault_mode(s, terms=["y[t-1]", "x[t-4]", "y[t - 1]"]),
        lambda s: "term y[t-1] is listed twice",
    ),
    "unknown-basis": (
        "fault-modes",
        lambda s: _fault_mode(s, basis="fourier"),
        lambda s: "'chebyshev2', 'legendre' or 'power'",
    ),
    "degree-too-high": (
        "fault-modes",
        lambda s: _fault_mode(s, degree=9),
        lambda s: "less than or equal to 8",
    ),
    "named-baseline": (
        "fault-modes",
        lambda s: _fault_mode(s, name="baseline"),
        lambda s: "'baseline' names the healthy model",
    ),
    "bad-mode-name": (
        "fault-modes",
        lambda s: _fault_mode(s, name="k 2/x"),
        lambda s: "should match pattern",
    ),
    "no-records": ("baseline", lambda s: {"record_ids": []}, lambda s: "List should have at least 1 item"),
}


@pytest.mark.parametrize(("kind", "body", "message"), TRAINING_ERRORS.values(), ids=TRAINING_ERRORS.keys())
def test_training_errors(site: Site, admin, kind, body, message):
    with nothing_written(site.org, site.rig):
        response = admin.post(f"{API}/structures/{site.rig}/models/{kind}", json=body(site))
        assert_refused(response, 422, message(site))


@pytest.mark.parametrize("power", [10**4, 10**6])
def test_absurd_term_power_is_refused_promptly(site: Site, power):
    """A 200-character term name must not buy unbounded work (the power is a repeated product)."""
    term = f"x[t-1]^{power}"
    started = time.monotonic()
    with nothing_written(site.org, site.rig), site.org.client("admin") as admin:
        response = admin.post(
            f"{API}/structures/{site.rig}/models/baseline",
            json={"record_ids": [site.training[0]["record_id"]], "terms": ["y[t-1]", term]},
        )
        assert response.status_code == 422, response.text
        assert "power" in detail(response) or term in detail(response), response.text
    assert time.monotonic() - started < 5


# --- structures, text, authentication ----------------------------------------------------------


def test_duplicate_structure_name(database_site: Site):
    site = database_site
    with nothing_written(site.org, site.rig), site.org.client("admin") as admin:
        response = admin.post(f"{API}/structures", json={"name": "rig", "fs": 2000.0})
        assert_refused(response, 409, "a structure named 'rig' already exists in your organisation")
    # Names are unique per organisation, not across them.
    with Org.create(site.org.server).client("admin") as stranger:
        assert stranger.post(f"{API}/structures", json={"name": "rig", "fs": 2000.0}).status_code == 201


def test_structure_names_are_stored_trimmed_and_composed(database_site: Site):
    """Surrounding spaces go and combining accents are composed (NFC) before a name is stored or
    compared: " rig " is the existing "rig", and "e" + U+0301 is stored as U+00E9."""
    with Org.create(database_site.org.server).client("admin") as admin:
        created = admin.post(f"{API}/structures", json={"name": "  Pump 3 ", "fs": FS})
        decomposed = admin.post(f"{API}/structures", json={"name": "Cafe\u0301", "fs": FS})
        for response, name in ((created, "Pump 3"), (decomposed, "Caf\u00e9")):
            assert response.status_code == 201, response.text
            assert response.json()["name"] == name
            assert admin.get(f"{API}/structures/{response.json()['id']}").json()["name"] == name
        assert admin.post(f"{API}/structures", json={"name": "rig", "fs": FS}).status_code == 201
        listed = admin.get(f"{API}/structures").json()
        assert_refused(admin.post(f"{API}/structures", json={"name": " rig ", "fs": FS}), 409, "named 'rig'")
        assert admin.post(f"{API}/structures", json={"name": "Caf\u00e9", "fs": FS}).status_code == 409
        assert admin.get(f"{API}/structures").json() == listed


def test_a_structure_declares_what_its_signals_measure(api_server):
    """Created with the quantities and units of x and y (a unit normalised as names are), the
    structure reads and lists them back, and the OpenAPI schema offers their vocabulary; one
    created without them declares none, rather than the simulated rig's metres."""
    declared = {
        "excitation": {"quantity": "force", "unit": " N "},
        "response": {"quantity": "acceleration", "unit": "m/s\u00b2"},
    }
    with Org.create(api_server).client("admin") as admin:
        created = admin.post(f"{API}/structures", json={"name": "bridge", "fs": FS, **declared})
        plain = admin.post(f"{API}/structures", json={"name": "plain", "fs": FS})
        assert created.status_code == 201 and plain.status_code == 201, created.text + plain.text
        stated = {
            "excitation": {"quantity": "force", "unit": "N"},
            "response": {"quantity": "acceleration", "unit": "m/s\u00b2"},
        }
        read = admin.get(f"{API}/structures/{created.json()['id']}").json()
        listed = {s["name"]: s for s in admin.get(f"{API}/structures").json()}
        assert {key: created.json()[key] for key in stated} == stated
        assert {key: read[key] for key in stated} == stated
        assert {key: listed["bridge"][key] for key in stated} == stated
        assert (listed["plain"]["excitation"], listed["plain"]["response"]) == (None, None)
        schema = admin.get("/openapi.json").json()["components"]["schemas"]
    assert "displacement" in schema["Signal"]["properties"]["quantity"]["enum"]
    assert {"excitation", "response"} <= set(schema["StructureOut"]["required"])


def declaring(signal: str, quantity: str, unit: str) -> dict:
    """A structure's body that declares the ``signal`` (excitation or response) as given."""
    return {"name": "z", "fs": FS, signal: {"quantity": quantity, "unit": unit}}


STRUCTURE_ERRORS = {
    "empty-name": ({"name": "", "fs": FS}, "cannot be empty"),
    "control-character-in-name": ({"name": "a\nb", "fs": FS}, "U+000A"),
    # Names that would not show what they are (recordfiles.names): each refusal names the character.
    "space-only-name": ({"name": " ", "fs": FS}, "a name cannot be empty or only whitespace"),
    "byte-order-mark-name": (
        {"name": "\ufeff", "fs": FS},
        "no-break space): U+FEFF",
    ),
    "right-to-left-override-in-name": (
        {"name": "pump\u202egnp.exe", "fs": FS},
        "U+202E (RIGHT-TO-LEFT OVERRIDE) is character 5 of the name given",
    ),
    "zero-width-space-in-name": ({"name": "pump\u200b3", "fs": FS}, "invisible format character: U+200B"),
    "zero-fs": ({"name": "z", "fs": 0}, "greater than 0"),
    "string-fs": ({"name": "z", "fs": "1500"}, "valid number"),
    "unknown-field": ({"name": "z", "fs": FS, "owner": "me"}, "Extra inputs are not permitted"),
    "unit-with-space": (
        declaring("response", "velocity", "m s"),
        "the unit 'm s' is not allowed: a unit is 1 to 16 printable characters without spaces",
    ),
    "unit-too-long": (declaring("excitation", "force", "kilonewton-metres"), "a unit is 1 to 16 printable"),
    "unit-empty": (declaring("response", "strain", " "), "unit cannot be empty"),
    "unit-invisible": (
        declaring("response", "strain", "\u200b\u00b5\u03b5"),
        "invisible format character: U+200B",
    ),
    "unknown-quantity": (declaring("response", "mass", "kg"), "'pressure' or 'other'"),
    "quantity-missing": ({"name": "z", "fs": FS, "excitation": {"unit": "N"}}, "Field required"),
}


@pytest.mark.parametrize(("body", "fragment"), STRUCTURE_ERRORS.values(), ids=STRUCTURE_ERRORS.keys())
def test_invalid_structures(site: Site, admin, body, fragment):
    with nothing_written(site.org, site.rig):
        assert_refused(admin.post(f"{API}/structures", json=body), 422, fragment)


LONE_SURROGATE = {
    "structure-name": ("/structures", b'{"name": "rig-\\ud800", "fs": 1500}'),
    "structure-description": ("/structures", b'{"name": "s", "fs": 1500, "description": "\\udfff"}'),
    "term-name": ("/structures/{rig}/models/baseline", b'{"record_ids": [1], "terms": ["\\ud800"]}'),
    "mode-name": (
        "/structures/{rig}/models/fault-modes",
        b'{"name": "\\ud800", "k_min": 0, "k_max": 1, "experiments": []}',
    ),
}


@pytest.mark.parametrize(("path", "content"), LONE_SURROGATE.values(), ids=LONE_SURROGATE.keys())
def test_json_strings_that_are_not_unicode(database_site: Site, path, content):
    """A lone UTF-16 surrogate (legal JSON escape, not a character) is a 422, not a crash."""
    site = database_site
    with nothing_written(site.org, site.rig), site.org.client("admin") as admin:
        response = admin.post(
            API + path.format(rig=site.rig), content=content, headers={"Content-Type": "application/json"}
        )
        assert response.status_code == 422, response.text


def test_nul_characters_in_text(database_site: Site):
    """PostgreSQL text cannot hold NUL: the service must refuse it (or store it) - never a 500."""
    site = database_site
    with site.org.client("admin") as admin:
        response = admin.post(f"{API}/structures", json={"name": "nul", "fs": FS, "description": "a\x00b"})
    assert response.status_code in (201, 422), response.text
    with site.org.client("viewer") as viewer:
        response = viewer.get(f"{API}/structures/{site.rig}/verdicts", params={"fault_mode": "k2\x00"})
    assert response.status_code in (200, 422), response.text
    if response.status_code == 200:
        assert response.json()["items"] == []


def test_history_filters_outside_the_representable_range(database_site: Site):
    site = database_site
    cursor = base64.urlsafe_b64encode(b"0001-01-01T00:00:00+05:00|7").decode()
    queries = [
        {"start": "0001-01-01T00:00:00+05:00"},
        {"end": "9999-12-31T23:00:00-05:00"},
        {"cursor": cursor},
        {"cursor": base64.urlsafe_b64encode(b"2026-01-01T00:00:00+00:00|99999999999").decode()},
    ]
    failures = []
    for query in queries:
        with site.org.client("viewer") as viewer:
            response = viewer.get(f"{API}/structures/{site.rig}/verdicts", params=query)
        if response.status_code not in (200, 422):
            failures.append(f"{query} -> {response.status_code} {response.text[:100]}")
    assert not failures, "\n".join(failures)


AUTHORIZATIONS = {
    "none": (None, "missing API key"),
    "not-bearer": ("Basic dXNlcjpwYXNz", "missing API key"),
    "bare-bearer": ("Bearer", "missing API key"),
    "garbage": ("Bearer not-a-key", "the API key is not valid"),
    "unknown-prefix": ("Bearer nw_000000000000_" + "A" * 43, "the API key is not valid"),
    "wrong-secret": ("Bearer {tampered}", "the API key is not valid"),
}


@pytest.mark.parametrize(("authorization", "message"), AUTHORIZATIONS.values(), ids=AUTHORIZATIONS.keys())
def test_missing_or_invalid_api_key(site: Site, api_server, authorization, message):
    key = site.org.keys["admin"]
    tampered = key[:-1] + ("A" if key[-1] != "A" else "B")
    headers = {"Authorization": authorization.format(tampered=tampered)} if authorization else {}
    requests = [
        ("GET", "/structures", None),
        ("GET", f"/structures/{site.rig}", None),
        ("POST", "/structures", b'{"name": ""}'),  # authentication comes before validation
        ("POST", f"/structures/{site.rig}/models/baseline", b'{"record_ids": [1]}'),
        ("POST", f"/structures/{site.rig}/records", raw_json(json_body(300))),
        ("POST", f"/records/{site.training[0]['record_id']}/inspect", None),
    ]
    with nothing_written(site.org, site.rig), http_client(base_url=api_server.url, timeout=60) as anonymous:
        for method, path, content in requests:
            response = anonymous.request(
                method, API + path, content=content, headers={**headers, "Content-Type": "application/json"}
            )
            assert_refused(response, 401, message)
            assert response.headers["www-authenticate"] == "Bearer"


@pytest.mark.parametrize("role", [None, "admin"], ids=["anonymous", "admin"])
@pytest.mark.parametrize("path", ["/structures", "/structures/1/models/fault-modes"])
def test_json_bodies_are_bounded_too(small: Small, role, path):
    """A body declared far over the limit is answered at once (401 or 413 without a key, 413
    with one) on every route, not only on record uploads: nothing should wait for 10 GB."""
    authorization = f"Authorization: Bearer {small.org.keys[role]}\r\n" if role else ""
    head = (
        f"POST {API}{path} HTTP/1.1\r\nHost: 127.0.0.1\r\n{authorization}"
        "Content-Type: application/json\r\nContent-Length: 10000000000\r\n\r\n"
    ).encode()
    with socket.create_connection(("127.0.0.1", small.server.port), timeout=3) as connection:
        connection.sendall(head + b'{"name": "' + b"a" * 4096)
        try:
            answer = connection.recv(65536)
        except TimeoutError:
            pytest.fail(f"POST {path} with a 10 GB body: no answer within 3 s, the server waits for it all")
    expected = (b"HTTP/1.1 413",) if role else (b"HTTP/1.1 401", b"HTTP/1.1 413")
    assert answer.startswith(expected), answer[:200]


def test_a_1_gib_upload_is_refused_without_being_read(small: Small):
    """Content-Length: 1 GiB on the record upload: 413 at once, after 64 KiB of it were sent,
    so the server neither waited for nor buffered the body."""
    head = (
        f"POST {records_url(small.structure_id)} HTTP/1.1\r\nHost: 127.0.0.1\r\n"
        f"Authorization: Bearer {small.org.keys['ingest']}\r\nContent-Type: application/x-npz\r\n"
        f"Content-Length: {2**30}\r\n\r\n"
    ).encode()
    with socket.create_connection(("127.0.0.1", small.server.port), timeout=3) as connection:
        connection.sendall(head + b"\0" * 65536)
        try:
            answer = connection.recv(65536)
        except TimeoutError:
            pytest.fail("a 1 GiB upload got no answer within 3 s: the server waits for the body")
    assert answer.startswith(b"HTTP/1.1 413"), answer[:200]
    assert b"exceeds the limit" in answer
