"""The fleet views, ``/metrics`` and uploads against the size of the fleet and its history.

    .venv/bin/python -m bench.fleet_scale [--backend sqlite|postgresql] [--sizes 100:10000,1000:100000]
        [--repeats 20] [--uploads 25] [--explain]

For each size N:M (structures : verdicts), in order:

1. Two fresh databases: SQLite files in a temporary folder, or two on a throwaway PostgreSQL server
   (``harness/postgres.py``: durability off, 32 MB of shared buffers; its binaries come from
   ``bash scripts/ensure-postgres.sh``). Each is migrated and given the demo (``service.demo``: a
   structure with a baseline, k2 and k1 models and a week of inspected records) and an ingest key
   of its organisation. One stays so: the empty database.
2. The other one's demo organisation is given a fleet, through the service's own tables:
   N structures, M records with empty signals (no view reads them), M verdicts, M / N a structure
   acquired 15 minutes apart up to now, each linked to the model versions of the demo's verdicts
   as an inspection links its own; a third of the structures had a fault for 20 records that
   cleared (a resolved persistence alarm), a tenth have one since a point in the second half of
   their history (an open alarm). Each structure's state row is computed from the plan of its
   history by the rules the service keeps it by (the newest verdict by acquisition then id; the
   acquisition of the first verdict of its last run; the counts): a bulk load bypasses the writes
   that keep it. On PostgreSQL each table is one ``COPY`` (the foreign keys' triggers off for the
   load, ``session_replication_role = replica``: the rows are consistent by construction), then
   the id sequences are moved past the rows and the tables vacuumed and analysed, as autovacuum
   would after a load; on SQLite, inserts of a few thousand rows a statement.
3. ``narxwatch serve`` (one process) on each. Times, on one keep-alive connection to the filled
   one, a warm-up then ``--repeats`` requests each, measured on the client from sending the
   request to having read the whole answer, and the serving process's CPU time over them (which a
   busy machine inflates least): ``GET /metrics``, ``GET /api/v1/structures`` (the first page of
   100), the same filtered by ``status=faulty``, ``GET /dashboard`` (the fleet's first page of 50,
   with the open alarms), one structure's verdict history (the API's first page of 50 and its
   dashboard page) and summary, and the organisation's alarms. Then, after three untimed ones to
   each (a server's first inspections load the models), ``--uploads`` simulated 2000-sample
   records to each demo structure with ``inspect=true``, one at a time, the two databases in turns
   (so that the machine's load drifts alike under both), and each server's CPU time over them.
4. ``--explain`` (PostgreSQL): the queries behind the fleet, history, alarm, summary and metrics
   reads, issued in this process by the service's own functions and captured, each run again under
   ``EXPLAIN (ANALYZE, BUFFERS)``; prints each one's execution time and every sequential scan of
   ``verdicts``, ``records``, ``structures`` or ``alarms`` (with its plan).

Prints a table per size (median and p95 in ms, server CPU ms a request, the answer's size, and
the uploads' p50 and server CPU on the empty and the filled database) with the machine's load
average. Exits non-zero when an answer is not 200, or when ``/metrics`` does not count the
records and verdicts stored. Nothing asserts on time.
"""

from __future__ import annotations

import argparse
import contextlib
import datetime as dt
import json
import os
import shutil
import statistics
import subprocess
import sys
import tempfile
import time
from collections.abc import Callable, Iterable, Iterator
from dataclasses import dataclass
from pathlib import Path
from typing import Any

from models.blas import one_blas_thread

one_blas_thread()  # before numpy is imported: one BLAS thread, as in narxwatch's processes
import httpx
import numpy as np
from prometheus_client.parser import text_string_to_metric_families
from sqlalchemy import JSON, Connection, Engine, event, func, insert, select, text

