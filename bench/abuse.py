"""Abuse benchmark: one organisation does the worst it can, another must not notice.

    .venv/bin/python bench/abuse.py [--quick] [--database sqlite|postgresql|both] [--seconds S]

For each database (SQLite, then a throwaway PostgreSQL server from harness/postgres.py):

1. In a fresh temporary folder, ``narxwatch demo-seed`` (the victim: organisation ``demo`` with its
   trained structure) and keys: the victim's ingest and viewer keys, the attacker's ingest and
   admin keys (organisation ``attacker``).
2. ``narxwatch serve --workers 2`` on a free port of 127.0.0.1 (all traffic stays on loopback),
   in its own process group, and on PostgreSQL two ``narxwatch worker`` processes for queued
   work. The attacker creates a structure and uploads a large record (``--large-samples``) and a
   small one.
3. The victim alone for ``--baseline`` seconds, then the victim during the attack for
   ``--seconds``. The victim is two clients, each pausing 0.1 s between requests: one reads
   (``GET /structures`` and the structure's verdict history, in turn), one uploads distinct
   2000-sample simulated records with ``inspect=true``.
4. The attack, with the attacker's keys only:
   - 40 slow bodies: uploads that declare a small JSON body and send it 2 bytes every
     ``--trickle`` seconds (reconnecting when the server answers or closes);
   - NPZ decompression bombs, one after another: a ~4 MB archive whose ``fs`` member declares
     5·10⁸ float64 (4 GB unpacked);
   - maximal trainings: two clients training a baseline on the large record in a loop (the
     costliest training the service still runs within a request), and ``--trainings`` concurrent
     clients training on the small one (``[record] * 20``, the finding's request, is refused at
     once since record ids may not repeat: tests/test_api_bounded.py shows it).
   Every attacking request is bounded by the end of the attack window; every loop ends there.
5. Throughout, the worker processes (the children of ``narxwatch serve`` that run uvicorn's
   workers, and the ``narxwatch worker`` processes) are watched every 0.2 s in /proc: their peak
   RSS (VmHWM) and whether any disappeared (uvicorn replaces a killed or unresponsive worker with
   a new process, so a death shows as a new PID).

Prints, per database, the victim's requests, 5xx answers, transport errors, p50/p95/max latency
(alone and under attack), the workers that died, each worker's peak RSS, what the attacker's
requests got, and one line per target of issue 13: victim 0 5xx (and no dropped connection),
victim p95 ≤ 1 s under attack, no worker dies, each worker's peak RSS ≤ 1 GB. The exit status
is non-zero when a target is missed. ``--quick`` is a shorter, lighter run of the same.
"""

from __future__ import annotations

import argparse
import io
import json
import os
import re
import signal
import socket
import subprocess
import sys
import tempfile
import threading
import time
import zipfile
from collections import Counter
from collections.abc import Callable, Iterator
from contextlib import ExitStack, contextmanager, suppress
from dataclasses import dataclass, field
from pathlib import Path

ROOT = Path(__file__).resolve().parents[1]
sys.path.insert(0, str(ROOT))  # this checkout's bench and harness, run as a script

from models.blas import one_blas_thread

one_blas_thread()  # before numpy is imported: one BLAS thread, as in narxwatch's processes
import httpx
import numpy as np

from bench.load_api import console_script, free_port, make_payloads, run_cli

HOST = "127.0.0.1"
API = "/api/v1"
TARGET_P95_S = 1.0
TARGET_RSS_BYTES = 1 << 30
SLOW_BODIES = 40
BOMB_ELEMENTS = 500_000_000  # float64: 4 GB once unpacked
VICTIM_PAUSE_S = 0.1
WATCH_INTERVAL_S = 0.2


# ----------------------------------------------------------------------------------------------
# Bodies


def npz(**arrays: np.ndarray) -> bytes:
    buffer = io.BytesIO()
    np.savez(buffer, **arrays)
    return buffer.getvalue()


