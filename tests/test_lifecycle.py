"""One request lifecycle: bounded waits for a connection and for a body, one commit per request,
and the SQLite writer gate taken by the engine.

- Slow bodies (issue 13, finding 2): one organisation's ingest key opens 40 uploads that send
  their JSON 2 bytes at a time against a real ``narxwatch serve``, on SQLite and on PostgreSQL,
  while another organisation's client times ``GET /structures``. The slow clients must get 408
  and the other organisation no 5xx and a p95 of at most a second: a request that holds a pooled
  connection while its body trickles in starves every other.
- Slow heads: 3 000 connections that trickle a request head they never end, against the same
  server with ``NARXWATCH_HEADER_TIMEOUT_SECONDS`` short and the soft limit on open files a
  systemd service gets by default: each is closed by the server once the deadline has passed,
  and the other organisation, opening a new connection for every request, is served throughout
  within the slow-body bound. Without the deadline a head could be trickled for ever, and the
  connections held used up the server's file descriptors, so that it accepted no one else.
- The head's deadline runs from a connection's opening and from the end of each response on a
  keep-alive connection, and stops when the head is complete: a connection that says nothing is
  closed silently, a next head trickled after a response is answered 408 and closed, and heads
  each sent within the deadline are all served, however long the connection lives.
- On a route whose body FastAPI parses and on one that reads it itself, a body too slow is 408
  and a chunked body past the limit 413.
- A full connection pool is a 503 with ``Retry-After`` after ``NARXWATCH_POOL_TIMEOUT_SECONDS``.
- A commit that fails is never answered 2xx: the request's session commits before the response
  is sent (a deferred PostgreSQL constraint trigger makes the COMMIT itself fail).
- A write through a domain function waits for the writer gate without asking for it.
"""

from __future__ import annotations

import asyncio
import itertools
import json
import os
import random
import resource
import signal
import socket
import subprocess
import sys
import textwrap
import threading
import time
import uuid
from collections.abc import Callable, Iterator
from dataclasses import dataclass
from pathlib import Path

import httpx
import numpy as np
import pytest
import uvloop
from prometheus_client.parser import text_string_to_metric_families
from sqlalchemy import exc, func, select

from harness import migrated
from harness.api_helpers import API, create_structure, json_body, time_victim
from harness.cli import NARXWATCH
from harness.job_helpers import database_url as new_database
from harness.live import LiveServer, free_port, http_client, wait_until_serving
from service.config import Settings
from service.db import make_engine, session_factory, transaction
from service.domain import structures
from service.schemas import StructureCreate
from service.security import Role, authenticate, create_key
from service.tables import Organisation, Record, Structure

ROOT = Path(__file__).resolve().parents[1]
SLOW_CLIENTS = 40
BODY_TIMEOUT = 3.0  # NARXWATCH_BODY_TIMEOUT_SECONDS of the served app: short, so the test ends soon
TRICKLE_PAUSE = 0.1  # seconds between two 2-byte pieces of a slow body
VICTIM_P95 = 1.0  # seconds
POOL_TIMEOUT = 0.5  # NARXWATCH_POOL_TIMEOUT_SECONDS of the pool test
SLOW_HEADS = 3000
HEADER_TIMEOUT = 2.0  # NARXWATCH_HEADER_TIMEOUT_SECONDS of the served app
HEAD_PAUSE = 0.5  # seconds between two pieces of a slow head
# A slow connection is seen closed this long after its deadline at most: the client's clock runs
# from before it connects, and it notices the end late while thousands of connections share its
# event loop, on a machine whose two cores other work shares.
CLOSE_MARGIN = 2.0
EARLY = 0.005  # the server's event loop keeps time in milliseconds: its timers may end this early
# Of thousands of slow heads, a loaded machine's client notices most closes late, many of them
# long after the deadline; the first hundredth it notices at the deadline itself. They
# are held to within half a deadline of the one the server is told: a server keeping a deadline
# half as long again would close none of them by then.
FIRST_CLOSES_MARGIN = 0.5 * HEADER_TIMEOUT
# The soft limit on open files of a systemd service (LimitNOFILE's default): the server raises it
# to the hard limit, or 3 000 connections would leave it no descriptor to accept another.
SERVICE_OPEN_FILES = 1024


