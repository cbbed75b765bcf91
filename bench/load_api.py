"""Load benchmark of the REST API on SQLite: record uploads with ``inspect=true`` against a no-op.

    .venv/bin/python bench/load_api.py [--requests N] [--concurrency C] [--workers W] [--duration S]

What it does, in order:

1. In a fresh temporary folder, ``narxwatch demo-seed`` (a trained demo structure with k2 and k1
   fault-mode models) and ``narxwatch keys create --org demo --role ingest`` with
   ``NARXWATCH_DATABASE_URL`` pointing to a new SQLite file there.
2. Pre-generates distinct 2000-sample records with the simulator (a new seed for each upload, the
   paper's four cases in turn: healthy, k2 3 %, k2 29 %, k1 30 %), JSON-encoded before any timing.
3. Starts a real server as a separate process: ``uvicorn bench.noop_app:create_app_with_noop
   --factory --workers W`` on a free loopback port. That is the production app plus
   ``POST /bench/noop``, which authenticates, reads and parses the same payload and does nothing
   else (``bench/noop_app.py``). Log level and access log are those of ``narxwatch serve``
   unless ``--no-access-log``; the log goes to a file in the temporary folder.
4. Four phases, each after a warm-up on the same connections: (a) the real upload
   ``POST /api/v1/structures/{id}/records?inspect=true`` at concurrency 1 (latency), (b) the same
   at concurrency C (sustained throughput), (c) and (d) the no-op at concurrency 1 and C. Every
   connection is an ``httpx.Client`` with keep-alive in its own thread (``--reconnect-every N``:
   a new connection after every N requests); latency is measured on the client, from sending the
   request to having read the whole answer.
5. Checks that every real upload created a record and a verdict: the verdicts' ``total`` of the
   structure's summary and the record ids paged from its verdict history must match the
   successful uploads, and (after the server stopped) the ``records`` table must have grown by
   exactly that many rows.

It prints a table (p50, p95, p99, max, throughput, errors, client and server CPU, each worker's
share), a CPU probe of the machine's speed before and after the load, the real/no-op
ratios and one "target met / missed" line per speed target. The exit status is non-zero when any
request failed (a non-2xx answer, a transport error, or an upload that was not created and
inspected) or the database check does not match; missing a speed target only prints "missed".
The load generator runs on the same machine and takes CPU from the server: its share is printed.

The server process and the temporary folder are removed on exit, Ctrl-C included.
"""

from __future__ import annotations

import argparse
import concurrent.futures
import json
import os
import re
import shutil
import signal
import socket
import sqlite3
import subprocess
import sys
import tempfile
import threading
import time
from collections import Counter
from collections.abc import Iterator
from contextlib import contextmanager, suppress
from dataclasses import dataclass, field
from pathlib import Path

ROOT = Path(__file__).resolve().parents[1]
if str(ROOT) not in sys.path:
    sys.path.insert(0, str(ROOT))

from models.blas import one_blas_thread

one_blas_thread()  # before numpy is imported: one BLAS thread, as in narxwatch's processes
import httpx
import numpy as np

from simulator.simulate import simulate
from simulator.study import CASES, StudySettings

TARGET_P50_MS = 15.0
TARGET_THROUGHPUT = 150.0
SAMPLES = 2000
NOOP_PATH = "/bench/noop"  # bench/noop_app.py (not imported here: the client needs no FastAPI)
SERVER_APP = "bench.noop_app:create_app_with_noop"
CLOCK_TICKS = os.sysconf("SC_CLK_TCK")
REQUEST_TIMEOUT = 60.0  # seconds
CLOSE = {"Connection": "close"}
ACCESS_LINE = re.compile(r'^INFO: +[0-9.]+:[0-9]+ - "')


# ----------------------------------------------------------------------------------------------
# Payloads


def _encoded_record(index_and_seed: tuple[int, np.random.SeedSequence]) -> bytes:
    index, seed = index_and_seed
    case = CASES[index % len(CASES)]
    record = simulate(StudySettings().scenario(case.fault, case.true_k), SAMPLES, seed)
    return json.dumps({"x": record.x.tolist(), "y": record.y.tolist(), "fs": record.fs}).encode()