def npz_bomb(elements: int = BOMB_ELEMENTS) -> bytes:
    """A valid-looking record whose ``fs`` member declares ``elements`` float64 zeros, deflated:
    a few MB that unpack to ``8 * elements`` bytes."""
    buffer = io.BytesIO()
    with zipfile.ZipFile(buffer, "w", zipfile.ZIP_DEFLATED, compresslevel=9) as archive:
        for name in ("x", "y"):
            member = io.BytesIO()
            np.save(member, np.zeros(300))
            archive.writestr(f"{name}.npy", member.getvalue())
        with archive.open("fs.npy", "w", force_zip64=True) as stream:
            header = {"descr": "<f8", "fortran_order": False, "shape": (elements,)}
            np.lib.format.write_array_header_1_0(stream, header)
            chunk = bytes(1 << 24)
            left = 8 * elements
            while left:
                stream.write(chunk[: min(left, len(chunk))])
                left -= min(left, len(chunk))
    return buffer.getvalue()


def cached_bomb() -> bytes:
    """The bomb, kept in the system's temporary folder: deflating 4 GB takes tens of seconds."""
    path = Path(tempfile.gettempdir()) / f"narxwatch-abuse-bomb-{BOMB_ELEMENTS}.npz"
    if not path.exists():
        partial = path.with_suffix(f".{os.getpid()}.part")
        partial.write_bytes(npz_bomb())
        partial.replace(path)
    return path.read_bytes()


def noise_npz(n: int, seed: int) -> bytes:
    rng = np.random.default_rng(seed)
    return npz(x=rng.normal(0.0, 1.0, n), y=rng.normal(0.0, 1e-3, n), fs=np.float64(1500.0))


# ----------------------------------------------------------------------------------------------
# The server and its workers


def spawn_server(env: dict[str, str], port: int, log: Path) -> subprocess.Popen[bytes]:
    return spawn(["serve", "--host", HOST, "--port", str(port), "--workers", "2"], env, log)


def spawn(args: list[str], env: dict[str, str], log: Path) -> subprocess.Popen[bytes]:
    with log.open("wb") as out:
        return subprocess.Popen(
            [console_script("narxwatch"), *args],
            env=env,
            cwd=ROOT,
            stdout=out,
            stderr=subprocess.STDOUT,
            start_new_session=True,
        )


def stop(process: subprocess.Popen[bytes]) -> None:
    if process.poll() is None:
        with suppress(ProcessLookupError):
            os.killpg(process.pid, signal.SIGTERM)
        try:
            process.wait(30)
        except subprocess.TimeoutExpired:
            with suppress(ProcessLookupError):
                os.killpg(process.pid, signal.SIGKILL)
            process.wait(30)


def wait_ready(url: str, process: subprocess.Popen[bytes], timeout: float = 300) -> None:
    deadline = time.monotonic() + timeout
    while time.monotonic() < deadline and process.poll() is None:
        with suppress(httpx.TransportError):
            if httpx.get(f"{url}/readyz", timeout=2).status_code == 200:
                return
        time.sleep(0.2)
    raise SystemExit(f"narxwatch serve at {url} did not become ready (exit status {process.poll()})")


def _status_fields(pid: int) -> dict[str, str]:
    try:
        text = Path(f"/proc/{pid}/status").read_text()
    except OSError:
        return {}
    return dict(line.split(":", 1) for line in text.splitlines() if ":" in line)


def worker_pids(server_pid: int) -> set[int]:
    """uvicorn's worker processes: children of the server started by multiprocessing's spawn."""
    found = set()
    for entry in Path("/proc").iterdir():
        if not entry.name.isdigit():
            continue
        try:
            stat = (entry / "stat").read_text()
            cmdline = (entry / "cmdline").read_bytes()
        except OSError:
            continue
        parent = int(stat.rsplit(")", 1)[1].split()[1])
        if parent == server_pid and b"spawn_main" in cmdline:
            found.add(int(entry.name))
    return found


def _running(pid: int) -> bool:
    """Alive and not a zombie (a killed child stays in /proc until its parent reaps it)."""
    return not _status_fields(pid).get("State", "Z").strip().startswith("Z")