def _service_open_files() -> None:
    _, hard = resource.getrlimit(resource.RLIMIT_NOFILE)
    resource.setrlimit(resource.RLIMIT_NOFILE, (SERVICE_OPEN_FILES, hard))


@dataclass
class Served:
    port: int
    attacker: str  # an ingest key of one organisation
    attacker_admin: str
    victim: str  # a viewer key of another

    @property
    def url(self) -> str:
        return f"http://127.0.0.1:{self.port}"


@pytest.fixture(params=["sqlite", "postgresql"])
def database_url(request, tmp_path) -> str:
    return new_database(request.param, tmp_path, request)


@pytest.fixture(scope="module", params=["sqlite", "postgresql"])
def served(request, tmp_path_factory) -> Iterator[Served]:
    """``narxwatch serve`` in one worker process, so that all the slow clients meet one pool. One
    server a database for the slow bodies and the slow heads: each test ends with every slow
    connection closed by the server (asserted), and neither changes what the other's asserts."""
    tmp_path = tmp_path_factory.mktemp("served")
    database_url = new_database(request.param, tmp_path, request)
    env = {
        **os.environ,
        "NARXWATCH_DATABASE_URL": database_url,
        "NARXWATCH_BODY_TIMEOUT_SECONDS": str(BODY_TIMEOUT),
        "NARXWATCH_HEADER_TIMEOUT_SECONDS": str(HEADER_TIMEOUT),
        "NARXWATCH_LOG_FORMAT": "text",
    }
    port = free_port()
    log = tmp_path / "serve.log"
    with log.open("w") as output:
        server = subprocess.Popen(
            [NARXWATCH, "serve", "--port", str(port), "--workers", "1"],
            env=env,
            stderr=output,
            stdout=output,
            preexec_fn=_service_open_files,
        )
    try:
        wait_until_serving(f"http://127.0.0.1:{port}", server, 120, log.read_text)
        engine = make_engine(database_url)
        with transaction(session_factory(engine)) as session:
            attacker_org, victim_org = (f"org-{uuid.uuid4().hex[:12]}" for _ in range(2))
            keys = Served(
                port,
                attacker=create_key(session, attacker_org, Role.ingest),
                attacker_admin=create_key(session, attacker_org, Role.admin),
                victim=create_key(session, victim_org, Role.viewer),
            )
        engine.dispose()
        yield keys
    finally:
        server.send_signal(signal.SIGINT)
        server.wait(timeout=30)


async def slow_upload(port: int, path: str, key: str, body: bytes, patience: float) -> int | None:
    """POST ``body`` 2 bytes at a time; the status of the answer, or None if none came in ``patience`` s."""
    reader, writer = await asyncio.open_connection("127.0.0.1", port)
    head = (
        f"POST {path} HTTP/1.1\r\nHost: 127.0.0.1:{port}\r\nAuthorization: Bearer {key}\r\n"
        f"Content-Type: application/json\r\nContent-Length: {len(body)}\r\n\r\n"
    )
    writer.write(head.encode())

    async def trickle() -> None:
        try:
            for start in range(0, len(body), 2):
                writer.write(body[start : start + 2])
                await writer.drain()
                await asyncio.sleep(TRICKLE_PAUSE)
        except ConnectionError:  # the server answered and closed the connection
            pass

    sending = asyncio.create_task(trickle())
    try:
        status_line = await asyncio.wait_for(reader.readline(), patience)
        return int(status_line.split()[1]) if status_line else None
    except TimeoutError:
        return None
    finally:
        sending.cancel()
        writer.close()


