"""Load benchmark of queued inspections on real PostgreSQL with Procrastinate workers.

    .venv/bin/python bench/load_queue.py [--records 2000] [--clients 4] [--workers 2] [--database-url URL]

1. A throwaway PostgreSQL server (harness/postgres.py; its binaries come from Debian's postgresql
   package, ``bash scripts/ensure-postgres.sh``) unless ``--database-url`` names one.
2. ``narxwatch demo-seed`` (the trained demo structure) and an ingest key.
3. ``narxwatch serve --workers 2`` (it only defers jobs) and ``--workers`` ``narxwatch worker``
   processes, each its own process.
4. ``--records`` distinct simulated 2000-sample records, generated before any timing, uploaded
   with ``inspect=queue`` by ``--clients`` concurrent clients (one keep-alive connection each).
5. Waits until every record has its verdict, then checks from the database itself: exactly
   ``--records`` new records, exactly that many verdicts, one per record, no 5xx.

Prints upload throughput and latency (p50, p95, p99, max), and end-to-end throughput (upload of
the first record to verdict of the last) with the queue latency (defer to success, from
Procrastinate's event log). Exits non-zero when any check fails.
"""

from __future__ import annotations

import argparse
import os
import signal
import subprocess
import sys
import tempfile
import threading
import time
from collections import Counter
from contextlib import ExitStack, suppress
from dataclasses import dataclass
from pathlib import Path

ROOT = Path(__file__).resolve().parents[1]
sys.path.insert(0, str(ROOT))  # this checkout's bench and harness, run as a script

# isort: split
import httpx
import numpy as np
import psycopg

from bench.load_api import console_script, free_port, make_payloads, run_cli
from service.jobs.distributed import conninfo


def spawn(args: list[str], env: dict[str, str], log: Path) -> subprocess.Popen[bytes]:
    with log.open("wb") as out:
        return subprocess.Popen(
            [console_script("narxwatch"), *args], env=env, cwd=ROOT, stdout=out, stderr=subprocess.STDOUT,
            start_new_session=True,
        )  # fmt: skip


def stop(process: subprocess.Popen[bytes]) -> None:
    if process.poll() is None:
        with suppress(ProcessLookupError):
            os.killpg(process.pid, signal.SIGTERM)
        try:
            process.wait(20)
        except subprocess.TimeoutExpired:
            os.killpg(process.pid, signal.SIGKILL)


def wait_ready(url: str, timeout: float = 120) -> None:
    deadline = time.monotonic() + timeout
    while time.monotonic() < deadline:
        with suppress(httpx.TransportError):
            if httpx.get(f"{url}/readyz", timeout=2).status_code == 200:
                return
        time.sleep(0.2)
    raise SystemExit(f"the API at {url} did not become ready")


def upload_all(url: str, key: str, structure_id: int, payloads: list[bytes], clients: int):
    """Every payload once, by ``clients`` threads; (status counts, latencies in s, ids, seconds)."""
    statuses: Counter[int] = Counter()
    latencies: list[float] = []
    ids: list[int] = []
    lock = threading.Lock()
    shares = [payloads[i::clients] for i in range(clients)]
    start = threading.Barrier(clients + 1)

    def client(share: list[bytes]) -> None:
        headers = {"Authorization": f"Bearer {key}", "Content-Type": "application/json"}
        with httpx.Client(base_url=url, headers=headers, timeout=60) as http:
            start.wait()
            for body in share:
                began = time.perf_counter()
                response = http.post(f"/api/v1/structures/{structure_id}/records?inspect=queue", content=body)
                took = time.perf_counter() - began
                with lock:
                    statuses[response.status_code] += 1
                    latencies.append(took)
                    if response.status_code == 202:
                        ids.append(response.json()["id"])

    threads = [threading.Thread(target=client, args=(share,)) for share in shares]
    for thread in threads:
        thread.start()
    start.wait()
    began = time.perf_counter()
    for thread in threads:
        thread.join()
    return statuses, np.array(latencies), ids, time.perf_counter() - began


@dataclass(frozen=True)
class Stored:
    """What the database holds once every uploaded record has its verdict (or the wait ended):
    when the last verdict was seen (``time.perf_counter``), the records added, the uploads'
    verdicts and the records they judge, and each inspection's time in the queue (defer to
    success) in seconds."""

    done: float
    records: int
    verdicts: int
    distinct_records: int
    queue_seconds: np.ndarray


