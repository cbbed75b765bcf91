"""The fleet views and ``/metrics`` against the size of the fleet and its history, on SQLite.

    .venv/bin/python -m bench.fleet_scale [--sizes 100:10000,1000:100000] [--repeats 20]

For each size N:M (structures : verdicts), in order:

1. A fresh SQLite file in a temporary folder is migrated and filled through the service's own
   tables with bulk inserts (``executemany``, a few thousand rows a statement): one organisation,
   N structures, M records with empty signals (the views never read them) and M verdicts, M / N a
   structure, acquired 15 minutes apart; each structure healthy until a point drawn at random,
   then faulty (a third of them stay healthy). Each structure's state row is computed from the
   rows inserted, by the rules the service keeps it by (the newest verdict by acquisition then
   id; the acquisition of the first verdict of its last run; the counts): a bulk insert bypasses
   the writes that keep it.
2. ``narxwatch serve`` (one process) on that file; a viewer key and a dashboard login.
3. Times, on one keep-alive connection, a warm-up then ``--repeats`` requests each, measured on
   the client from sending the request to having read the whole answer: ``GET /metrics``,
   ``GET /api/v1/structures`` (the first page of 100), the same filtered by ``status=faulty``,
   ``GET /dashboard`` (the fleet's first page of 50) and a structure's summary.

Prints a table per size (median and p95 in ms, the answer's size). Exits non-zero when an answer
is not 200, or when ``/metrics`` does not count M records and M verdicts. Nothing asserts on time.
The issue's sizes (10 000 structures, 1 000 000 verdicts on SQLite) take minutes to fill: pass
them with ``--sizes`` on a machine with the time.
"""

from __future__ import annotations

import argparse
import datetime as dt
import os
import shutil
import socket
import statistics
import subprocess
import sys
import tempfile
import time
from collections.abc import Iterator
from pathlib import Path
from typing import Any

import service  # noqa: F401  (first: the single BLAS thread narxwatch's processes run with)

# isort: split
import httpx
import numpy as np
from prometheus_client.parser import text_string_to_metric_families
from sqlalchemy import Connection, insert, select

from service.db import make_engine, session_factory, transaction
from service.migrate import upgrade_database
from service.security import Role, create_key
from service.tables import Organisation, Record, Structure, StructureState, Verdict, utcnow

T0 = dt.datetime(2025, 1, 1, tzinfo=dt.UTC)
EVERY = dt.timedelta(minutes=15)
BATCH = 5000
NARXWATCH = shutil.which("narxwatch", path=str(Path(sys.executable).parent))
COOKIE = "narxwatch_session"
ORGANISATION = "fleet"


def fill(url: str, structures: int, verdicts: int, seed: int) -> str:
    """The fleet of step 1; a viewer key of its organisation."""
    upgrade_database(url)
    engine = make_engine(url)
    with transaction(session_factory(engine)) as session:
        key = create_key(session, ORGANISATION, Role.viewer)
        organisation_id = session.scalar(select(Organisation.id).where(Organisation.name == ORGANISATION))
    now = utcnow()
    states = {
        s: {
            "structure_id": s,
            "organisation_id": organisation_id,
            "status": None,
            "since": None,
            "latest_verdict_id": None,
            "latest_acquired_at": None,
            "records": 0,
            "healthy": 0,
            "faulty": 0,
            "unknown_fault": 0,
        }
        for s in range(1, structures + 1)
    }
    with engine.begin() as connection:
        connection.execute(
            insert(Structure),
            [
                {"id": s, "organisation_id": organisation_id, "name": f"unit {s:05d}", "fs": 1500.0}
                | {"description": "", "created_at": now}
                for s in states
            ],
        )
        records: list[dict[str, Any]] = []
        judged: list[dict[str, Any]] = []
        for row_id, (s, index, status) in enumerate(_history(structures, verdicts, seed), start=1):
            at = T0 + index * EVERY
            records.append(_record(row_id, s, at, now))
            judged.append(_verdict(row_id, s, at, now, status))
            state = states[s]  # each structure's rows come oldest first: each is the newest yet
            if status != state["status"]:
                state |= {"status": status, "since": at}
            state |= {"latest_verdict_id": row_id, "latest_acquired_at": at}
            state["records"] += 1
            state[status] += 1
            if len(records) == BATCH:
                _flush(connection, records, judged)
        _flush(connection, records, judged)
        connection.execute(insert(StructureState), list(states.values()))
    engine.dispose()
    return key


def _history(structures: int, verdicts: int, seed: int) -> Iterator[tuple[int, int, str]]:
    """(structure, index in its history, status) of every verdict, structure by structure."""
    rng = np.random.default_rng(seed)
    per, extra = divmod(verdicts, structures)
    for s in range(1, structures + 1):
        count = per + (s <= extra)
        onset = count if s % 3 == 0 else int(rng.integers(0, count + 1))
        for index in range(count):
            yield s, index, "healthy" if index < onset else "faulty"


def _record(row_id: int, structure_id: int, at: dt.datetime, now: dt.datetime) -> dict[str, Any]:
    return {
        "id": row_id,
        "structure_id": structure_id,
        "fs": 1500.0,
        "n_samples": 2000,
        "acquired_at": at,
        "created_at": now,
        "sha256": f"{row_id:064x}",
        "x": b"",
        "y": b"",
    }