@dataclass
class WorkerWatch:
    """Every worker process seen, its peak RSS (VmHWM, bytes) and which of them went away: uvicorn's
    workers of the server (replaced when they die) and the ``narxwatch worker`` job processes."""

    server_pid: int
    job_workers: list[int]
    peak: dict[int, int] = field(default_factory=dict)
    gone: list[int] = field(default_factory=list)
    _stop: threading.Event = field(default_factory=threading.Event)

    def _look(self) -> None:
        alive = worker_pids(self.server_pid) | {pid for pid in self.job_workers if _running(pid)}
        for pid in alive:
            hwm = _status_fields(pid).get("VmHWM", "0 kB").split()[0]
            self.peak[pid] = max(self.peak.get(pid, 0), int(hwm) * 1024)
        self.gone += [pid for pid in self.peak if pid not in alive and pid not in self.gone]

    def kind(self, pid: int) -> str:
        return "job" if pid in self.job_workers else "serve"

    @contextmanager
    def watching(self) -> Iterator[WorkerWatch]:
        def run() -> None:
            while not self._stop.wait(WATCH_INTERVAL_S):
                self._look()

        self._look()
        thread = threading.Thread(target=run, daemon=True)
        thread.start()
        try:
            yield self
        finally:
            self._stop.set()
            thread.join()
            self._look()


# ----------------------------------------------------------------------------------------------
# Clients


@dataclass
class Tally:
    """Answers (status code, or the transport error's name) and latencies of one kind of client."""

    answers: Counter[str] = field(default_factory=Counter)
    latencies: list[float] = field(default_factory=list)
    lock: threading.Lock = field(default_factory=threading.Lock)

    def note(self, answer: str, took: float | None = None) -> None:
        with self.lock:
            self.answers[answer] += 1
            if took is not None:
                self.latencies.append(took)

    def server_errors(self) -> int:
        return sum(n for answer, n in self.answers.items() if answer.isdigit() and int(answer) >= 500)

    def transport_errors(self) -> int:
        return sum(n for answer, n in self.answers.items() if not answer.isdigit())

    def percentiles(self) -> tuple[float, float, float]:
        if not self.latencies:
            return (float("nan"),) * 3
        p50, p95, top = np.percentile(self.latencies, [50, 95, 100])
        return float(p50), float(p95), float(top)


def timed(tally: Tally, request: Callable[[], httpx.Response]) -> httpx.Response | None:
    began = time.perf_counter()
    try:
        response = request()
    except httpx.TransportError as exc:
        tally.note(type(exc).__name__, time.perf_counter() - began)
        return None
    tally.note(str(response.status_code), time.perf_counter() - began)
    return response


def victim(url: str, keys: dict[str, str], structure_id: int, payloads: list[bytes], until: float) -> Tally:
    """The other organisation's reader and uploader until ``until`` (time.monotonic)."""
    tally = Tally()

    def reader() -> None:
        headers = {"Authorization": f"Bearer {keys['viewer']}"}
        paths = [f"{API}/structures", f"{API}/structures/{structure_id}/verdicts?limit=50"]
        with httpx.Client(base_url=url, headers=headers, timeout=60) as http:
            for i in range(1_000_000):
                if time.monotonic() >= until:
                    return
                timed(tally, lambda i=i: http.get(paths[i % 2]))
                time.sleep(VICTIM_PAUSE_S)

    def uploader() -> None:
        headers = {"Authorization": f"Bearer {keys['ingest']}", "Content-Type": "application/json"}
        route = f"{API}/structures/{structure_id}/records?inspect=true"
        with httpx.Client(base_url=url, headers=headers, timeout=60) as http:
            for body in payloads:
                if time.monotonic() >= until:
                    return
                timed(tally, lambda body=body: http.post(route, content=body))
                time.sleep(VICTIM_PAUSE_S)

    threads = [threading.Thread(target=reader), threading.Thread(target=uploader)]
    for thread in threads:
        thread.start()
    for thread in threads:
        thread.join()
    return tally


def slow_body(port: int, key: str, structure_id: int, trickle: float, until: float, tally: Tally) -> None:
    """One upload whose body arrives 2 bytes every ``trickle`` s; again when the server ends it."""
    body = json.dumps({"x": [0.5] * 300, "y": [0.25] * 300, "fs": 1500.0}).encode()
    head = (
        f"POST {API}/structures/{structure_id}/records HTTP/1.1\r\nHost: {HOST}:{port}\r\n"
        f"Authorization: Bearer {key}\r\nContent-Type: application/json\r\n"
        f"Content-Length: {len(body)}\r\n\r\n"
    ).encode()
    while time.monotonic() < until:
        try:
            with socket.create_connection((HOST, port), timeout=5) as connection:
                connection.sendall(head)
                connection.settimeout(trickle)
                tally.note(_trickle(connection, body, until))
        except OSError as exc:
            tally.note(type(exc).__name__)
            time.sleep(1)