def make_payloads(count: int, seed: int) -> list[bytes]:
    """``count`` distinct JSON records (a new seed each; the four cases in turn), in parallel."""
    seeds = np.random.SeedSequence(seed).spawn(count)
    workers = max(1, min(os.cpu_count() or 1, 4))
    with concurrent.futures.ProcessPoolExecutor(workers) as pool:
        return list(pool.map(_encoded_record, enumerate(seeds), chunksize=32))


# ----------------------------------------------------------------------------------------------
# The server process


def free_port() -> int:
    with socket.socket() as probe:
        probe.bind(("127.0.0.1", 0))
        return probe.getsockname()[1]


def console_script(name: str) -> str:
    """A console script installed next to this interpreter (the project's venv)."""
    path = Path(sys.executable).with_name(name)
    if not path.exists():
        raise SystemExit(f"{path} is missing: install the project into this environment first")
    return str(path)


def run_cli(args: list[str], env: dict[str, str]) -> str:
    done = subprocess.run(
        [console_script("narxwatch"), *args], env=env, cwd=ROOT, capture_output=True, text=True, timeout=600
    )
    if done.returncode != 0:
        raise SystemExit(
            f"narxwatch {' '.join(args)} failed ({done.returncode}):\n{done.stdout}{done.stderr}"
        )
    return done.stdout


class Server:
    """``uvicorn bench.noop_app:create_app_with_noop --factory`` in its own process group."""

    def __init__(self, env: dict[str, str], workers: int, log: Path, access_log: bool) -> None:
        self.port = free_port()
        self.workers = workers
        self.log_path = log
        command = [
            sys.executable, "-m", "uvicorn", SERVER_APP, "--factory",
            "--host", "127.0.0.1", "--port", str(self.port),
            "--workers", str(workers), "--log-level", "info",
            "--http", "service.api.protocol:HeaderTimeoutProtocol",  # as `narxwatch serve`
        ]  # fmt: skip
        if not access_log:
            command.append("--no-access-log")
        self._log = log.open("wb")
        self.process = subprocess.Popen(
            command, env=env, cwd=ROOT, stdin=subprocess.DEVNULL, stdout=self._log, stderr=subprocess.STDOUT,
            start_new_session=True,  # Ctrl-C reaches this script, which then stops the server itself
        )  # fmt: skip

    @property
    def url(self) -> str:
        return f"http://127.0.0.1:{self.port}"

    def wait_ready(self, timeout: float = 120.0) -> None:
        """Until /readyz answers and every worker has logged its startup."""
        deadline = time.monotonic() + timeout
        with httpx.Client(base_url=self.url, timeout=5) as client:
            while True:
                if self.process.poll() is not None:
                    raise SystemExit(f"the server exited with {self.process.returncode}:\n{self.log_tail()}")
                started = self.log_path.read_bytes().count(b"Application startup complete")
                with suppress(httpx.TransportError):
                    if client.get("/readyz").status_code == 200 and started >= self.workers:
                        return
                if time.monotonic() > deadline:
                    raise SystemExit(
                        f"the server did not become ready in {timeout:.0f} s:\n{self.log_tail()}"
                    )
                time.sleep(0.1)

    def cpu_seconds(self) -> dict[int, float]:
        """User + system CPU time of the server and each of its live descendants (its workers), by pid."""
        return {pid: process_cpu(pid) for pid in _descendants(self.process.pid)}

    def log_tail(self, lines: int = 30, access: bool = True) -> str:
        """The log's last lines; without uvicorn's access-log lines unless ``access``."""
        try:
            text = self.log_path.read_text(errors="replace").splitlines()
        except OSError:
            return "(no log)"
        kept = [line for line in text if access or not ACCESS_LINE.match(line)]
        return "\n".join(kept[-lines:]) or "(nothing but access-log lines)"

    def stop(self) -> None:
        """SIGTERM to the server's process group (graceful), SIGKILL if it lingers."""
        if self.process.poll() is None:
            with suppress(ProcessLookupError):
                os.killpg(self.process.pid, signal.SIGTERM)
            try:
                self.process.wait(timeout=20)
            except subprocess.TimeoutExpired:
                with suppress(ProcessLookupError):
                    os.killpg(self.process.pid, signal.SIGKILL)
                self.process.wait(timeout=10)
        self._log.close()


