"""What an upload body and a record's values may be (issue 13): hostile NPZ archives, values whose
statistics overflow, one length rule, a tolerant rate check made first, and a queued re-upload that
tells the truth.

Through HTTP against the real app on SQLite: every refusal here is made before the database is
reached. A refused upload leaves nothing behind (``api_helpers.nothing_written``), and no verdict
row holds a non-finite figure. The queued re-upload, a job on the queue, on PostgreSQL too.
"""

from __future__ import annotations

import math
import resource
import socket
import threading
import time
from dataclasses import dataclass

import httpx
import numpy as np
import pytest
from sqlalchemy import select

from harness.api_helpers import (
    API,
    FS,
    Org,
    clients,
    create_structure,
    csv_text,
    detail,
    json_body,
    noise,
    nothing_written,
    npz_bytes,
    post_record,
    simulated,
    train_fault_mode,
    verdicts_of,
    wait_for,
)
from harness.live import LiveServer
from harness.npz_bombs import bomb_npz, cut_off_header_npz
from models.signals import magnitude_limit, minimum_samples
from service.tables import Verdict

NPZ = "application/x-npz"


@dataclass
class Site:
    server: LiveServer
    org: Org
    rig: int  # an active k2 fault-mode model of degree 3 (cubic stiffness), longest lag 4
    bare: int  # no models
    healthy: np.ndarray  # x, y of a healthy simulated record of the rig, 2000 samples


@pytest.fixture(scope="module")
def api_server(sqlite_api_server: LiveServer) -> LiveServer:
    return sqlite_api_server


@pytest.fixture(scope="module")
def site(api_server: LiveServer) -> Site:
    org = Org.create(api_server)
    with clients(org) as (admin, ingest, _):
        rig = create_structure(admin, "rig")["id"]
        train_fault_mode(admin, ingest, rig, "k2", seed=31)
        bare = create_structure(admin, "bare")["id"]
    record = simulated("none", 0.0, 32)
    return Site(api_server, org, rig, bare, np.stack([record.x, record.y]))


@pytest.fixture
def ingest(site: Site):
    with site.org.client("ingest") as client:
        yield client


def assert_refused(response: httpx.Response, status: int | tuple[int, ...], *fragments: str) -> str:
    assert response.status_code in (status if isinstance(status, tuple) else (status,)), response.text
    text = detail(response)
    for fragment in fragments:
        assert fragment in text, f"{fragment!r} not in {text!r}"
    return text


def peak_rss_bytes() -> int:
    """This process's peak resident set (the live server runs on a thread of it)."""
    return resource.getrusage(resource.RUSAGE_SELF).ru_maxrss * 1024


# --- hostile NPZ archives (findings 1 and 6) --------------------------------------------------


@pytest.mark.parametrize(
    ("member", "status", "fragment"),
    [
        ("fs", 422, "NPZ member 'fs' must be one number, but it unpacks to 40003"),
        ("temperature", 422, "NPZ member 'temperature' must be one number, but it unpacks to 40003"),
        ("x", 413, "the NPZ's arrays unpack to more than the upload limit"),
    ],
)
def test_npz_bomb_is_refused_before_it_is_decompressed(site: Site, ingest, member, status, fragment):
    """A 4 MB archive whose member declares 5·10⁸ float64 (4 GB): refused, and the server's peak
    memory does not grow by anything like it (it did by gigabytes, until a worker was killed)."""
    x, y = noise(300)
    bomb = bomb_npz(x, y, bomb=member, items=500_000_000)
    assert 3_000_000 < len(bomb) < site.server.settings.max_upload_bytes
    before = peak_rss_bytes()
    with nothing_written(site.org, site.rig):
        assert_refused(post_record(ingest, site.rig, bomb, NPZ), status, fragment)
    assert peak_rss_bytes() - before < 200 * 2**20


def test_npz_with_a_cut_off_npy_header_is_a_422(site: Site, ingest):
    x, _ = noise(300)
    with nothing_written(site.org, site.rig):
        response = post_record(ingest, site.rig, cut_off_header_npz(x), NPZ)
        assert_refused(response, 422, "NPZ member 'y' has a malformed .npy header")


def test_npz_with_other_members_than_scalar_conditions_is_refused(site: Site, ingest):
    x, y = noise(300)
    with nothing_written(site.org, site.rig):
        response = post_record(ingest, site.rig, npz_bytes(x=x, y=y, fs=FS, z=np.zeros(3)), NPZ)
        assert_refused(response, 422, "NPZ member 'z' holds 3 values (shape (3,)); a condition is one number")