def _trickle(connection: socket.socket, body: bytes, until: float) -> str:
    """Send ``body`` 2 bytes per timeout of the socket; what the server said, if anything."""
    for offset in range(0, len(body), 2):
        if time.monotonic() >= until:
            return "still waiting at the end"
        try:
            answer = connection.recv(4096)
        except TimeoutError:  # nothing from the server yet: go on trickling
            connection.sendall(body[offset : offset + 2])
            continue
        status = re.match(rb"HTTP/1\.[01] (\d{3})", answer)
        return status.group(1).decode() if status else "closed by the server"
    return "sent whole"


def repeat(
    url: str, key: str, send: Callable[[httpx.Client, float], httpx.Response], until: float, tally: Tally
) -> None:
    """``send`` again and again until ``until``, each request bounded by the time left."""
    headers = {"Authorization": f"Bearer {key}"}
    while (left := until - time.monotonic()) > 1:
        with httpx.Client(base_url=url, headers=headers) as http:
            if timed(tally, lambda http=http, left=left: send(http, left)) is None:
                time.sleep(0.5)


@dataclass
class Attack:
    slow: Tally = field(default_factory=Tally)
    bombs: Tally = field(default_factory=Tally)
    large_trainings: Tally = field(default_factory=Tally)
    many_trainings: Tally = field(default_factory=Tally)


def attack(
    url: str, port: int, keys: dict[str, str], target: dict[str, int], bomb: bytes, args, until: float
) -> tuple[Attack, list[threading.Thread]]:
    """Start every attacking client; they stop by themselves at ``until``."""
    tallies = Attack()
    sid = target["structure_id"]
    baseline = f"{API}/structures/{sid}/models/baseline"

    def bombs(http: httpx.Client, left: float) -> httpx.Response:
        return http.post(
            f"{API}/structures/{sid}/records",
            content=bomb,
            headers={"Content-Type": "application/x-npz"},
            timeout=left,
        )

    def train_on(record: str) -> Callable[[httpx.Client, float], httpx.Response]:
        return lambda http, left: http.post(baseline, json={"record_ids": [target[record]]}, timeout=left)

    threads = [
        threading.Thread(
            target=slow_body, args=(port, keys["ingest"], sid, args.trickle, until, tallies.slow)
        )
        for _ in range(SLOW_BODIES)
    ]
    threads.append(threading.Thread(target=repeat, args=(url, keys["ingest"], bombs, until, tallies.bombs)))
    threads += [
        threading.Thread(
            target=repeat, args=(url, keys["admin"], train_on("large"), until, tallies.large_trainings)
        )
        for _ in range(2)
    ]
    threads += [
        threading.Thread(
            target=repeat, args=(url, keys["admin"], train_on("small"), until, tallies.many_trainings)
        )
        for _ in range(args.trainings)
    ]
    for thread in threads:
        thread.start()
    return tallies, threads


# ----------------------------------------------------------------------------------------------
# One database


@dataclass
class Outcome:
    database: str
    alone: Tally
    attacked: Tally
    attack: Attack
    watch: WorkerWatch
    deaths_logged: int

    def misses(self) -> list[str]:
        missed = []
        errors = self.attacked.server_errors() + self.attacked.transport_errors()
        if errors:
            missed.append(f"victim answered 5xx or dropped {errors} time(s): {dict(self.attacked.answers)}")
        if not self.attacked.percentiles()[1] <= TARGET_P95_S:
            missed.append(f"victim p95 {self.attacked.percentiles()[1]:.2f} s > {TARGET_P95_S} s")
        if self.watch.gone or self.deaths_logged:
            missed.append(
                f"worker processes died: {self.watch.gone} ({self.deaths_logged} in the server log)"
            )
        if fat := {pid: rss for pid, rss in self.watch.peak.items() if rss > TARGET_RSS_BYTES}:
            missed.append(
                f"worker peak RSS over 1 GB: { {pid: f'{rss / 2**30:.2f} GB' for pid, rss in fat.items()} }"
            )
        return missed