def _verdict(
    row_id: int, structure_id: int, at: dt.datetime, now: dt.datetime, status: str
) -> dict[str, Any]:
    faulty = status == "faulty"
    return {
        "id": row_id,
        "record_id": row_id,
        "structure_id": structure_id,
        "acquired_at": at,
        "created_at": now,
        "model_set": "1",
        "status": status,
        "fault_detected": faulty,
        "fault_mode": "k2" if faulty else None,
        "reference_mode": "k2",
        "k_hat": 12.0 if faulty else 0.1,
        "sigma_k": 0.5,
        "interval_low": 11.0 if faulty else -0.9,
        "interval_high": 13.0 if faulty else 1.1,
        "alpha": 0.05,
        "lags": 40,
        "n_samples": 2000,
        "z_critical": 1.96,
        "q_critical_detection": 55.8,
        "detected_by": ["k2"] if faulty else [],
        "modes": [],
    }


def _flush(connection: Connection, records: list[dict[str, Any]], judged: list[dict[str, Any]]) -> None:
    if records:
        connection.execute(insert(Record), records)
        connection.execute(insert(Verdict), judged)
    records.clear()
    judged.clear()


def serve(url: str, folder: Path) -> tuple[subprocess.Popen, str]:
    """``narxwatch serve`` on ``url``, once it answers; its log goes to ``folder``."""
    with socket.socket() as probe:
        probe.bind(("127.0.0.1", 0))
        port = probe.getsockname()[1]
    env = {**os.environ, "NARXWATCH_DATABASE_URL": url}
    with (folder / "serve.log").open("w") as log:
        process = subprocess.Popen([NARXWATCH, "serve", "--port", str(port)], env=env, stderr=log)
    base = f"http://127.0.0.1:{port}"
    deadline = time.monotonic() + 120
    while True:
        try:
            if httpx.get(f"{base}/healthz").status_code == 200:
                return process, base
        except httpx.TransportError:
            pass
        if process.poll() is not None or time.monotonic() > deadline:
            raise SystemExit(f"narxwatch serve did not start; see {folder / 'serve.log'}")
        time.sleep(0.2)


def timed(client: httpx.Client, path: str, repeats: int) -> tuple[list[float], int]:
    """Milliseconds of ``repeats`` requests after a warm-up, and the answer's size in bytes."""
    client.get(path)
    times = []
    for _ in range(repeats):
        began = time.perf_counter()
        response = client.get(path)
        times.append((time.perf_counter() - began) * 1000)
        if response.status_code != 200:
            raise SystemExit(f"GET {path} answered {response.status_code}: {response.text[:300]}")
    return times, len(response.content)


def counted(client: httpx.Client) -> tuple[float, float]:
    """The records and the verdicts (all statuses) ``/metrics`` counts."""
    samples = [
        sample
        for family in text_string_to_metric_families(client.get("/metrics").text)
        for sample in family.samples
    ]
    records = sum(s.value for s in samples if s.name == "narxwatch_records_received_total")
    return records, sum(s.value for s in samples if s.name == "narxwatch_verdicts_total")


def measure(structures: int, verdicts: int, repeats: int, seed: int) -> None:
    with tempfile.TemporaryDirectory(prefix="fleet-scale-") as name:
        folder = Path(name)
        url = f"sqlite:///{folder / 'fleet.db'}"
        began = time.perf_counter()
        key = fill(url, structures, verdicts, seed)
        filled = time.perf_counter() - began
        process, base = serve(url, folder)
        try:
            login = httpx.post(f"{base}/dashboard/login", data={"api_key": key, "next": "/dashboard"})
            if login.status_code != 303:
                raise SystemExit(f"the dashboard login answered {login.status_code}")
            headers = {"Authorization": f"Bearer {key}"}
            cookies = {COOKIE: login.cookies[COOKIE]}
            with httpx.Client(base_url=base, headers=headers, cookies=cookies, timeout=120) as client:
                if (found := counted(client)) != (verdicts, verdicts):
                    raise SystemExit(f"/metrics counts {found}, not {verdicts} records and verdicts")
                paths = {
                    "GET /metrics": "/metrics",
                    "GET /api/v1/structures (first page)": "/api/v1/structures",
                    "GET /api/v1/structures?status=faulty": "/api/v1/structures?status=faulty",
                    "GET /dashboard (first page)": "/dashboard",
                    "GET /api/v1/structures/1/summary": "/api/v1/structures/1/summary",
                }
                rows = [(label, *timed(client, path, repeats)) for label, path in paths.items()]
        finally:
            process.terminate()
            process.wait(timeout=30)
    print(
        f"\n{structures} structures, {verdicts} verdicts (filled in {filled:.1f} s), {repeats} requests each"
    )
    print(f"{'request':<42} {'median ms':>10} {'p95 ms':>8} {'bytes':>9}")
    for label, times, size in rows:
        p95 = float(np.percentile(times, 95))
        print(f"{label:<42} {statistics.median(times):>10.1f} {p95:>8.1f} {size:>9}")


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument(
        "--sizes", default="100:10000,1000:100000", help="structures:verdicts, comma-separated"
    )
    parser.add_argument("--repeats", type=int, default=20)
    parser.add_argument("--seed", type=int, default=2026)
    args = parser.parse_args()
    for size in args.sizes.split(","):
        structures, verdicts = (int(part) for part in size.split(":"))
        measure(structures, verdicts, args.repeats, args.seed)


if __name__ == "__main__":
    main()