@pytest.mark.parametrize("media", ["text/csv", "application/json"])
def test_short_numbers_cannot_make_a_record_larger_than_an_npz_could(site: Site, ingest, media):
    """A body of "0,1" rows (4 bytes a sample) would hold 4·2²⁰ samples within 16 MiB and take
    hundreds of MB to parse; a record holds at most limit/16 samples, whatever its format."""
    most = site.server.settings.max_upload_bytes // 16
    n = most + 1
    x = b"01" * (n // 2) + b"0" * (n % 2)  # a valid record but for its length: 0, 1, 0, 1, …
    y = x[::-1]
    if media == "text/csv":
        body = b"x,y\n" + b"".join(bytes([a, 44, b, 10]) for a, b in zip(x, y, strict=True))
    else:
        body = b'{"fs": 1500, "x": [' + b",".join(x[i : i + 1] for i in range(n)) + b'], "y": ['
        body += b",".join(y[i : i + 1] for i in range(n)) + b"]}"
    with nothing_written(site.org, site.bare):
        response = post_record(ingest, site.bare, body, media)
        assert_refused(response, 413, f"a record may hold at most {most} samples")


# --- values whose statistics overflow (finding 3) ---------------------------------------------


def _scaled(site: Site, x_scale: float = 1.0, y_scale: float = 1.0) -> dict:
    x, y = site.healthy
    return {"x": (x * x_scale).tolist(), "y": (y * y_scale).tolist(), "fs": FS}


def _non_finite_verdicts(site: Site) -> list[int]:
    """Ids of the rig's verdict rows with a non-finite or missing figure, read from the database."""
    with site.server.app.state.sessions() as session:
        rows = session.scalars(select(Verdict).where(Verdict.structure_id == site.rig)).all()
    bad = []
    for row in rows:
        figures = [row.z_critical, row.q_critical_detection]
        figures += [value for mode in row.modes for value in mode.values() if isinstance(value, float)]
        if row.status != "unknown_fault":
            figures += [row.k_hat, row.sigma_k, row.interval_low, row.interval_high]
        if not all(value is not None and math.isfinite(value) for value in figures):
            bad.append(row.id)
    return bad


def test_y_times_1e60_is_refused_alike_in_every_inspect_mode(site: Site, ingest):
    """Stored as healthy with null σ̂k, Q and p before; now the same 422 whether inspected on
    upload, queued, or only stored (its inspection would refuse it), and nothing is written."""
    body = _scaled(site, y_scale=1e60)
    peak = float(np.max(np.abs(site.healthy[1]))) * 1e60
    limit = magnitude_limit(2000, 3)
    assert 1e20 * limit < peak < magnitude_limit(2000, 1)  # refused for cubic terms only
    expected = f"y reaches {peak:.3g} in magnitude; with 2000 samples and terms of degree 3"
    with nothing_written(site.org, site.rig):
        on_upload = assert_refused(post_record(ingest, site.rig, body, inspect="true"), 422, expected)
        queued = assert_refused(post_record(ingest, site.rig, body, inspect="queue"), 422, expected)
        stored = assert_refused(post_record(ingest, site.rig, body, inspect="false"), 422, expected)
    assert queued == on_upload == stored
    assert _non_finite_verdicts(site) == []


@pytest.mark.parametrize("inspect", ["true", "queue", "false"])
def test_x_times_1e200_is_refused_even_without_inspection(site: Site, ingest, inspect):
    """Beyond what even linear terms' sums of squares can hold: not worth storing."""
    body = _scaled(site, x_scale=1e200)
    with nothing_written(site.org, site.rig):
        response = post_record(ingest, site.rig, body, inspect=inspect)
        assert_refused(response, 422, "x reaches", "the statistics overflow", "rescale the record")
    assert _non_finite_verdicts(site) == []


def test_a_record_within_the_bound_gets_a_finite_verdict(site: Site, ingest):
    """The bound is not a guess: y at a tenth of it still gives finite statistics."""
    y = site.healthy[1]
    scale = 0.1 * magnitude_limit(2000, 3) / float(np.max(np.abs(y)))
    response = post_record(ingest, site.rig, _scaled(site, y_scale=scale), inspect="true")
    assert response.status_code == 201, response.text
    verdict = response.json()["verdict"]
    assert all(math.isfinite(mode["q"]) and math.isfinite(mode["sigma_k"]) for mode in verdict["modes"])
    assert _non_finite_verdicts(site) == []


# --- one length rule (finding 7) --------------------------------------------------------------


@pytest.mark.parametrize("inspect", ["true", "queue"])
def test_one_length_rule_for_upload_queue_and_inspection(site: Site, ingest, inspect):
    """A record long enough to store but too short for the rig's model (longest lag 4): refused
    at upload when it is to be inspected, with the number the later inspection states."""
    lags = site.server.settings.lags
    storable, inspectable = minimum_samples(lags), minimum_samples(lags, 4)
    assert (storable, inspectable) == (5 * lags + 8, 4 + 5 * lags + 8)
    body = json_body(inspectable - 1)
    message = f"{inspectable - 1} samples is too short; this needs at least {inspectable}"
    with nothing_written(site.org, site.rig):
        assert_refused(post_record(ingest, site.rig, body, inspect=inspect), 422, message)
    stored = post_record(ingest, site.rig, body)
    assert stored.status_code == 201, stored.text
    assert_refused(ingest.post(f"{API}/records/{stored.json()['id']}/inspect"), 422, message)


# --- the sampling rate (finding 7) ------------------------------------------------------------


def test_a_rate_equal_but_for_rounding_is_the_structures(site: Site, ingest):
    body = json_body(300, fs=1500.0000001)
    response = post_record(ingest, site.bare, body)
    assert response.status_code == 201, response.text
    assert response.json()["fs"] == FS
    body["fs"] = FS  # the same data at the exact rate is the same record
    assert post_record(ingest, site.bare, body).json()["id"] == response.json()["id"]


def test_a_refused_rate_is_printed_with_the_digits_that_differ(site: Site, ingest):
    with nothing_written(site.org, site.bare):
        response = post_record(ingest, site.bare, json_body(300, fs=1500.00001))
        assert_refused(response, 422, "sampled at 1500.00001 Hz but structure 'bare' is monitored at 1500 Hz")


def test_the_rate_is_checked_before_any_inspection(site: Site, ingest):
    """Too short for the model and at a wrong rate: the rate, checked first, is what is refused."""
    body = json_body(100, fs=1000.0)
    with nothing_written(site.org, site.rig):
        response = post_record(ingest, site.rig, body, inspect="true")
        assert_refused(response, 422, "sampled at 1000 Hz but structure 'rig' is monitored at 1500 Hz")


# --- parsing off the event loop (issue 13, from reading the code) ------------------------------


def test_a_body_is_parsed_off_the_event_loop(site: Site):
    """While a 13 MB CSV is parsed (to fail at its last line), the server answers other requests:
    a /healthz sent after the whole body had gone out is answered before the upload is. Parsed on
    the event loop, as before, nothing else was answered until the parse had ended."""
    x, y = noise(300_000)
    content = (csv_text(x, y) + "1.0,abc\n").encode()
    assert 10 * 2**20 < len(content) < site.server.settings.max_upload_bytes
    head = (
        f"POST {API}/structures/{site.rig}/records HTTP/1.1\r\nHost: 127.0.0.1\r\n"
        f"Authorization: Bearer {site.org.keys['ingest']}\r\nContent-Type: text/csv\r\n"
        f"Content-Length: {len(content)}\r\nConnection: close\r\n\r\n"
    ).encode()
    polls: list[tuple[float, float]] = []  # (sent, answered) of each /healthz
    stop = threading.Event()

    def poll() -> None:
        with site.server.client() as client:
            while not stop.is_set():
                sent = time.monotonic()
                assert client.get("/healthz").status_code == 200
                polls.append((sent, time.monotonic()))

    poller = threading.Thread(target=poll)
    poller.start()
    try:
        with socket.create_connection(("127.0.0.1", site.server.port)) as upload:
            upload.sendall(head + content)
            body_sent = time.monotonic()
            answer = b"".join(iter(lambda: upload.recv(65536), b""))
            answered = time.monotonic()
    finally:
        stop.set()
        poller.join()
    assert answer.startswith(b"HTTP/1.1 422"), answer[:300]
    assert b"'abc' in column 'y' is not a number" in answer
    assert any(body_sent < sent and done < answered for sent, done in polls), "no request answered meanwhile"


# --- a queued re-upload (issue 13, from reading the code) -------------------------------------


def test_queued_reupload_inspects_with_the_current_models(admin_of_new_rig):
    """A record whose verdict is from older models is queued again, and answers so truthfully;
    one whose verdict is from the active models is not queued, and gets that verdict back."""
    org, rig = admin_of_new_rig
    record = simulated("k2", 12.0, 33)
    body = npz_bytes(x=record.x, y=record.y, fs=record.fs)
    with clients(org) as (admin, ingest, viewer):
        first = post_record(ingest, rig, body, NPZ, inspect="true")
        assert first.status_code == 201, first.text
        record_id, old = first.json()["id"], first.json()["verdict"]["model_versions"]
        newer = train_fault_mode(admin, ingest, rig, "k2", seed=35)
        again = post_record(ingest, rig, body, NPZ, inspect="queue")
        assert again.status_code == 202, again.text
        answer = again.json()
        assert (answer["id"], answer["created"], answer["verdict"]) == (record_id, False, None)

        def verdict_of_newer_model() -> dict | None:
            found = [v for v in verdicts_of(viewer, rig, record_id) if v["model_versions"] != old]
            return found[0] if found else None

        verdict = wait_for(verdict_of_newer_model, 60, "the queued inspection with the newer model")
        assert verdict["model_versions"] == [{"id": newer["id"], "name": "k2", "version": newer["version"]}]
        once_more = post_record(ingest, rig, body, NPZ, inspect="queue")
        assert once_more.status_code == 200, once_more.text
        assert once_more.json()["verdict"]["id"] == verdict["id"]
        assert len(verdicts_of(viewer, rig, record_id)) == 2


@pytest.fixture
def admin_of_new_rig(database_server: LiveServer) -> tuple[Org, int]:
    """An organisation with a structure and a trained k2 model of its own, on each database: the
    re-upload is queued as a job."""
    org = Org.create(database_server)
    with clients(org) as (admin, ingest, _):
        rig = create_structure(admin, "requeued")["id"]
        train_fault_mode(admin, ingest, rig, "k2", seed=34)
    return org, rig