def test_slow_bodies_get_408_and_never_slow_another_organisation(served: Served):
    headers = {"Authorization": f"Bearer {served.attacker_admin}"}
    with http_client(base_url=served.url, headers=headers) as admin:
        structure_id = create_structure(admin)["id"]
    path = f"{API}/structures/{structure_id}/records"
    body = json.dumps(json_body(2000, seed=5)).encode()  # ~80 kB: hours at 2 bytes per piece
    patience = BODY_TIMEOUT + 20

    async def scenario() -> tuple[list[int | None], list[tuple[float, int | None]]]:
        slow = [
            asyncio.create_task(slow_upload(served.port, path, served.attacker, body, patience))
            for _ in range(SLOW_CLIENTS)
        ]
        timings = await time_victim(served.url, served.victim, slow)
        return list(await asyncio.gather(*slow)), timings

    started = time.monotonic()
    statuses, timings = asyncio.run(scenario())
    elapsed = time.monotonic() - started
    assert len(timings) >= 10, f"only {len(timings)} requests of the other organisation were timed"
    failed = [status for _, status in timings if status != 200]
    assert not failed, f"the other organisation got {failed} among {len(timings)} requests"
    p95 = float(np.percentile([seconds for seconds, _ in timings], 95))
    assert p95 <= VICTIM_P95, f"the other organisation's p95 was {p95:.2f} s"
    assert statuses == [408] * SLOW_CLIENTS, f"slow clients answered {sorted(statuses, key=str)}"
    assert elapsed < BODY_TIMEOUT + 10, f"the slow bodies were cut after {elapsed:.1f} s"


def slow_head_pieces() -> Iterator[bytes]:
    """A request head 3 bytes at a time, header after header, never ending."""
    head = itertools.chain(
        [b"GET /healthz HTTP/1.1\r\nHost: 127.0.0.1\r\n"],
        (b"X-Slow-%d: 1\r\n" % n for n in itertools.count()),
    )
    for line in head:
        yield from (line[start : start + 3] for start in range(0, len(line), 3))


@dataclass
class Closed:
    """How a connection trickling a head ended: ``after`` seconds from when the deadline began
    (None: still open when the client gave up), with what the server wrote."""

    after: float | None
    received: bytes


async def trickle_head(
    reader: asyncio.StreamReader, writer: asyncio.StreamWriter, began: float, patience: float
) -> Closed:
    """Send a head that never ends, ``HEAD_PAUSE`` s between pieces, until the server closes the
    connection (end of stream or reset) or ``patience`` s pass; ``began``: when its deadline did,
    at the latest (``time.monotonic``)."""

    async def trickle() -> None:
        await asyncio.sleep(random.uniform(0, HEAD_PAUSE))  # the pieces of all spread over a pause
        try:
            for piece in slow_head_pieces():
                writer.write(piece)
                await writer.drain()
                await asyncio.sleep(HEAD_PAUSE)
        except ConnectionError:  # closed by the server
            pass

    sending = asyncio.create_task(trickle())
    received = b""
    try:
        async with asyncio.timeout(patience):
            while chunk := await reader.read(4096):
                received += chunk
    except TimeoutError:
        return Closed(None, received)
    except ConnectionError:
        pass
    finally:
        sending.cancel()
        writer.close()
    return Closed(time.monotonic() - began, received)


async def slow_head(port: int, patience: float) -> Closed:
    began = time.monotonic()  # before connecting: the server's deadline runs from its accepting
    return await trickle_head(*await asyncio.open_connection("127.0.0.1", port), began, patience)


def time_victim_on_new_connections(served: Served, going: Callable[[int], bool]) -> list[float]:
    """``GET /structures`` of the other organisation, each on a new connection, one after another
    while ``going(requests timed so far)``. Fails at the first answer that is not 200. Called in a
    thread of its own, its clock not slowed by the event loop of thousands of slow connections."""
    timings: list[float] = []
    headers = {"Authorization": f"Bearer {served.victim}"}
    one_use = httpx.Limits(max_keepalive_connections=0)  # the server must accept a new one each time
    with http_client(base_url=served.url, headers=headers, timeout=10, limits=one_use) as client:
        while going(len(timings)):
            started = time.monotonic()
            response = client.get(f"{API}/structures")
            assert response.status_code == 200, f"the other organisation got {response.status_code}"
            timings.append(time.monotonic() - started)
    return timings


@pytest.fixture
def many_open_files() -> Iterator[None]:
    """Room in this process for the slow connections' sockets, beside its own files."""
    soft, hard = resource.getrlimit(resource.RLIMIT_NOFILE)
    needed = SLOW_HEADS + 500
    assert hard == resource.RLIM_INFINITY or hard >= needed, f"the hard limit on open files is {hard}"
    resource.setrlimit(resource.RLIMIT_NOFILE, (max(soft, needed), hard))
    yield
    resource.setrlimit(resource.RLIMIT_NOFILE, (soft, hard))


