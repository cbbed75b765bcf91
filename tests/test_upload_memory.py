"""Uploads whose parse costs memory beyond their size, sent at once against a real server.

- A header of a million columns: twelve 8 MB CSVs whose header names 10⁶ columns,
  sent at once by one organisation's ingest key to a real ``narxwatch serve`` of one process on
  SQLite, while another organisation's client times ``GET /structures``; and twelve of 16 MB to
  two worker processes on PostgreSQL. Each header cost the server about thirty times its size
  in cells before the 422, all twelve at once gigabytes, and the other organisation's reads
  seconds. Every upload must be refused with a 4xx, the server's memory (the resident sets of
  its processes) grow by at most 600 MB, and the other organisation's p95 stay within half a
  second. The header is refused before anything reaches the database: the two attacks are each
  database once, one process and several, not every pairing of them.
- Parses beyond ``NARXWATCH_MAX_CONCURRENT_UPLOADS`` wait at most
  ``NARXWATCH_UPLOAD_WAIT_SECONDS``, then are answered 503 with Retry-After.
"""

from __future__ import annotations

import asyncio
import os
import signal
import subprocess
import threading
import time
import uuid
from collections.abc import Iterator
from dataclasses import dataclass
from pathlib import Path

import httpx
import numpy as np
import pytest

from harness.api_helpers import API, create_structure, csv_text, noise, time_victim
from harness.cli import NARXWATCH
from harness.live import LiveServer, free_port, http_client, wait_until_serving
from service.config import Settings
from service.db import make_engine, session_factory, transaction
from service.security import Role, create_key

UPLOADS = 12
COLUMNS = 10**6
MEMORY_GROWTH = 600 * 2**20  # bytes of resident memory the server may gain under the attack
VICTIM_P95 = 0.5  # seconds
VICTIM_FLOOR = 3.0  # seconds the other organisation's reads are timed at least: refusals are quick
SAMPLE_EVERY = 0.02  # seconds between two readings of the server's memory
PAGE = os.sysconf("SC_PAGE_SIZE")


@dataclass(frozen=True)
class Attack:
    database: str
    body_bytes: int
    workers: int


ATTACKS = [
    Attack("sqlite", 8 * 2**20, 1),
    Attack("postgresql", 16 * 2**20, 2),
]


@dataclass
class Served:
    url: str
    pid: int
    rig: int  # a structure of the attacking organisation
    attacker: str  # its ingest key
    victim: str  # a viewer key of another organisation


def resident_bytes(pid: int) -> int:
    """The resident memory of ``pid`` and of every process descended from it, from /proc.

    The descendants are read from each thread's ``children`` list, not found by reading every
    process's ``stat``: the test samples fifty times a second, in the process that times the
    other organisation's reads, and a scan of a busy machine's processes at that rate took a
    good part of a CPU from them."""
    total, seen, unseen = 0, set(), [pid]
    while unseen:
        member = unseen.pop()
        if member in seen:
            continue
        seen.add(member)
        folder = Path("/proc") / str(member)
        try:
            total += int((folder / "statm").read_text().split()[1]) * PAGE
            for task in (folder / "task").iterdir():
                unseen += [int(child) for child in (task / "children").read_text().split()]
        except OSError:  # ended meanwhile
            continue
    return total


class PeakMemory:
    """``with PeakMemory(pid) as peak:`` reads the server's resident memory every
    ``SAMPLE_EVERY`` s while the block runs; ``peak.growth`` is its highest over the first."""

    def __init__(self, pid: int) -> None:
        self.pid = pid
        self.baseline = resident_bytes(pid)
        self.highest = self.baseline
        self._stop = threading.Event()
        self._thread = threading.Thread(target=self._sample)

    @property
    def growth(self) -> int:
        return self.highest - self.baseline

    def _sample(self) -> None:
        while not self._stop.wait(SAMPLE_EVERY):
            self.highest = max(self.highest, resident_bytes(self.pid))

    def __enter__(self) -> PeakMemory:
        self._thread.start()
        return self

    def __exit__(self, *_: object) -> None:
        self._stop.set()
        self._thread.join()
        self.highest = max(self.highest, resident_bytes(self.pid))