def run_database(name: str, url: str, args, bomb: bytes, payloads: list[bytes], folder: Path) -> Outcome:
    env = {**os.environ, "NARXWATCH_DATABASE_URL": url, "NARXWATCH_LOG_FORMAT": "text"}
    say(f"[{name}] seeding the demo (the victim) and minting keys …")
    run_cli(["demo-seed"], env)

    def key(org: str, role: str) -> str:
        return run_cli(["keys", "create", "--org", org, "--role", role], env).strip()

    victim_keys = {role: key("demo", role) for role in ("ingest", "viewer")}
    attacker_keys = {role: key("attacker", role) for role in ("ingest", "admin")}
    port = free_port()
    api_url = f"http://{HOST}:{port}"
    log = folder / f"serve-{name}.log"
    server = spawn_server(env, port, log)
    # On PostgreSQL queued work (inspections, and whatever the service queues) runs in
    # `narxwatch worker` processes, as in production: two of them, watched like the server's.
    job_workers = [
        spawn(["worker"], env, folder / f"worker-{i}.log") for i in range(2 if name == "postgresql" else 0)
    ]
    try:
        wait_ready(api_url, server)
        with httpx.Client(base_url=api_url, timeout=120) as http:
            structures = http.get(
                f"{API}/structures", headers={"Authorization": f"Bearer {victim_keys['viewer']}"}
            )
            victim_sid = structures.json()[0]["id"]
            target = attacker_setup(http, attacker_keys, args.large_samples)
        say(f"[{name}] the victim alone for {args.baseline:.0f} s …")
        half = len(payloads) // 3
        alone = victim(api_url, victim_keys, victim_sid, payloads[:half], time.monotonic() + args.baseline)
        say(
            f"[{name}] the attack for {args.seconds:.0f} s (40 slow bodies, bombs, "
            f"2 + {args.trainings} trainings) …"
        )
        logged_before = log.stat().st_size  # worker deaths are counted from here on
        with WorkerWatch(server.pid, [worker.pid for worker in job_workers]).watching() as watch:
            until = time.monotonic() + args.seconds
            tallies, threads = attack(api_url, port, attacker_keys, target, bomb, args, until)
            time.sleep(min(2.0, args.seconds / 10))  # the attack takes hold before the victim comes
            attacked = victim(api_url, victim_keys, victim_sid, payloads[half:], until)
            for thread in threads:
                thread.join(timeout=max(1.0, until - time.monotonic() + 30))
            lingering = sum(thread.is_alive() for thread in threads)
            if lingering:
                say(f"[{name}] {lingering} attacking client(s) still waiting; they are abandoned")
    finally:
        for process in (server, *job_workers):
            stop(process)
    with log.open("rb") as text:
        text.seek(logged_before)
        deaths = len(re.findall(rb"Child process \[\d+\] died", text.read()))
    return Outcome(name, alone, attacked, tallies, watch, deaths)


def attacker_setup(http: httpx.Client, keys: dict[str, str], large_samples: int) -> dict[str, int]:
    admin = {"Authorization": f"Bearer {keys['admin']}"}
    response = http.post(f"{API}/structures", json={"name": "target", "fs": 1500.0}, headers=admin)
    response.raise_for_status()
    sid = response.json()["id"]
    ids = {"structure_id": sid}
    for name, n in (("large", large_samples), ("small", 2000)):
        response = http.post(
            f"{API}/structures/{sid}/records",
            content=noise_npz(n, seed=n),
            headers={**admin, "Content-Type": "application/x-npz"},
        )
        response.raise_for_status()
        ids[name] = response.json()["id"]
    return ids


# ----------------------------------------------------------------------------------------------
# Report