def test_slow_heads_are_closed_at_the_deadline_and_never_slow_another_organisation(
    served: Served, many_open_files: None
):
    baseline = time_victim_on_new_connections(served, lambda timed: timed < 20)
    patience = HEADER_TIMEOUT + 8
    attacking = threading.Event()
    attacking.set()
    timings: list[float] = []
    victim_failed: list[Exception] = []

    def victim() -> None:
        try:
            timings.extend(time_victim_on_new_connections(served, lambda _: attacking.is_set()))
        except Exception as error:  # failed in this thread: reported in the test's
            victim_failed.append(error)

    async def attack() -> list[Closed]:
        waves = []
        for _ in range(SLOW_HEADS // 300):  # opened a wave at a time: no burst past the backlog
            waves += [asyncio.create_task(slow_head(served.port, patience)) for _ in range(300)]
            await asyncio.sleep(0.1)
        return list(await asyncio.gather(*waves))

    timer = threading.Thread(target=victim)
    timer.start()
    try:
        closed = uvloop.run(attack())
    finally:
        attacking.clear()
        timer.join()
    assert not victim_failed, f"the other organisation failed: {victim_failed[0]!r}"
    assert len(timings) >= 10, f"only {len(timings)} requests of the other organisation were timed"
    p95, before = (float(np.percentile(sample, 95)) for sample in (timings, baseline))
    assert p95 <= VICTIM_P95, f"the other organisation's p95 was {p95:.2f} s ({before:.2f} s unattacked)"
    # Every slow head closed (a deadline not kept holds them past the client's patience), none
    # before the deadline the server is told, and the first hundredth at it.
    held = sum(end.after is None for end in closed)
    assert not held, f"{held} of {SLOW_HEADS} slow heads were still open after {patience:.0f} s"
    seconds = sorted(end.after for end in closed if end.after is not None)
    first = seconds[len(seconds) // 100]
    assert seconds[0] >= HEADER_TIMEOUT - EARLY and first <= HEADER_TIMEOUT + FIRST_CLOSES_MARGIN, (
        f"closed after {seconds[0]:.3f} to {seconds[-1]:.2f} s (a hundredth by {first:.2f} s, "
        f"median {seconds[len(seconds) // 2]:.2f} s)"
    )
    answers = {end.received.partition(b"\r\n")[0] for end in closed}
    assert answers <= {b"", b"HTTP/1.1 408 Request Timeout"}, answers
    told = f"did not arrive within {HEADER_TIMEOUT:g} s".encode()
    assert all(told in end.received for end in closed if end.received), "a 408 named another deadline"


async def read_answer(reader: asyncio.StreamReader) -> tuple[int, bytes]:
    """The status and body of one answer on a keep-alive connection."""
    head = await reader.readuntil(b"\r\n\r\n")
    lines = head.decode().split("\r\n")
    length = next(int(line.split(":")[1]) for line in lines if line.lower().startswith("content-length:"))
    return int(lines[0].split()[1]), await reader.readexactly(length)


async def paced_requests(port: int, count: int) -> list[int]:
    """``count`` requests on one connection, each head trickled over most of the deadline."""
    reader, writer = await asyncio.open_connection("127.0.0.1", port)
    statuses = []
    for _ in range(count):
        for line in (b"GET /healthz HTTP/1.1\r\n", b"Host: 127.0.0.1\r\n", b"\r\n"):
            writer.write(line)
            await asyncio.sleep(0.6 * HEADER_TIMEOUT / 3)
        statuses.append((await read_answer(reader))[0])
    writer.close()
    return statuses


async def answered_then_trickled(port: int, patience: float) -> tuple[int, Closed]:
    """One request answered on a keep-alive connection, then a next head trickled."""
    reader, writer = await asyncio.open_connection("127.0.0.1", port)
    began = time.monotonic()  # before the answer, whose end starts the deadline
    writer.write(b"GET /healthz HTTP/1.1\r\nHost: 127.0.0.1\r\n\r\n")
    status, _ = await read_answer(reader)
    return status, await trickle_head(reader, writer, began, patience)


async def silent(port: int, patience: float) -> Closed:
    """A connection that sends nothing."""
    began = time.monotonic()
    reader, writer = await asyncio.open_connection("127.0.0.1", port)
    try:
        received = await asyncio.wait_for(reader.read(), patience)
    except TimeoutError:
        return Closed(None, b"")
    finally:
        writer.close()
    return Closed(time.monotonic() - began, received)


def test_the_head_deadline_runs_from_the_opening_and_from_each_answer(tmp_path: Path):
    settings = Settings(
        database_url=migrated.sqlite(tmp_path / "narxwatch.db"), header_timeout_seconds=HEADER_TIMEOUT
    )
    patience = HEADER_TIMEOUT + 8

    async def scenario() -> tuple[list[int], tuple[int, Closed], Closed]:
        return await asyncio.gather(
            paced_requests(server.port, 3),
            answered_then_trickled(server.port, patience),
            silent(server.port, patience),
        )

    def timeouts(url: str) -> dict[str, float]:
        """The head timeouts /metrics counts, by what had arrived of the head."""
        (family,) = [
            family
            for family in text_string_to_metric_families(httpx.get(f"{url}/metrics").text)
            if family.name == "narxwatch_http_header_timeouts"
        ]
        counts = {"part": 0.0, "none": 0.0}
        counts |= {s.labels["head"]: s.value for s in family.samples if s.name.endswith("_total")}
        return counts

    with LiveServer(settings) as server:
        before = timeouts(server.url)
        paced, (answered, trickled), quiet = asyncio.run(scenario())
        after = timeouts(server.url)
    # One connection closed with part of a head, one that sent nothing: counted, not logged.
    assert {head: after[head] - before[head] for head in after} == {"part": 1, "none": 1}
    assert paced == [200] * 3  # 3 heads in 1.2 s each: longer than one deadline in all, and served
    assert answered == 200
    for closed in (trickled, quiet):
        assert closed.after is not None, "the connection was still open"
        assert HEADER_TIMEOUT - EARLY <= closed.after <= HEADER_TIMEOUT + CLOSE_MARGIN, (
            f"closed after {closed.after:.3f} s"
        )
    assert trickled.received.startswith(b"HTTP/1.1 408 "), trickled.received
    assert b"NARXWATCH_HEADER_TIMEOUT_SECONDS" in trickled.received
    assert quiet.received == b"", quiet.received  # nothing asked, nothing answered: as keep-alive's end


def test_a_full_pool_is_a_503_with_retry_after(database_url: str):
    settings = Settings(database_url=database_url, pool_timeout_seconds=POOL_TIMEOUT)
    with LiveServer(settings) as server, server.client(server.key(Role.viewer)) as client:
        assert client.get(f"{API}/structures").status_code == 200
        engine = server.app.state.engine
        held = []
        try:
            while True:  # take every connection the pool will give
                held.append(engine.connect())
        except exc.TimeoutError:
            pass
        try:
            started = time.monotonic()
            response = client.get(f"{API}/structures", timeout=10)
            waited = time.monotonic() - started
        finally:
            for connection in held:
                connection.close()
        assert response.status_code == 503, response.text
        assert int(response.headers["Retry-After"]) >= 1
        assert "busy" in response.json()["detail"]
        assert POOL_TIMEOUT <= waited < POOL_TIMEOUT + 2, f"answered after {waited:.2f} s"
        assert client.get(f"{API}/structures").status_code == 200  # connections back: served again


def raw_post(
    port: int, path: str, key: str, pieces: list[bytes], pause: float, declared: int | None
) -> bytes:
    """A POST whose body is sent in ``pieces``, ``pause`` s apart (until the server answers), with
    a declared ``Content-Length`` or, without one, chunked; the head of the answer."""
    length = f"Content-Length: {declared}" if declared is not None else "Transfer-Encoding: chunked"
    head = (
        f"POST {path} HTTP/1.1\r\nHost: 127.0.0.1\r\nAuthorization: Bearer {key}\r\n"
        f"Content-Type: application/json\r\n{length}\r\n\r\n"
    )
    if declared is None:
        pieces = [b"%x\r\n%s\r\n" % (len(piece), piece) for piece in pieces] + [b"0\r\n\r\n"]
    with socket.create_connection(("127.0.0.1", port), timeout=30) as connection:
        connection.sendall(head.encode())
        try:
            for piece in pieces:
                connection.sendall(piece)
                time.sleep(pause)
        except ConnectionError:  # answered and closed
            pass
        return connection.recv(65536).partition(b"\r\n\r\n")[0]


@pytest.mark.parametrize("route", ["structures", "records"])
def test_every_route_bounds_its_body_in_time_and_size(tmp_path: Path, route: str):
    """A route whose body FastAPI parses (structures) and one that reads it itself (records):
    a body too slow is 408, a chunked body past the limit 413 (not the 400 FastAPI's body
    parsing makes of other errors); both close the connection, whose body is left unread."""
    database = migrated.sqlite(tmp_path / "narxwatch.db")
    limits = {"max_upload_bytes": 4000, "max_request_bytes": 4000}
    settings = Settings(database_url=database, body_timeout_seconds=1.0, **limits)
    with LiveServer(settings) as server:
        key = server.key(Role.admin)
        path = f"{API}/structures"
        if route == "records":
            with server.client(key) as admin:
                path = f"{API}/structures/{create_structure(admin)['id']}/records"
        slow = raw_post(server.port, path, key, [b"{ "] * 100, 0.05, declared=1000)
        assert slow.startswith(b"HTTP/1.1 408 "), slow
        assert b"connection: close" in slow.lower()
        large = raw_post(server.port, path, key, [b" " * 1000] * 5, 0.0, declared=None)
        assert large.startswith(b"HTTP/1.1 413 "), large
        assert b"connection: close" in large.lower()


def test_only_record_uploads_take_bodies_the_size_of_a_record(tmp_path: Path):
    """Every other route takes a small JSON document (NARXWATCH_MAX_REQUEST_BYTES), refused before
    it is parsed, authenticated or not: FastAPI parses it before the route, and nested empty
    arrays cost Python some 25 times their text. Uploads of records and record sets take up to
    NARXWATCH_MAX_UPLOAD_BYTES."""
    database = migrated.sqlite(tmp_path / "narxwatch.db")
    settings = Settings(database_url=database, max_request_bytes=2000, max_upload_bytes=8000)
    nested = b"[" + b"[]," * 1700 + b"[]]"  # 5 kB
    document = b'{"x": "' + b"a" * 5000 + b'"}'
    with (
        LiveServer(settings) as server,
        server.client(server.key(Role.admin)) as admin,
        server.client() as anonymous,
    ):
        structure_id = create_structure(admin)["id"]
        headers = {"Content-Type": "application/json"}
        for client in (admin, anonymous):
            refused = client.post(f"{API}/structures", content=nested, headers=headers)
            assert refused.status_code == 413, refused.text
            assert "2000 bytes (NARXWATCH_MAX_REQUEST_BYTES)" in refused.json()["detail"]
        for route in ("records", "record-sets"):
            path = f"{API}/structures/{structure_id}/{route}"
            read = admin.post(path, content=document, headers=headers)
            assert read.status_code in (415, 422), read.text  # read, and refused for what it holds
            too_large = admin.post(path, content=document * 2, headers=headers)
            assert too_large.status_code == 413, too_large.text
            assert "8000 bytes (NARXWATCH_MAX_UPLOAD_BYTES)" in too_large.json()["detail"]
        with server.app.state.engine.connect() as connection:
            assert connection.scalar(select(func.count()).select_from(Record)) == 0
            assert connection.scalar(select(func.count()).select_from(Structure)) == 1


REFUSE_AT_COMMIT = """
CREATE FUNCTION refuse_at_commit() RETURNS trigger LANGUAGE plpgsql AS $$
BEGIN RAISE EXCEPTION 'refused at commit'; END $$;
CREATE CONSTRAINT TRIGGER refuse_at_commit AFTER INSERT ON structures
DEFERRABLE INITIALLY DEFERRED FOR EACH ROW WHEN (NEW.name = 'refused-at-commit')
EXECUTE FUNCTION refuse_at_commit();
"""


def test_a_failed_commit_is_never_answered_2xx(postgres_url: str):
    """The COMMIT itself fails (a deferred trigger): had the session been committed after the
    response was sent, the client would have had its 201 for a structure that does not exist."""
    url = migrated.postgresql(postgres_url, f"narxwatch_commit_{uuid.uuid4().hex[:8]}")
    with LiveServer(Settings(database_url=url)) as server, server.client(server.key(Role.admin)) as admin:
        with server.app.state.engine.begin() as connection:
            connection.exec_driver_sql(REFUSE_AT_COMMIT)
        refused = admin.post(f"{API}/structures", json={"name": "refused-at-commit", "fs": 1500.0})
        assert not refused.is_success, refused.text
        assert refused.status_code == 500
        accepted = admin.post(f"{API}/structures", json={"name": "accepted", "fs": 1500.0})
        assert accepted.status_code == 201, accepted.text
        with server.app.state.engine.connect() as connection:  # committed before the answer
            names = connection.scalars(select(Structure.name)).all()
        assert names == ["accepted"]


GATE_HOLDER = textwrap.dedent(
    """
    import sys
    from pathlib import Path
    from service.db import WriterGate

    with WriterGate(Path(sys.argv[1])).held():
        print("held", flush=True)
        sys.stdin.readline()
    """
)


def test_a_domain_write_on_sqlite_takes_the_writer_gate_unasked(tmp_path: Path):
    """Another process holds the gate: a read goes on, a structure created through the domain
    function (which never mentions the gate) waits until the gate is let go, then is stored."""
    database = tmp_path / "narxwatch.db"
    url = migrated.sqlite(database)
    sessions = session_factory(make_engine(url))
    with transaction(sessions) as session:
        key = create_key(session, "gated", Role.admin)
    holder = subprocess.Popen(
        [sys.executable, "-c", GATE_HOLDER, str(database)],
        cwd=ROOT,
        stdin=subprocess.PIPE,
        stdout=subprocess.PIPE,
        text=True,
    )
    written = threading.Event()

    def write() -> None:
        with sessions() as session:
            principal = authenticate(session, key)
            assert principal is not None
            structures.create_structure(session, principal, StructureCreate(name="gated", fs=1500.0))
            session.commit()
        written.set()

    try:
        assert holder.stdout is not None and holder.stdin is not None
        assert holder.stdout.readline().strip() == "held"
        with sessions() as session:  # reads never wait for the gate
            assert session.scalars(select(Structure)).all() == []
        writer = threading.Thread(target=write)
        writer.start()
        assert not written.wait(1.0), "a domain write went ahead while another process held the gate"
        holder.stdin.write("release\n")
        holder.stdin.flush()
        assert written.wait(10), "the write stayed blocked after the gate was let go"
        writer.join()
    finally:
        holder.kill()
        holder.wait()
    with sessions() as session:
        assert session.scalars(select(Structure.name)).all() == ["gated"]


def test_the_gate_is_given_back_at_commit_and_at_rollback(tmp_path: Path):
    """Two threads of one process: the second writer waits while the first's write transaction
    is open, and goes ahead once it ends, however it ends."""
    url = migrated.sqlite(tmp_path / "narxwatch.db")
    sessions = session_factory(make_engine(url))

    def second_write(name: str, done: threading.Event) -> None:
        with transaction(sessions) as session:
            session.add(Organisation(name=name))
        done.set()

    for end in ("commit", "rollback"):
        with sessions() as first:
            first.add(Organisation(name=end))
            first.flush()
            second_done = threading.Event()
            thread = threading.Thread(target=second_write, args=(f"after-{end}", second_done))
            thread.start()
            assert not second_done.wait(0.5), f"a second writer went ahead before the first's {end}"
            getattr(first, end)()
            assert second_done.wait(10), f"the gate was not given back at {end}"
            thread.join()
    with sessions() as session:
        names = session.scalars(select(Organisation.name).order_by(Organisation.id)).all()
    assert names == ["commit", "after-commit", "after-rollback"]