from bench.load_api import free_port, make_payloads, process_cpu
from service.config import Settings
from service.dashboard import views
from service.db import make_engine, session_factory, transaction
from service.demo import ORGANISATION, seed_demo
from service.domain import alarms, fleet, history
from service.jobs.backends import job_backend
from service.migrate import upgrade_database
from service.observability.metrics import DatabaseCollector
from service.schemas import PersistenceRule
from service.security import Principal, Role, create_key
from service.tables import (
    Alarm,
    Organisation,
    Record,
    Structure,
    StructureState,
    Verdict,
    VerdictModel,
    utcnow,
)

EVERY = dt.timedelta(minutes=15)
BATCH = 5000  # rows a statement, on SQLite
NARXWATCH = shutil.which("narxwatch", path=str(Path(sys.executable).parent))
COOKIE = "narxwatch_session"
EPISODE = 20  # records a cleared fault lasts
# The service's default re-notification period; open alarms were last announced at 16 points in it.
RENOTIFY = dt.timedelta(seconds=Settings.model_fields["renotify_after_seconds"].default)
WARM_UPS = 3  # untimed uploads to each database before the timed ones
BIG_TABLES = ("verdicts", "records", "structures", "alarms")


# --- the fleet's history ----------------------------------------------------------------------


@dataclass(frozen=True)
class Plan:
    """One structure's history: ``count`` verdicts, faulty within ``runs`` ([start, end) indices)."""

    structure_id: int
    count: int
    runs: tuple[tuple[int, int], ...]

    def status(self, index: int) -> str:
        return "faulty" if any(a <= index < b for a, b in self.runs) else "healthy"