@pytest.fixture(params=ATTACKS, ids=lambda a: f"{a.database}-{a.body_bytes >> 20}MB-{a.workers}w")
def attack(request) -> Attack:
    return request.param


@pytest.fixture
def served(attack: Attack, tmp_path: Path, request) -> Iterator[Served]:
    """``narxwatch serve`` with the attack's workers, its upload limit raised to the attack's body."""
    if attack.database == "sqlite":
        database_url = f"sqlite:///{tmp_path / 'narxwatch.db'}"
    else:
        from harness import migrated

        name = f"narxwatch_memory_{uuid.uuid4().hex[:8]}"
        database_url = migrated.postgresql(request.getfixturevalue("postgres_url"), name)
    env = {
        **os.environ,
        "NARXWATCH_DATABASE_URL": database_url,
        "NARXWATCH_MAX_UPLOAD_BYTES": str(max(attack.body_bytes + 2**20, 16 * 2**20)),
        "NARXWATCH_LOG_FORMAT": "text",
    }
    port = free_port()
    url = f"http://127.0.0.1:{port}"
    log = tmp_path / "serve.log"
    with log.open("w") as output:
        server = subprocess.Popen(
            [NARXWATCH, "serve", "--port", str(port), "--workers", str(attack.workers)],
            env=env,
            stderr=output,
            stdout=output,
        )
    try:
        wait_until_serving(url, server, 120, log.read_text)
        engine = make_engine(database_url)
        with transaction(session_factory(engine)) as session:
            attacker_org, victim_org = (f"org-{uuid.uuid4().hex[:12]}" for _ in range(2))
            admin = create_key(session, attacker_org, Role.admin)
            attacker = create_key(session, attacker_org, Role.ingest)
            victim = create_key(session, victim_org, Role.viewer)
        engine.dispose()
        with http_client(base_url=url, headers={"Authorization": f"Bearer {admin}"}) as client:
            rig = create_structure(client)["id"]
        yield Served(url, server.pid, rig, attacker, victim)
    finally:
        server.send_signal(signal.SIGINT)
        server.wait(timeout=30)


def wide_header_csv(size: int) -> bytes:
    """A CSV of ``size`` bytes whose header names ``COLUMNS`` columns, then one row."""
    width = size // COLUMNS - 1  # characters of each name, a comma after it
    header = ",".join(f"c{column:0{width - 1}d}" for column in range(COLUMNS))
    return f"{header}\n1,2\n".encode()


async def upload(client: httpx.AsyncClient, path: str, body: bytes) -> tuple[int, float]:
    started = time.monotonic()
    response = await client.post(path, content=body, headers={"Content-Type": "text/csv"})
    return response.status_code, time.monotonic() - started