def report(outcomes: list[Outcome]) -> None:
    print()
    print(f"machine load (1-minute average) at the end: {os.getloadavg()[0]:.1f} on {os.cpu_count()} cores")
    head = (
        f"{'database':11}{'phase':9}{'requests':>9}{'5xx':>5}{'dropped':>8}"
        f"{'p50 ms':>9}{'p95 ms':>9}{'max ms':>9}  {'workers died':14}peak RSS per worker (MB)"
    )
    print(head)
    print("-" * len(head))
    for outcome in outcomes:
        for phase, tally in (("alone", outcome.alone), ("attacked", outcome.attacked)):
            p50, p95, top = (1000 * v for v in tally.percentiles())
            workers = died = ""
            if phase == "attacked":
                died = f"{len(outcome.watch.gone)} ({outcome.deaths_logged} logged)"
                workers = ", ".join(
                    f"{rss / 2**20:.0f}{' (job)' if outcome.watch.kind(pid) == 'job' else ''}"
                    for pid, rss in sorted(outcome.watch.peak.items())
                )
            print(
                f"{outcome.database:11}{phase:9}{len(tally.latencies):>9}{tally.server_errors():>5}"
                f"{tally.transport_errors():>8}{p50:>9.0f}{p95:>9.0f}{top:>9.0f}  {died:14}{workers}"
            )
    print()
    for outcome in outcomes:
        a = outcome.attack
        print(
            f"[{outcome.database}] attacker's answers: slow bodies {dict(a.slow.answers)}; "
            f"bombs {dict(a.bombs.answers)}; "
            f"trainings on the large record {dict(a.large_trainings.answers)}; "
            f"concurrent trainings {dict(a.many_trainings.answers)}"
        )
    print()
    for outcome in outcomes:
        misses = outcome.misses()
        for miss in misses:
            print(f"[{outcome.database}] target missed: {miss}")
        if not misses:
            print(
                f"[{outcome.database}] every target met: victim 0 5xx, p95 ≤ 1 s, no worker died, RSS ≤ 1 GB"
            )


def say(message: str) -> None:
    print(message, flush=True)


def parse_args(argv: list[str] | None) -> argparse.Namespace:
    parser = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    parser.add_argument("--quick", action="store_true", help="a shorter, lighter run of the same")
    parser.add_argument("--database", choices=["sqlite", "postgresql", "both"], default="both")
    parser.add_argument("--seconds", type=float, help="length of the attack (default 90, quick 25)")
    parser.add_argument("--baseline", type=float, help="the victim alone first (default 10, quick 5)")
    parser.add_argument("--trickle", type=float, help="seconds between a slow body's 2 bytes (5, quick 2)")
    parser.add_argument("--trainings", type=int, help="concurrent small trainings (default 45, quick 15)")
    parser.add_argument("--large-samples", type=int, help="the large record (default 150 000, quick 100 000)")
    args = parser.parse_args(argv)
    defaults = {
        "seconds": (90, 25),
        "baseline": (10, 5),
        "trickle": (5, 2),
        "trainings": (45, 15),
        "large_samples": (150_000, 100_000),
    }
    for name, (full, quick) in defaults.items():
        if getattr(args, name) is None:
            setattr(args, name, quick if args.quick else full)
    if not 0 < args.seconds <= 600 or not 0 < args.baseline <= 120:
        parser.error("the attack lasts at most 600 s and the baseline at most 120 s")
    return args


def main(argv: list[str] | None = None) -> int:
    args = parse_args(argv)
    names = ["sqlite", "postgresql"] if args.database == "both" else [args.database]
    say("building the NPZ bomb and the victim's records …")
    bomb = cached_bomb()
    say(f"the bomb: {len(bomb) / 2**20:.1f} MB, declaring {BOMB_ELEMENTS:.0e} float64 in its fs member")
    payloads = make_payloads(600 if args.quick else 1500, seed=20261123)
    outcomes = []
    for name in names:
        with ExitStack() as stack:
            folder = Path(stack.enter_context(tempfile.TemporaryDirectory(prefix=f"narxwatch-abuse-{name}-")))
            if name == "sqlite":
                url = f"sqlite:///{folder / 'narxwatch.db'}"
            else:
                from harness import postgres

                url = stack.enter_context(postgres.postgres_server("abuse"))
                if url is None:
                    raise SystemExit(f"PostgreSQL unavailable: {postgres.missing_reason()}")
            outcomes.append(run_database(name, url, args, bomb, payloads, folder))
    report(outcomes)
    return 1 if any(outcome.misses() for outcome in outcomes) else 0


if __name__ == "__main__":
    sys.exit(main())