def cpu_probe_ms() -> float:
    """A fixed pure-Python loop (best of 3, ms): the machine's speed of the moment.

    On a shared virtual machine one core's speed can drift by a third within minutes, which
    moves every figure here with it; the probe before and after a run shows how far.
    """

    def once() -> float:
        started, total = time.perf_counter(), 0
        for i in range(1_000_000):
            total += i * i
        return (time.perf_counter() - started) * 1000

    return min(once() for _ in range(3))


def machine_busy() -> float:
    """CPU seconds all cores have spent on anything but idle and I/O wait since boot."""
    fields = [int(value) for value in Path("/proc/stat").read_text().split("\n", 1)[0].split()[1:]]
    return (sum(fields[:8]) - fields[3] - fields[4]) / CLOCK_TICKS  # user … steal, less idle, iowait


def process_cpu(pid: int) -> float:
    try:
        stat = Path(f"/proc/{pid}/stat").read_text()
    except OSError:
        return 0.0
    fields = stat.rsplit(")", 1)[1].split()
    return (int(fields[11]) + int(fields[12])) / CLOCK_TICKS  # utime, stime (fields 14, 15)


def _descendants(root: int) -> list[int]:
    parents: dict[int, list[int]] = {}
    for entry in Path("/proc").iterdir():
        if not entry.name.isdigit():
            continue
        try:
            ppid = int((entry / "stat").read_text().rsplit(")", 1)[1].split()[1])
        except (OSError, IndexError, ValueError):
            continue
        parents.setdefault(ppid, []).append(int(entry.name))
    found, todo = [], [root]
    while todo:
        pid = todo.pop()
        found.append(pid)
        todo.extend(parents.get(pid, []))
    return found


# ----------------------------------------------------------------------------------------------
# Load generation


@dataclass
class Phase:
    label: str
    endpoint: str
    path: str
    concurrency: int
    real: bool
    latencies_ms: list[float] = field(default_factory=list)
    statuses: Counter[int | str] = field(default_factory=Counter)
    failures: list[str] = field(default_factory=list)  # of measured requests
    warmup_failures: list[str] = field(default_factory=list)
    record_ids: list[int] = field(default_factory=list)
    warmup_record_ids: list[int] = field(default_factory=list)
    elapsed: float = 0.0
    client_cpu: float = 0.0
    server_cpu: float = 0.0
    process_cpu: list[float] = field(default_factory=list)  # cores, busiest server process first
    other_cpu: float = 0.0

    @property
    def completed(self) -> int:
        return len(self.latencies_ms)

    @property
    def errors(self) -> int:
        return len(self.failures)

    @property
    def throughput(self) -> float:
        ok = self.completed - self.errors
        return ok / self.elapsed if self.elapsed > 0 else 0.0

    def percentile(self, q: float) -> float:
        return float(np.percentile(self.latencies_ms, q)) if self.latencies_ms else float("nan")


class Feed:
    """Hands out payload indices: warm-up ones, then measured ones until a count or a deadline."""

    def __init__(self, start: int, measured: int, pool_size: int, distinct: bool) -> None:
        self._lock = threading.Lock()
        self._next = start
        self._stop_at = start  # set by begin()
        self._measured = measured
        self._pool = pool_size
        self._distinct = distinct
        self.deadline: float | None = None

    def take(self, stop_at: int | None = None) -> int | None:
        with self._lock:
            limit = self._stop_at if stop_at is None else stop_at
            if self._next >= limit or (self.deadline is not None and time.perf_counter() >= self.deadline):
                return None
            index = self._next
            self._next += 1
        if self._distinct and index >= self._pool:
            raise RuntimeError("payload pool exhausted")  # a sizing bug: never reuse a real record
        return index % self._pool

    def begin(self, deadline: float | None) -> None:
        with self._lock:
            self._stop_at = self._next + self._measured
            self.deadline = deadline

    @property
    def used(self) -> int:
        return self._next