def test_wide_headers_at_once_are_refused_within_bounded_memory(served: Served, attack: Attack):
    body = wide_header_csv(attack.body_bytes)
    assert abs(len(body) - attack.body_bytes) < 2**20 and body.split(b"\n")[0].count(b",") == COLUMNS - 1
    path = f"{API}/structures/{served.rig}/records"
    headers = {"Authorization": f"Bearer {served.attacker}"}

    async def scenario() -> tuple[list[tuple[int, float]], list[tuple[float, int | None]]]:
        async with httpx.AsyncClient(base_url=served.url, headers=headers, timeout=120) as client:
            uploads = [asyncio.create_task(upload(client, path, body)) for _ in range(UPLOADS)]
            timings = await time_victim(served.url, served.victim, uploads, VICTIM_FLOOR)
            return list(await asyncio.gather(*uploads)), timings

    # Each worker process warmed up first (its first upload and read import and connect): the
    # attack's cost is measured, not theirs.
    with http_client(base_url=served.url, headers=headers) as client:
        for _ in range(4 * attack.workers):
            assert (
                client.post(path, content=b"x,y\n1,2\n", headers={"Content-Type": "text/csv"}).status_code
                == 422
            )
            client.get(f"{API}/structures", headers={"Authorization": f"Bearer {served.victim}"})
    with PeakMemory(served.pid) as memory:
        answers, timings = asyncio.run(scenario())
    statuses = [status for status, _ in answers]
    latencies = [seconds for _, seconds in answers]
    p95 = float(np.percentile([seconds for seconds, _ in timings], 95))
    print(
        f"\n{attack}: server memory +{memory.growth / 2**20:.0f} MB (from {memory.baseline / 2**20:.0f} MB), "
        f"uploads answered {sorted(set(statuses))} in {min(latencies):.2f}–{max(latencies):.2f} s, "
        f"other organisation's p95 {p95:.3f} s over {len(timings)} reads"
    )
    assert all(400 <= status < 500 for status in statuses), f"the uploads were answered {statuses}"
    assert memory.growth <= MEMORY_GROWTH, f"the server grew by {memory.growth / 2**20:.0f} MB"
    failed = [status for _, status in timings if status != 200]
    assert not failed, f"the other organisation got {failed} among {len(timings)} requests"
    assert len(timings) >= 10, f"only {len(timings)} requests of the other organisation were timed"
    assert p95 <= VICTIM_P95, f"the other organisation's p95 was {p95:.2f} s"


# --- parses beyond the bound wait, then are answered 503 --------------------------------------

UPLOAD_WAIT = 0.15  # NARXWATCH_UPLOAD_WAIT_SECONDS of the served app: well under one large parse


def test_a_parse_waiting_beyond_its_bound_is_a_503_with_retry_after(tmp_path: Path):
    """One parse at a time: while a 13 MB CSV is parsed (a second or so), a second upload waits
    ``UPLOAD_WAIT`` s for its turn and is answered 503 with Retry-After, and the first is
    answered as it would have been alone; once it has ended, an upload is parsed again."""
    settings = Settings(
        database_url=f"sqlite:///{tmp_path / 'narxwatch.db'}",
        max_concurrent_uploads=1,
        upload_wait_seconds=UPLOAD_WAIT,
    )
    x, y = noise(300_000)
    large = (csv_text(x, y) + "1.0,abc\n").encode()  # refused at its last line, after the whole parse
    with LiveServer(settings) as server, server.client(server.key(Role.admin)) as admin:
        path = f"{API}/structures/{create_structure(admin)['id']}/records"
        headers = {"Content-Type": "text/csv"}

        async def both() -> list[httpx.Response]:
            async with httpx.AsyncClient(base_url=server.url, headers=admin.headers, timeout=60) as client:
                first = asyncio.create_task(client.post(path, content=large, headers=headers))
                async with asyncio.timeout(30):  # until the first body's parse has begun
                    while not server.app.state.uploads.running():
                        await asyncio.sleep(0.01)
                second = client.post(path, content=b"x,y\n1,abc\n", headers=headers)
                return list(await asyncio.gather(first, second))

        started = time.monotonic()
        first, second = asyncio.run(both())
        assert second.status_code == 503, second.text
        assert int(second.headers["Retry-After"]) >= 1
        assert "NARXWATCH_MAX_CONCURRENT_UPLOADS" in second.json()["detail"]
        assert first.status_code == 422 and "'abc' in column 'y' is not a number" in first.text
        assert time.monotonic() - started > UPLOAD_WAIT
        again = admin.post(path, content=b"x,y\n1,abc\n", headers=headers)
        assert again.status_code == 422 and "'abc' in column 'y' is not a number" in again.text


@pytest.mark.parametrize(("name", "value"), [("max_concurrent_uploads", 0), ("upload_wait_seconds", 0)])
def test_the_parse_bound_is_a_validated_setting(monkeypatch, name: str, value: float):
    monkeypatch.setenv(f"NARXWATCH_{name.upper()}", str(value))
    with pytest.raises(ValueError, match=name):
        Settings()