def main(argv: list[str] | None = None) -> int:
    parser = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    parser.add_argument("--records", type=int, default=2000)
    parser.add_argument("--clients", type=int, default=4)
    parser.add_argument("--workers", type=int, default=2, help="narxwatch worker processes")
    parser.add_argument(
        "--database-url", help="an existing, empty PostgreSQL database (default: a throwaway server)"
    )
    args = parser.parse_args(argv)
    with ExitStack() as stack:
        url = args.database_url
        if url is None:
            from harness import postgres

            url = stack.enter_context(postgres.postgres_server("load"))
            if url is None:
                raise SystemExit(f"PostgreSQL unavailable: {postgres.missing_reason()}")
        folder = Path(stack.enter_context(tempfile.TemporaryDirectory(prefix="narxwatch-load-")))
        env = {**os.environ, "NARXWATCH_DATABASE_URL": url, "NARXWATCH_LOG_FORMAT": "text"}
        print("seeding the demo structure …", flush=True)
        run_cli(["demo-seed"], env)
        key = run_cli(["keys", "create", "--org", "demo", "--role", "ingest"], env).strip()
        print(f"simulating {args.records} records …", flush=True)
        payloads = make_payloads(args.records, seed=20261121)
        port = free_port()
        api = spawn(["serve", "--port", str(port), "--workers", "2"], env, folder / "api.log")
        stack.callback(stop, api)
        for i in range(args.workers):
            stack.callback(stop, spawn(["worker"], env, folder / f"worker-{i}.log"))
        api_url = f"http://127.0.0.1:{port}"
        wait_ready(api_url)
        structure_id = httpx.get(
            f"{api_url}/api/v1/structures", headers={"Authorization": f"Bearer {key}"}
        ).json()[0]["id"]
        with psycopg.connect(conninfo(url)) as db:
            records_before = db.execute("SELECT count(*) FROM records").fetchone()[0]
        print(f"uploading with {args.clients} clients, {args.workers} workers …", flush=True)
        began = time.perf_counter()
        statuses, latencies, ids, upload_seconds = upload_all(
            api_url, key, structure_id, payloads, args.clients
        )
        stored = stored_verdicts(url, ids, records_before)
    return report(args.records, statuses, latencies, ids, upload_seconds, stored.done - began, stored)


def stored_verdicts(url: str, ids: list[int], records_before: int) -> Stored:
    """What the database holds once every record of ``ids`` has its verdict, waiting up to ten
    minutes for them."""
    with psycopg.connect(conninfo(url), autocommit=True) as db:
        deadline = time.monotonic() + 600
        query = "SELECT count(*) FROM verdicts WHERE record_id = ANY(%s)"
        while db.execute(query, (ids,)).fetchone()[0] < len(ids) and time.monotonic() < deadline:
            time.sleep(0.2)
        done = time.perf_counter()
        records = db.execute("SELECT count(*) FROM records").fetchone()[0] - records_before
        verdicts = db.execute(query, (ids,)).fetchone()[0]
        distinct = db.execute(
            "SELECT count(DISTINCT record_id) FROM verdicts WHERE record_id = ANY(%s)", (ids,)
        )
        distinct_records = distinct.fetchone()[0]
        queue = db.execute(
            "SELECT extract(epoch FROM s.at - d.at) FROM procrastinate_events s "
            "JOIN procrastinate_events d ON d.job_id = s.job_id AND d.type = 'deferred' "
            "JOIN procrastinate_jobs j ON j.id = s.job_id "
            "WHERE s.type = 'succeeded' AND j.task_name = 'inspect_record'"
        ).fetchall()
    return Stored(done, records, verdicts, distinct_records, np.array([float(row[0]) for row in queue]))


def report(
    expected: int,
    statuses: Counter[int],
    latencies: np.ndarray,
    ids: list[int],
    upload_seconds: float,
    end_to_end: float,
    stored: Stored,
) -> int:
    """The figures printed, then the checks: every one of the ``expected`` uploads answered 202
    and stored with one verdict. The exit status: 1 if a check failed."""
    ms = 1000 * np.percentile(latencies, [50, 95, 99, 100])
    print()
    print(f"{'':28}{'value':>12}")
    print(f"{'uploads (202)':28}{statuses[202]:>12}   answers: {dict(statuses)}")
    print(f"{'upload throughput':28}{len(latencies) / upload_seconds:>10.0f}/s")
    print(f"{'upload p50 / p95 / p99 / max':28}{ms[0]:>9.1f} ms / {ms[1]:.1f} / {ms[2]:.1f} / {ms[3]:.1f} ms")
    print(
        f"{'end to end (to last verdict)':28}{end_to_end:>10.1f} s  = {len(ids) / end_to_end:.0f} verdicts/s"
    )
    if stored.queue_seconds.size:
        q = np.percentile(stored.queue_seconds, [50, 95])
        print(f"{'queue latency p50 / p95':28}{q[0]:>10.2f} s / {q[1]:.2f} s")
    print(
        f"{'records / verdicts stored':28}{stored.records:>12} / {stored.verdicts} "
        f"({stored.distinct_records} records)"
    )
    failures = []
    if statuses[202] != expected or set(statuses) != {202}:
        failures.append(f"answers other than 202: {dict(statuses)}")
    if not stored.records == stored.verdicts == stored.distinct_records == expected:
        failures.append(f"expected {expected} records and verdicts, one each")
    for failure in failures:
        print(f"FAILED: {failure}")
    print("all checks passed" if not failures else "")
    return 1 if failures else 0


if __name__ == "__main__":
    sys.exit(main())