class PhaseRun:
    """One run of a phase: ``phase.concurrency`` threads, one keep-alive connection each:
    warm-up, barrier, load. Its threads share what this object holds: the barrier they meet at
    once warmed up, the clock and CPU readings taken there, and the lock over the phase's figures.

    With ``reconnect_every`` > 0 each thread's every n-th request asks the server to close the
    connection, so that the thread's next request comes on a new one.
    """

    def __init__(
        self,
        phase: Phase,
        server: Server,
        key: str,
        payloads: list[bytes],
        feed: Feed,
        warmup: int,
        duration: float | None,
        reconnect_every: int,
        stop: threading.Event,
    ) -> None:
        self.phase, self.server, self.payloads, self.feed = phase, server, payloads, feed
        self.duration, self.reconnect_every, self.stop = duration, reconnect_every, stop
        self.headers = {"Authorization": f"Bearer {key}", "Content-Type": "application/json"}
        self.warm_each = max(2, -(-warmup // phase.concurrency))
        self.lock = threading.Lock()
        self.barrier = threading.Barrier(phase.concurrency + 1, action=self.start_measuring)
        self.clock: dict[str, float] = {}  # set at the barrier
        self.before: dict[int, float] = {}  # the server's CPU seconds by pid, at the barrier

    def start_measuring(self) -> None:
        """Run by the last thread to reach the barrier, before any goes on."""
        self.before.update(self.server.cpu_seconds())
        self.clock["cpu"], self.clock["machine"] = time.process_time(), machine_busy()
        self.clock["start"] = time.perf_counter()
        self.feed.begin(self.clock["start"] + self.duration if self.duration else None)

    def run(self) -> None:
        """The threads' warm-up and load, then the phase's time and CPU shares."""
        concurrency = self.phase.concurrency
        warm_limit = self.feed.used + self.warm_each * concurrency
        threads = [
            threading.Thread(target=self.worker, args=(warm_limit,), name=f"load-{i}", daemon=True)
            for i in range(concurrency)
        ]
        for thread in threads:
            thread.start()
        try:
            # All warmed up; start_measuring has run.
            self.barrier.wait(timeout=REQUEST_TIMEOUT * (self.warm_each + 1))
        except threading.BrokenBarrierError:
            self.phase.warmup_failures.append("the warm-up did not finish")
            self.stop.set()
        try:
            for thread in threads:
                thread.join()
        except BaseException:
            self.stop.set()
            self.barrier.abort()
            raise
        if "start" in self.clock:
            self.measured()

    def worker(self, warm_limit: int) -> None:
        """One thread's connection: its share of the warm-up, the barrier, then the load."""
        client = httpx.Client(base_url=self.server.url, headers=self.headers, timeout=REQUEST_TIMEOUT)
        try:
            for _ in range(self.warm_each):
                index = self.feed.take(warm_limit)
                if index is None or self.stop.is_set():
                    break
                self.send(client, index, self.phase.warmup_record_ids, measured=False)
            self.barrier.wait()
            sent = 0
            while not self.stop.is_set() and (index := self.feed.take()) is not None:
                sent += 1
                # "Connection: close" ends this connection after the answer; the next request
                # opens a new one, which may land on another worker process.
                last = self.reconnect_every > 0 and sent % self.reconnect_every == 0
                self.send(client, index, self.phase.record_ids, measured=True, close=last)
        except threading.BrokenBarrierError:
            return
        except Exception as exc:  # a bug here must end the phase, not leave the others waiting
            with self.lock:
                self.phase.warmup_failures.append(f"load thread failed: {type(exc).__name__}: {exc}")
            self.stop.set()
            self.barrier.abort()
        finally:
            client.close()

    def send(
        self, client: httpx.Client, index: int, record_ids: list[int], measured: bool, close: bool = False
    ) -> None:
        """One request, its latency and answer counted in the phase (or its warm-up)."""
        started = time.perf_counter()
        try:
            response = client.post(
                self.phase.path, content=self.payloads[index], headers=CLOSE if close else None
            )
            elapsed_ms = (time.perf_counter() - started) * 1000
            status: int | str = response.status_code
            problem, record_id = self.problem(response)
        except (httpx.HTTPError, ValueError) as exc:  # transport errors, a 2xx answer that is not JSON
            elapsed_ms = (time.perf_counter() - started) * 1000
            status, problem, record_id = type(exc).__name__, f"{type(exc).__name__}: {exc}", None
        with self.lock:
            if record_id is not None and problem is None:
                record_ids.append(record_id)
            if measured:
                self.phase.latencies_ms.append(elapsed_ms)
                self.phase.statuses[status] += 1
                if problem is not None:
                    self.phase.failures.append(problem)
            elif problem is not None:
                self.phase.warmup_failures.append(problem)

    def problem(self, response: httpx.Response) -> tuple[str | None, int | None]:
        """What is wrong with an answer (None: nothing), and the record id a real upload made."""
        if not 200 <= response.status_code < 300:
            return f"HTTP {response.status_code}: {response.text[:300]}", None
        if not self.phase.real:
            return None, None
        answer = response.json()
        if response.status_code != 201 or not answer.get("created") or answer.get("verdict") is None:
            return (
                f"HTTP {response.status_code}: not a new, inspected record: {response.text[:200]}",
                answer.get("id"),
            )
        return None, answer.get("id")

    def measured(self) -> None:
        """The phase's time, and the CPU this client, the server's processes and the rest of the
        machine used during it (cores)."""
        phase = self.phase
        phase.elapsed = time.perf_counter() - self.clock["start"]
        phase.client_cpu = (time.process_time() - self.clock["cpu"]) / phase.elapsed
        after = self.server.cpu_seconds()
        used = sorted(
            ((cpu - self.before.get(pid, 0.0)) / phase.elapsed for pid, cpu in after.items()), reverse=True
        )
        phase.server_cpu = sum(used)
        phase.process_cpu = [share for share in used if share >= 0.02]
        busy = (machine_busy() - self.clock["machine"]) / phase.elapsed
        phase.other_cpu = max(0.0, busy - phase.client_cpu - phase.server_cpu)


# ----------------------------------------------------------------------------------------------
# Checks and report


def verify(
    server: Server, key: str, structure_id: int, expected_ids: set[int], before: Counter[int]
) -> list[str]:
    """Problems found comparing the verdicts the run added with its successful uploads.

    ``before`` counts the verdicts of each record the structure already had (the demo's seeded
    history): those must be there unchanged, and are no upload's.
    """
    problems = []
    with httpx.Client(base_url=server.url, headers={"Authorization": f"Bearer {key}"}, timeout=60) as client:
        summary = client.get(f"/api/v1/structures/{structure_id}/summary")
        summary.raise_for_status()
        total = summary.json()["total"]
        if total != len(expected_ids) + before.total():
            problems.append(
                f"summary total is {total} verdicts, expected {before.total()} seeded + {len(expected_ids)}"
            )
        seen: list[int] = []
        cursor = None
        for _ in range(10_000):  # bounded: at most 10 million verdicts
            params: dict[str, str | int] = {"limit": 1000}
            if cursor:
                params["cursor"] = cursor
            page = client.get(f"/api/v1/structures/{structure_id}/verdicts", params=params)
            page.raise_for_status()
            body = page.json()
            seen.extend(item["record_id"] for item in body["items"])
            cursor = body["next_cursor"]
            if not cursor:
                break
    listed = Counter(seen)
    if any(listed[record_id] != count for record_id, count in before.items()):
        problems.append("the run changed the verdicts of the seeded history")
    added = listed - before
    if any(count > 1 for count in added.values()):
        problems.append(f"the verdict history lists {sum(c > 1 for c in added.values())} uploads twice")
    if set(added) != expected_ids:
        missing, extra = len(expected_ids - set(added)), len(set(added) - expected_ids)
        problems.append(
            f"verdict history vs uploads: {missing} uploads without a verdict, {extra} unexpected"
        )
    return problems


def verdicts_per_record(database: Path, structure_id: int) -> Counter[int]:
    with sqlite3.connect(database) as connection:
        query = "SELECT record_id FROM verdicts WHERE structure_id = ?"
        return Counter(row[0] for row in connection.execute(query, (structure_id,)))


def count_records(database: Path, structure_id: int) -> int:
    with sqlite3.connect(database) as connection:
        query = "SELECT count(*) FROM records WHERE structure_id = ?"
        return connection.execute(query, (structure_id,)).fetchone()[0]


def report(
    phases: list[Phase], args: argparse.Namespace, payload_bytes: int, access_log: bool, probes: list[float]
) -> None:
    cores = os.cpu_count()
    print()
    print(
        f"narxwatch API load, SQLite, uvicorn --workers {args.workers}, {cores} CPU cores, "
        f"access log {'on' if access_log else 'off'}; {SAMPLES}-sample JSON records "
        f"(~{payload_bytes / 1024:.0f} KiB each), client and server on the same machine"
    )
    print(
        "CPU probe (1e6-step Python loop, best of 3) before / after the load: "
        + " / ".join(f"{probe:.1f} ms" for probe in probes)
        + "; compare runs only at similar probe times"
    )
    header = (
        f"{'phase':<5} {'endpoint':<20} {'conc':>4} {'requests':>8} {'errors':>6} {'p50 ms':>7} "
        f"{'p95 ms':>7} {'p99 ms':>7} {'max ms':>7} {'req/s':>7}  {'CPU client':>10} {'server':>6} "
        f"{'other':>6} {'server ms/req':>13}  {'by process':<12}"
    )
    print(header)
    print("-" * len(header))
    for p in phases:
        print(
            f"{p.label:<5} {p.endpoint:<20} {p.concurrency:>4} {p.completed:>8} {p.errors:>6} "
            f"{p.percentile(50):>7.2f} {p.percentile(95):>7.2f} {p.percentile(99):>7.2f} "
            f"{max(p.latencies_ms, default=float('nan')):>7.1f} {p.throughput:>7.1f}  "
            f"{p.client_cpu:>10.0%} {p.server_cpu:>6.0%} {p.other_cpu:>6.0%} {_server_ms(p):>13}  "
            + "/".join(f"{share * 100:.0f}" for share in p.process_cpu)
        )
    print(
        f"CPU: 100 % = one core of {cores}. 'client' is this load generator (it competes with the server "
        "for the same cores), 'server' all uvicorn processes ('by process': each one's share, in %), "
        "'other' everything else on the machine."
    )
    uneven = [p for p in phases if p.concurrency > 1 and _uneven(p, args.workers)]
    if uneven:
        print(
            f"WARNING: in phase(s) {', '.join(p.label for p in uneven)} one worker process did most of "
            "the work: the connections landed unevenly on the workers (a keep-alive connection stays "
            "with the worker that accepted it). Repeat the run, or pass --reconnect-every N."
        )
    busiest = max(phases, key=lambda p: p.other_cpu)
    if busiest.other_cpu > 0.15:
        print(
            f"WARNING: other processes used up to {busiest.other_cpu:.0%} of a core during phase "
            f"{busiest.label}: the machine was not quiet, so these figures understate the server."
        )
    latency, sustained, noop_latency, noop_sustained = phases

    def ratio(a: float, b: float) -> str:
        return f"{a / b:.2f}" if b > 0 else "n/a"

    c = args.concurrency
    p50s = (
        ratio(latency.percentile(50), noop_latency.percentile(50)),
        ratio(sustained.percentile(50), noop_sustained.percentile(50)),
    )
    print()
    print(
        f"real / no-op: p50 {p50s[0]} at concurrency 1, {p50s[1]} at concurrency {c}; "
        f"throughput {ratio(sustained.throughput, noop_sustained.throughput)} at concurrency {c}; "
        f"server CPU per request {ratio(_per_request(sustained), _per_request(noop_sustained))}"
    )
    p50 = latency.percentile(50)
    print(
        f"target p50 <= {TARGET_P50_MS:g} ms (upload + inspect, concurrency 1): "
        f"{'met' if p50 <= TARGET_P50_MS else 'MISSED'} ({p50:.2f} ms)"
    )
    rate = sustained.throughput
    print(
        f"target >= {TARGET_THROUGHPUT:g} req/s sustained (upload + inspect, concurrency {args.concurrency}, "
        f"{args.workers} worker(s)): {'met' if rate >= TARGET_THROUGHPUT else 'MISSED'} ({rate:.1f} req/s)"
    )


def _uneven(phase: Phase, workers: int) -> bool:
    """True when, with several workers, one did more than 3/4 of the server's work."""
    busy = [share for share in phase.process_cpu if share >= 0.05]
    return workers > 1 and bool(busy) and busy[0] > 0.75 * phase.server_cpu and phase.server_cpu > 0.5


def _per_request(phase: Phase) -> float:
    """Server CPU milliseconds per successful request."""
    return phase.server_cpu / phase.throughput * 1000 if phase.throughput > 0 else float("nan")


def _server_ms(phase: Phase) -> str:
    return f"{_per_request(phase):.2f}"


# ----------------------------------------------------------------------------------------------


def say(message: str) -> None:
    print(message, flush=True)


def parse_args(argv: list[str] | None) -> argparse.Namespace:
    parser = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    parser.add_argument(
        "--requests", type=int, default=1000, help="measured requests per phase (default 1000)"
    )
    parser.add_argument(
        "--concurrency", type=int, default=8, help="connections of phases b and d (default 8)"
    )
    parser.add_argument("--workers", type=int, default=2, help="uvicorn worker processes (default 2)")
    parser.add_argument(
        "--duration", type=float, default=None,
        help="measure each phase for S seconds instead (still at most --requests requests)",
    )  # fmt: skip
    parser.add_argument("--warmup", type=int, default=50, help="warm-up requests per phase (default 50)")
    parser.add_argument(
        "--reconnect-every",
        type=int,
        default=0,
        metavar="N",
        help="open a new connection after every N requests (default 0: keep each connection; uvicorn "
        "never moves a keep-alive connection to another worker, so a few connections can load one worker)",
    )
    parser.add_argument("--server-log", type=Path, default=None, help="keep a copy of the server's log here")
    parser.add_argument("--seed", type=int, default=20260101, help="seed of the simulated records")
    parser.add_argument(
        "--no-access-log",
        action="store_true",
        help="run uvicorn without its access log (narxwatch serve has one)",
    )
    args = parser.parse_args(argv)
    if args.reconnect_every < 0:
        parser.error("--reconnect-every must be 0 or more")
    for name in ("requests", "concurrency", "workers"):
        if getattr(args, name) < 1:
            parser.error(f"--{name} must be at least 1")
    if args.requests > 100_000 or args.concurrency > 64:
        parser.error("--requests is limited to 100000 and --concurrency to 64")
    if args.duration is not None and not 0 < args.duration <= 3600:
        parser.error("--duration must be in (0, 3600] seconds")
    return args


@contextmanager
def terminate_as_interrupt() -> Iterator[None]:
    """SIGTERM ends the run like Ctrl-C, so the server and the folder are cleaned up."""

    def handler(signum: int, _frame: object) -> None:
        raise KeyboardInterrupt(f"signal {signum}")

    previous = signal.signal(signal.SIGTERM, handler)
    try:
        yield
    finally:
        signal.signal(signal.SIGTERM, previous)


def main(argv: list[str] | None = None) -> int:
    args = parse_args(argv)
    access_log = not args.no_access_log
    stop = threading.Event()
    server: Server | None = None
    with terminate_as_interrupt(), tempfile.TemporaryDirectory(prefix="narxwatch-load-") as folder:
        try:
            database = Path(folder) / "narxwatch.db"
            env = {
                **os.environ,
                "NARXWATCH_DATABASE_URL": f"sqlite:///{database}",
                "PYTHONPATH": os.pathsep.join(filter(None, [str(ROOT), os.environ.get("PYTHONPATH")])),
            }
            say(f"database {database}: narxwatch demo-seed, keys create --org demo --role ingest")
            structure_id, key = seeded(env)
            records_before = count_records(database, structure_id)
            verdicts_before = verdicts_per_record(database, structure_id)

            warm_each = max(2, -(-args.warmup // args.concurrency))
            real_needed = max(2, args.warmup) + args.requests + warm_each * args.concurrency + args.requests
            say(f"simulating {real_needed} distinct {SAMPLES}-sample records (JSON-encoded before timing)")
            payloads = make_payloads(real_needed, args.seed)
            mean_size = sum(len(p) for p in payloads) / len(payloads)

            probes = [cpu_probe_ms()]
            server = Server(env, args.workers, Path(folder) / "server.log", access_log)
            say(f"starting {SERVER_APP} on {server.url} with {args.workers} worker(s)")
            server.wait_ready()
            phases = run_phases(args, server, key, structure_id, payloads, stop)
            probes.append(cpu_probe_ms())
            report(phases, args, int(mean_size), access_log, probes)

            uploaded = {i for p in phases if p.real for i in (*p.record_ids, *p.warmup_record_ids)}
            try:
                problems = verify(server, key, structure_id, uploaded, verdicts_before)
            except httpx.HTTPError as exc:
                problems = [f"the verdict check itself failed: {type(exc).__name__}: {exc}"]
            server.stop()
            if args.server_log:
                shutil.copyfile(server.log_path, args.server_log)
            added = count_records(database, structure_id) - records_before
            if added != len(uploaded):
                problems.append(f"the records table grew by {added} rows, expected {len(uploaded)}")
            print()
            print(
                f"database check: {len(uploaded)} successful uploads (warm-up included) -> "
                + ("records and verdicts match" if not problems else "; ".join(problems))
            )
            failures = report_failures(phases, server)
            return 1 if failures or problems else 0
        except KeyboardInterrupt:
            stop.set()
            print("\ninterrupted: stopping the server and removing the temporary folder", file=sys.stderr)
            return 130
        finally:
            if server is not None:
                server.stop()


def seeded(env: dict[str, str]) -> tuple[int, str]:
    """``narxwatch demo-seed`` and an ingest key: the demo structure's id, and the key."""
    output = run_cli(["demo-seed"], env)
    found = re.search(r"is structure (\d+)", output)
    if found is None:
        raise SystemExit(f"cannot find the structure id in demo-seed's output:\n{output}")
    keys = re.findall(
        r"^(nw_\S+)$", run_cli(["keys", "create", "--org", "demo", "--role", "ingest"], env), re.M
    )
    if len(keys) != 1:
        raise SystemExit("cannot find the key in the output of narxwatch keys create")
    return int(found.group(1)), keys[0]


def run_phases(
    args: argparse.Namespace,
    server: Server,
    key: str,
    structure_id: int,
    payloads: list[bytes],
    stop: threading.Event,
) -> list[Phase]:
    """The four phases in turn: the real upload, then the no-op, each at concurrency 1 and C."""
    real_path = f"/api/v1/structures/{structure_id}/records?inspect=true"
    real_feed = Feed(0, args.requests, len(payloads), distinct=True)
    noop_feed = Feed(0, args.requests, len(payloads), distinct=False)
    phases = [
        Phase("a", "upload, inspect=true", real_path, 1, real=True),
        Phase("b", "upload, inspect=true", real_path, args.concurrency, real=True),
        Phase("c", "no-op, same payload", NOOP_PATH, 1, real=False),
        Phase("d", "no-op, same payload", NOOP_PATH, args.concurrency, real=False),
    ]
    for phase in phases:
        say(f"phase {phase.label}: {phase.endpoint}, concurrency {phase.concurrency} ...")
        feed = real_feed if phase.real else noop_feed
        PhaseRun(
            phase, server, key, payloads, feed, args.warmup, args.duration, args.reconnect_every, stop
        ).run()
        say(f"    {phase.completed} requests in {phase.elapsed:.1f} s, {phase.errors} failed")
    return phases


def report_failures(phases: list[Phase], server: Server) -> list[str]:
    """The failed requests, measured or not, printed with the most frequent and the server log's
    last lines other than the access log."""
    failures = [f for p in phases for f in p.failures] + [
        f"(phase {p.label}, outside the measurement) {f}" for p in phases for f in p.warmup_failures
    ]
    if failures:
        print(
            f"{len(failures)} request(s) failed; answers: "
            + "; ".join(f"phase {p.label} {dict(p.statuses)}" for p in phases)
        )
        print("the most frequent failures:")
        for failure in Counter(failures).most_common(5):
            print(f"    {failure[1]} x {failure[0]}")
        print(f"server log, last lines other than the access log:\n{server.log_tail(40, access=False)}")
    return failures


if __name__ == "__main__":
    sys.exit(main())