def plans(first_id: int, structures: int, verdicts: int, seed: int) -> list[Plan]:
    rng = np.random.default_rng(seed)
    per, extra = divmod(verdicts, structures)
    made = []
    for s in range(structures):
        count = per + (s < extra)
        runs = []
        if rng.random() < 1 / 3 and count >= 4 * EPISODE:
            start = int(rng.integers(0, count // 2 - EPISODE))
            runs.append((start, start + EPISODE))
        if rng.random() < 1 / 10 and count >= 2:
            runs.append((int(rng.integers(count // 2, count)), count))
        made.append(Plan(first_id + s, count, tuple(runs)))
    return made


@dataclass(frozen=True)
class Ids:
    """The first id each filled table's rows take (after the demo's and the first uploads')."""

    structure: int
    record: int
    verdict: int
    alarm: int


RULE = PersistenceRule(kind="persistence").model_dump()


def _mode(name: str, k_hat: float, detects: bool) -> dict[str, Any]:
    return {
        "name": name, "k_hat": k_hat, "sigma_k": 0.5, "sigma_k_record": 0.5, "z": k_hat / 0.5,
        "detects": detects, "residual_variance": 1.2e-9, "q": 31.0, "q_critical": 55.8,
        "p_value": 0.6, "accepted": True, "at_range_limit": False,
    }  # fmt: skip


MODES = {
    "healthy": [_mode("k2", 0.1, False), _mode("k1", -0.2, False)],
    "faulty": [_mode("k2", 12.0, True), _mode("k1", 4.0, False)],
}
DETECTED_BY = {"healthy": [], "faulty": ["k2"]}


class Filler:
    """The rows of step 3, table by table, in order of id (each index grows at its end)."""

    def __init__(self, organisation_id: int, plans: list[Plan], ids: Ids, versions: list[int]) -> None:
        self.organisation_id, self.plans, self.ids, self.versions = organisation_id, plans, ids, versions
        self.model_set = ",".join(str(v) for v in versions)
        self.now = utcnow()
        longest = max(p.count for p in plans)
        self.t0 = self.now.replace(microsecond=0) - longest * EVERY

    def at(self, index: int) -> dt.datetime:
        return self.t0 + index * EVERY

    def _rows(self) -> Iterator[tuple[int, Plan, int]]:
        """(offset of the row from the first id, its structure's plan, its index in the history)."""
        offset = 0
        for plan in self.plans:
            for index in range(plan.count):
                yield offset, plan, index
                offset += 1

    def structures(self) -> Iterator[dict[str, Any]]:
        for p in self.plans:
            yield {
                "id": p.structure_id, "organisation_id": self.organisation_id,
                "name": f"unit {p.structure_id:05d}", "fs": 1500.0, "description": "",
                "created_at": self.now,
            }  # fmt: skip

    def records(self) -> Iterator[dict[str, Any]]:
        for offset, plan, index in self._rows():
            yield {
                "id": self.ids.record + offset, "structure_id": plan.structure_id, "fs": 1500.0,
                "n_samples": 2000, "acquired_at": self.at(index), "created_at": self.now,
                "sha256": f"{self.ids.record + offset:064x}", "x": b"", "y": b"",
                "signals_pruned_at": None, "channels": None,
            }  # fmt: skip

    def verdicts(self) -> Iterator[dict[str, Any]]:
        for offset, plan, index in self._rows():
            status = plan.status(index)
            faulty = status == "faulty"
            yield {
                "id": self.ids.verdict + offset, "record_id": self.ids.record + offset,
                "structure_id": plan.structure_id, "acquired_at": self.at(index), "created_at": self.now,
                "model_set": self.model_set, "status": status, "fault_detected": faulty,
                "fault_mode": "k2" if faulty else None, "reference_mode": "k2",
                "k_hat": 12.0 if faulty else 0.1, "sigma_k": 0.5,
                "interval_low": 11.0 if faulty else -0.9, "interval_high": 13.0 if faulty else 1.1,
                "alpha": 0.05, "lags": 40, "n_samples": 2000, "z_critical": 1.96,
                "q_critical_detection": 55.8, "detected_by": DETECTED_BY[status], "modes": MODES[status],
            }  # fmt: skip

    def links(self) -> Iterator[dict[str, Any]]:
        for offset, _, _ in self._rows():
            for version in self.versions:
                yield {"verdict_id": self.ids.verdict + offset, "model_version_id": version}

    def alarms(self) -> Iterator[dict[str, Any]]:
        """A persistence alarm per faulty run, opened on its third record (k = 3 of m = 5),
        resolved five records after the run ended (``clear_after``), or open. An open one was
        last announced again within the re-notification period, as the sweep keeps them: left
        unannounced, all would fall due at once, and the serving process's sweep of them (200
        at a time) would be timed with the uploads (1.5× their CPU at 10 000 structures)."""
        alarm_id = self.ids.alarm
        record = self.ids.record
        for plan in self.plans:
            for start, end in plan.runs:
                if end - start < 3:
                    continue
                ended = end < plan.count
                through = min(end + 4, plan.count - 1) if ended else plan.count - 1
                yield {
                    "id": alarm_id, "structure_id": plan.structure_id,
                    "organisation_id": self.organisation_id, "rule_kind": "persistence", "rule": RULE,
                    "fault_mode": None, "state": "resolved" if ended else "open",
                    "opened_at": self.at(start + 2), "record_id": record + start + 2,
                    "triggered_at": self.at(start + 2), "drift_started_at": None,
                    "evaluated_through": self.at(through), "acknowledged_at": None,
                    "acknowledged_by": None, "acknowledgement_note": None,
                    "resolved_at": self.at(through) if ended else None, "resolved_by": None,
                    "resolution": "cleared" if ended else None, "resolution_note": None,
                    "renotified_at": None if ended else self.now - (alarm_id % 16) * RENOTIFY / 16,
                }  # fmt: skip
                alarm_id += 1
            record += plan.count

    def states(self) -> Iterator[dict[str, Any]]:
        verdict = self.ids.verdict
        for p in self.plans:
            last = p.count - 1
            status = p.status(last)
            # The last run starts after the last verdict of the other status.
            if status == "faulty":
                since = next(a for a, b in p.runs if b == p.count)
            else:
                since = max((b for _, b in p.runs), default=0)
            faulty = sum(b - a for a, b in p.runs)
            yield {
                "structure_id": p.structure_id, "organisation_id": self.organisation_id,
                "status": status, "since": self.at(since), "latest_verdict_id": verdict + last,
                "latest_acquired_at": self.at(last), "records": p.count, "healthy": p.count - faulty,
                "faulty": faulty, "unknown_fault": 0,
            }  # fmt: skip
            verdict += p.count

    def tables(self) -> list[tuple[type, Callable[[], Iterator[dict[str, Any]]]]]:
        """Each table with its rows, parents first."""
        return [
            (Structure, self.structures),
            (Record, self.records),
            (Verdict, self.verdicts),
            (VerdictModel, self.links),
            (Alarm, self.alarms),
            (StructureState, self.states),
        ]


def fill(url: str, structures: int, verdicts: int, seed: int) -> int:
    """Step 2 on a database holding the demo; the id of the structure whose history is timed."""
    engine = make_engine(url)
    with engine.connect() as connection:
        organisation_id = connection.scalar(select(Organisation.id).where(Organisation.name == ORGANISATION))
        ids = Ids(*(_next_id(connection, table) for table in (Structure, Record, Verdict, Alarm)))
        newest = connection.scalar(select(func.max(Verdict.id)))
        versions = sorted(
            connection.scalars(select(VerdictModel.model_version_id).where(VerdictModel.verdict_id == newest))
        )
    filler = Filler(organisation_id, plans(ids.structure, structures, verdicts, seed), ids, versions)
    if engine.dialect.name == "postgresql":
        _copy_all(engine, filler)
    else:
        with engine.begin() as connection:
            for table, rows in filler.tables():
                for batch in _batches(rows(), BATCH):
                    connection.execute(insert(table), batch)
    engine.dispose()
    # Timed: the structure halfway down those with an open alarm (with none, down the fleet).
    watched = [p for p in filler.plans if p.runs and p.runs[-1][1] == p.count] or filler.plans
    return watched[len(watched) // 2].structure_id


def _next_id(connection: Connection, table: type) -> int:
    return (connection.scalar(select(func.max(table.id))) or 0) + 1  # type: ignore[attr-defined]


def _batches(rows: Iterable[dict[str, Any]], size: int) -> Iterator[list[dict[str, Any]]]:
    batch: list[dict[str, Any]] = []
    for row in rows:
        batch.append(row)
        if len(batch) == size:
            yield batch
            batch = []
    if batch:
        yield batch


def _copy_all(engine: Engine, filler: Filler) -> None:
    """Each table by ``COPY … FROM STDIN``, in one transaction, foreign-key triggers off."""
    with engine.begin() as connection:
        raw = connection.connection.driver_connection
        raw.execute("SET LOCAL session_replication_role = replica")
        for table, rows in filler.tables():
            sql_table = table.__table__  # type: ignore[attr-defined]
            columns = [c.name for c in sql_table.columns]
            documents = {c.name for c in sql_table.columns if isinstance(c.type, JSON)}
            texts: dict[int, str] = {}  # the JSON of each (shared, constant) document, by identity
            with (
                raw.cursor() as cursor,
                cursor.copy(f"COPY {sql_table.name} ({', '.join(columns)}) FROM STDIN") as copy,
            ):
                for row in rows():
                    for name in documents:
                        value = row[name]
                        if value is not None:  # SQL NULL, not JSON null
                            row[name] = texts.get(id(value)) or texts.setdefault(id(value), json.dumps(value))
                    copy.write_row([row[c] for c in columns])
        for table in (Structure, Record, Verdict, Alarm):
            name = table.__tablename__
            connection.execute(
                text(f"SELECT setval(pg_get_serial_sequence('{name}', 'id'), max(id)) FROM {name}")
            )
    with engine.connect() as connection:
        connection.execution_options(isolation_level="AUTOCOMMIT").execute(text("VACUUM ANALYZE"))


# --- the service, measured --------------------------------------------------------------------


@contextlib.contextmanager
def serving(url: str, log: Path) -> Iterator[tuple[str, int]]:
    """``narxwatch serve`` on ``url`` once it answers, stopped on leaving: its address and process
    id; its log goes to ``log``."""
    port = free_port()
    env = {**os.environ, "NARXWATCH_DATABASE_URL": url}
    with log.open("w") as written:
        process = subprocess.Popen([NARXWATCH, "serve", "--port", str(port)], env=env, stderr=written)
    base = f"http://127.0.0.1:{port}"
    try:
        deadline = time.monotonic() + 120
        while True:
            with contextlib.suppress(httpx.TransportError):
                if httpx.get(f"{base}/healthz").status_code == 200:
                    break
            if process.poll() is not None or time.monotonic() > deadline:
                raise SystemExit(f"narxwatch serve did not start; see {log}")
            time.sleep(0.2)
        yield base, process.pid
    finally:
        process.terminate()
        process.wait(timeout=30)


@contextlib.contextmanager
def client(base: str, key: str) -> Iterator[httpx.Client]:
    """A keep-alive client with the key as bearer and a dashboard login's cookie."""
    login = httpx.post(f"{base}/dashboard/login", data={"api_key": key, "next": "/dashboard"})
    if login.status_code != 303:
        raise SystemExit(f"the dashboard login answered {login.status_code}")
    headers = {"Authorization": f"Bearer {key}"}
    cookies = {COOKIE: login.cookies[COOKIE]}
    with httpx.Client(base_url=base, headers=headers, cookies=cookies, timeout=120) as opened:
        yield opened


def timed(client: httpx.Client, path: str, repeats: int, server: int) -> tuple[list[float], float, int]:
    """Milliseconds of ``repeats`` requests after a warm-up, the CPU milliseconds the ``server``
    process spent on each (the figure a busy machine inflates least), and the answer's size."""
    client.get(path)
    times = []
    cpu = process_cpu(server)
    for _ in range(repeats):
        began = time.perf_counter()
        response = client.get(path)
        times.append((time.perf_counter() - began) * 1000)
        if response.status_code != 200:
            raise SystemExit(f"GET {path} answered {response.status_code}: {response.text[:300]}")
    return times, (process_cpu(server) - cpu) * 1000 / repeats, len(response.content)


def upload(client: httpx.Client, structure_id: int, payload: bytes) -> float:
    """Milliseconds of one upload with ``inspect=true``."""
    began = time.perf_counter()
    response = client.post(
        f"/api/v1/structures/{structure_id}/records?inspect=true",
        content=payload,
        headers={"Content-Type": "application/json"},
    )
    if response.status_code != 201 or response.json().get("verdict") is None:
        raise SystemExit(f"an upload answered {response.status_code}: {response.text[:300]}")
    return (time.perf_counter() - began) * 1000


def counted(client: httpx.Client) -> tuple[float, float]:
    """The records and the verdicts (all statuses) ``/metrics`` counts."""
    samples = [
        sample
        for family in text_string_to_metric_families(client.get("/metrics").text)
        for sample in family.samples
    ]
    records = sum(s.value for s in samples if s.name == "narxwatch_records_received_total")
    return records, sum(s.value for s in samples if s.name == "narxwatch_verdicts_total")


def stored(url: str) -> tuple[int, int]:
    """The records and the verdicts the tables hold, counted."""
    engine = make_engine(url)
    with engine.connect() as connection:
        counts = (
            connection.scalar(select(func.count()).select_from(Record)) or 0,
            connection.scalar(select(func.count()).select_from(Verdict)) or 0,
        )
    engine.dispose()
    return counts


# --- EXPLAIN ----------------------------------------------------------------------------------


def explain(url: str, structure_id: int) -> None:
    """Step 4: every query of the reads below, under ``EXPLAIN (ANALYZE, BUFFERS)``."""
    engine = make_engine(url)
    sessions = session_factory(engine)
    with engine.connect() as connection:
        organisation_id = connection.scalar(select(Organisation.id).where(Organisation.name == ORGANISATION))
    principal = Principal(organisation_id, Role.viewer, key_id=0)
    queue_stats = job_backend(Settings(database_url=url), sessions, in_service=False).queue_stats
    reads: dict[str, Callable[[Any], object]] = {
        "metrics": lambda s: list(DatabaseCollector(s, queue_stats).collect()),
        "fleet page (API)": lambda s: fleet.fleet(s, principal),
        "fleet page, faulty": lambda s: fleet.fleet(s, principal, standing="faulty"),
        "fleet page (dashboard)": lambda s: views.fleet_page(s, principal, views.FleetFilter()),
        "history page": lambda s: history.history(
            s,
            principal,
            structure_id,
            start=None,
            end=None,
            status=None,
            fault_mode=None,
            cursor=None,
            limit=50,
        ),
        "summary": lambda s: history.summary(s, principal, structure_id),
        "structure page (dashboard)": lambda s: views.structure_page(
            s, principal, structure_id, views.HistoryFilter(), dt.datetime.now(dt.UTC)
        ),
        "alarms": lambda s: alarms.list_alarms(s, principal),
        "alarms of the structure": lambda s: alarms.list_alarms(s, principal, structure_id=structure_id),
    }
    print("\nEXPLAIN (ANALYZE, BUFFERS) of each query (ms: the plan's execution time)")
    flagged = 0
    for label, read in reads.items():
        statements: list[tuple[str, Any]] = []

        def capture(conn, cursor, statement, parameters, context, executemany, into=statements) -> None:
            into.append((statement, parameters))

        event.listen(engine, "before_cursor_execute", capture)
        try:
            with transaction(sessions) as session:
                read(session)
        finally:
            event.remove(engine, "before_cursor_execute", capture)
        for statement, parameters in statements:
            if not statement.lstrip().upper().startswith("SELECT"):
                continue
            with engine.connect() as connection:
                plan = [
                    row[0]
                    for row in connection.exec_driver_sql(
                        f"EXPLAIN (ANALYZE, BUFFERS) {statement}", parameters
                    )
                ]
            ms = next(line.split(":")[1].strip() for line in plan if line.startswith("Execution Time"))
            scans = [line for line in plan if any(f"Seq Scan on {t} " in line for t in BIG_TABLES)]
            print(f"  {label:<28} {ms:>12}  {' '.join(statement.split())[:110]}")
            if scans:
                flagged += 1
                print("    SEQUENTIAL SCAN:\n" + "\n".join(f"      {line}" for line in plan))
    print(f"  {flagged} queries scan one of {', '.join(BIG_TABLES)} sequentially")
    engine.dispose()


# --- the run ----------------------------------------------------------------------------------


@contextlib.contextmanager
def databases(backend: str, folder: Path) -> Iterator[tuple[str, str]]:
    """Two fresh, empty databases' URLs: the one to fill and the empty one."""
    if backend == "sqlite":
        yield f"sqlite:///{folder / 'fleet.db'}", f"sqlite:///{folder / 'empty.db'}"
        return
    from harness.postgres import create_database, missing_reason, postgres_server

    with postgres_server("fleet") as url:
        if url is None:
            raise SystemExit(f"PostgreSQL unavailable: {missing_reason()}")
        yield url, create_database(url, "empty")


def seeded(url: str) -> tuple[int, str]:
    """Step 1: the demo's structure id and an ingest key of its organisation."""
    upgrade_database(url)
    sessions = session_factory(make_engine(url))
    with transaction(sessions) as session:
        structure = seed_demo(session, Settings(database_url=url))
        key = create_key(session, ORGANISATION, Role.ingest)
    return structure.id, key


def measure(backend: str, structures: int, verdicts: int, args: argparse.Namespace) -> None:
    payloads = make_payloads(2 * (args.uploads + WARM_UPS), args.seed)
    with tempfile.TemporaryDirectory(prefix="fleet-scale-") as name, databases(backend, Path(name)) as urls:
        folder = Path(name)
        url, empty_url = urls
        (demo, key), (empty_demo, empty_key) = seeded(url), seeded(empty_url)
        began = time.perf_counter()
        watched = fill(url, structures, verdicts, args.seed)
        filled = time.perf_counter() - began
        with (
            serving(url, folder / "fleet.log") as (base, server),
            client(base, key) as opened,
            serving(empty_url, folder / "empty.log") as (empty_base, empty_server),
            client(empty_base, empty_key) as empty_client,
        ):
            if (found := counted(opened)) != stored(url):
                raise SystemExit(f"/metrics counts {found} records and verdicts, the tables {stored(url)}")
            paths = {
                "GET /metrics": "/metrics",
                "GET /api/v1/structures (first page)": "/api/v1/structures",
                "GET /api/v1/structures?status=faulty": "/api/v1/structures?status=faulty",
                "GET /dashboard (fleet, first page)": "/dashboard",
                "GET …/structures/S/verdicts (first page)": f"/api/v1/structures/{watched}/verdicts?limit=50",
                "GET /dashboard/structures/S": f"/dashboard/structures/{watched}",
                "GET …/structures/S/summary": f"/api/v1/structures/{watched}/summary",
                "GET /api/v1/alarms (first page)": "/api/v1/alarms",
            }
            rows = [(label, *timed(opened, path, args.repeats, server)) for label, path in paths.items()]
            # Untimed first: each server's first inspections load the models and fill its caches.
            for i in range(WARM_UPS):
                upload(empty_client, empty_demo, payloads[-1 - 2 * i])
                upload(opened, demo, payloads[-2 - 2 * i])
            # In turns, so that the machine's load drifts alike under both.
            empty: list[float] = []
            full: list[float] = []
            cpu = {server: process_cpu(server), empty_server: process_cpu(empty_server)}
            for i in range(args.uploads):
                turns = [
                    (empty, empty_client, empty_demo, payloads[2 * i]),
                    (full, opened, demo, payloads[2 * i + 1]),
                ]
                for times, each, structure_id, payload in turns if i % 2 else reversed(turns):
                    times.append(upload(each, structure_id, payload))
            upload_cpu = {pid: (process_cpu(pid) - spent) * 1000 / args.uploads for pid, spent in cpu.items()}
        if args.explain and backend == "postgresql":
            explain(url, watched)
    load = os.getloadavg()
    print(
        f"\n{backend}: {structures} structures, {verdicts} verdicts (filled in {filled:.1f} s), "
        f"S = structure {watched} ({verdicts // structures} verdicts); {args.repeats} requests each; "
        f"load average {load[0]:.1f} {load[1]:.1f} {load[2]:.1f}"
    )
    print(f"{'request':<42} {'median ms':>10} {'p95 ms':>8} {'server CPU ms':>14} {'bytes':>9}")
    for label, times, cpu, size in rows:
        p95 = float(np.percentile(times, 95))
        print(f"{label:<42} {statistics.median(times):>10.1f} {p95:>8.1f} {cpu:>14.1f} {size:>9}")
    ratio = statistics.median(full) / statistics.median(empty)
    print(
        f"{'upload, inspect=true: p50 empty, filled':<42} {statistics.median(empty):>10.1f} "
        f"{statistics.median(full):>8.1f} ms ({ratio:.2f}×, {args.uploads} uploads each, in turns)"
    )
    print(
        f"{'upload, inspect=true: server CPU empty, filled':<42} {upload_cpu[empty_server]:>10.1f} "
        f"{upload_cpu[server]:>8.1f} ms ({upload_cpu[server] / upload_cpu[empty_server]:.2f}×)"
    )


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--backend", choices=["sqlite", "postgresql"], default="sqlite")
    parser.add_argument(
        "--sizes", default="100:10000,1000:100000", help="structures:verdicts, comma-separated"
    )
    parser.add_argument("--repeats", type=int, default=20)
    parser.add_argument("--uploads", type=int, default=25, help="timed uploads on each database")
    parser.add_argument("--explain", action="store_true", help="EXPLAIN the reads (PostgreSQL)")
    parser.add_argument("--seed", type=int, default=2026)
    args = parser.parse_args()
    for size in args.sizes.split(","):
        structures, verdicts = (int(part) for part in size.split(":"))
        measure(args.backend, structures, verdicts, args)


if __name__ == "__main__":
    main()
