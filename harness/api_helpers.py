"""Shared set-up for the HTTP tests: structures, records, trained fault-mode models, and a check
that a refused request left nothing behind.

Everything goes through the API of a :class:`live.LiveServer`, but for the rows the refusal check
reads from its database (``nothing_written``).
"""

from __future__ import annotations

import ast
import asyncio
import io
import itertools
import json
import sys
import threading
import time
import uuid
from collections.abc import Callable, Iterator
from contextlib import contextmanager
from dataclasses import dataclass
from typing import Any

import httpx
import numpy as np
from sqlalchemy import select

from harness.live import LiveServer
from service.db import Base, transaction
from service.security import Role
from simulator.simulate import SimulatedRecord, simulate
from simulator.study import StudySettings
from simulator.theory import EXACT_TERMS

API = "/api/v1"
FS = 1500.0
SETTINGS = StudySettings()
# Magnitudes of the fault-mode training experiments: three are enough for a degree-1 basis
# (two functions) and keep each training to a fraction of a second.
TRAINING_K = (-30.0, 0.0, 30.0)
# Nine: the model's own error, the same in every record it inspects, is then a share of σ̂k² small
# enough for a CUSUM with a false-alarm rate of a year (service.domain.alarms.MAX_THRESHOLD).
CUSUM_TRAINING_K = (-30.0, -22.5, -15.0, -7.5, 0.0, 7.5, 15.0, 22.5, 30.0)
TRAINING_SAMPLES = 2000
# The paper rig's structure (SPEC §2), which the rig's models here are trained with by name: a
# training without terms chooses them (a baseline) or takes the active baseline's (a fault mode).
RIG_TERMS = [term.name for term in EXACT_TERMS]
_noise_seeds = itertools.count(1_000_000)

# CPython 3.11 keeps the AST constructor's recursion depth in interpreter-wide state, so two
# threads parsing at once can fail with "SystemError: AST constructor recursion depth mismatch"
# (pytest-dev/pytest#10763, python/cpython#106905). Here they do: the server thread logs each 500
# with a traceback, whose carets 3.11 places with ast.parse, while pytest parses sources to report
# the failing test, and the INTERNALERROR ends the session. Parsing is serialised to avoid it.
if sys.version_info < (3, 12) and not hasattr(ast.parse, "serialised"):
    _parse, _parsing = ast.parse, threading.RLock()

    def _serialised_parse(*args: Any, **kwargs: Any) -> Any:
        with _parsing:
            return _parse(*args, **kwargs)

    _serialised_parse.serialised = True  # type: ignore[attr-defined]
    ast.parse = _serialised_parse  # type: ignore[assignment]


# --- bodies ---------------------------------------------------------------------------------


def noise(n: int, seed: int | None = None) -> tuple[np.ndarray, np.ndarray]:
    """Two unrelated white signals of ``n`` samples: a valid record, never inspected."""
    rng = np.random.default_rng(next(_noise_seeds) if seed is None else seed)
    return rng.normal(0.0, 1.0, n), rng.normal(0.0, 1e-3, n)


def json_body(n: int = 300, *, fs: float = FS, seed: int | None = None, **extra: Any) -> dict[str, Any]:
    x, y = noise(n, seed)
    return {"x": x.tolist(), "y": y.tolist(), "fs": fs, **extra}


def npz_bytes(**arrays: Any) -> bytes:
    buffer = io.BytesIO()
    np.savez(buffer, **arrays)
    return buffer.getvalue()


def csv_text(x: np.ndarray, y: np.ndarray, fs: float | None = FS) -> str:
    head = f"# fs={fs:g}\n" if fs is not None else ""
    return head + "x,y\n" + "".join(f"{a:.17g},{b:.17g}\n" for a, b in zip(x, y, strict=True))


def record_set_csv(records: int, samples: int, seed: int) -> str:
    """A CSV of ``records`` realisations side by side: the groups x and y, as Wiener–Hammerstein's
    files hold theirs."""
    rng = np.random.default_rng(seed)
    x, y = rng.standard_normal((2, samples, records)) * 1e-3
    header = ",".join(["x"] + [""] * (records - 1) + ["y"] + [""] * (records - 1))
    rows = (",".join(f"{v:.9g}" for v in (*xs, *ys)) for xs, ys in zip(x, y, strict=True))
    return "\n".join([header, *rows])


def raw_json(document: Any) -> bytes:
    """JSON as Python writes it: non-finite floats become the non-standard NaN/Infinity tokens."""
    return json.dumps(document).encode()


# --- requests -------------------------------------------------------------------------------


def records_url(structure_id: int) -> str:
    return f"{API}/structures/{structure_id}/records"


def post_record(
    client: httpx.Client,
    structure_id: int,
    body: dict[str, Any] | bytes | str,
    content_type: str | None = None,
    **params: Any,
) -> httpx.Response:
    """Upload ``body`` (a dict is sent as JSON) with the given Content-Type."""
    if isinstance(body, dict):
        content: bytes | str = raw_json(body)
        content_type = content_type or "application/json"
    else:
        content = body
    headers = {"Content-Type": content_type} if content_type is not None else {}
    return client.post(records_url(structure_id), content=content, headers=headers, params=params)


def stored(response: httpx.Response) -> dict:
    """The answer of an upload that stored a record (new, 201, or known, 200)."""
    assert response.status_code in (200, 201), response.text
    return response.json()


def upload_simulated(client: httpx.Client, structure_id: int, record: SimulatedRecord, **params: Any) -> dict:
    response = post_record(
        client, structure_id, npz_bytes(x=record.x, y=record.y, fs=record.fs), "application/x-npz", **params
    )
    assert response.status_code in (200, 201), response.text
    return response.json()


def simulated(fault: str, k: float, seed: Any, n: int = TRAINING_SAMPLES) -> SimulatedRecord:
    return simulate(SETTINGS.scenario(fault, k), n, np.random.SeedSequence(seed))  # type: ignore[arg-type]


def create_structure(admin: httpx.Client, name: str | None = None, fs: float = FS) -> dict:
    response = admin.post(f"{API}/structures", json={"name": name or f"rig-{uuid.uuid4().hex[:8]}", "fs": fs})
    assert response.status_code == 201, response.text
    return response.json()


def experiments(
    ingest: httpx.Client, structure_id: int, mode: str, seed: int, magnitudes: tuple[float, ...] = TRAINING_K
) -> list[dict]:
    """Upload one simulated training record per magnitude; the experiments of a training body."""
    return [
        {"record_id": upload_simulated(ingest, structure_id, simulated(mode, k, [seed, i]))["id"], "k": k}
        for i, k in enumerate(magnitudes)
    ]


def train_fault_mode(
    admin: httpx.Client,
    ingest: httpx.Client,
    structure_id: int,
    mode: str = "k2",
    seed: int = 1,
    magnitudes: tuple[float, ...] = TRAINING_K,
    **extra: Any,
) -> dict:
    """Train (a new version of) fault mode ``mode`` from simulated experiments (three by default)."""
    body = {
        "name": mode,
        "k_min": -32.0,
        "k_max": 32.0,
        "experiments": experiments(ingest, structure_id, mode, seed, magnitudes),
        "terms": RIG_TERMS,
        **extra,
    }
    response = admin.post(f"{API}/structures/{structure_id}/models/fault-modes", json=body)
    assert response.status_code == 201, response.text
    return response.json()


def verdicts(viewer: httpx.Client, structure_id: int) -> list[dict]:
    """The structure's verdicts (the tests here make far fewer than a page of 1000)."""
    return viewer.get(f"{API}/structures/{structure_id}/verdicts", params={"limit": 1000}).json()["items"]


def verdicts_of(viewer: httpx.Client, structure_id: int, record_id: int) -> list[dict]:
    return [v for v in verdicts(viewer, structure_id) if v["record_id"] == record_id]


def wait_for(condition: Callable[[], object], timeout: float, what: str) -> object:
    """Poll ``condition`` until it is true (returning its value), failing after ``timeout`` s."""
    deadline = time.monotonic() + timeout
    while time.monotonic() < deadline:
        if value := condition():
            return value
        time.sleep(0.1)
    raise AssertionError(f"{what}: not within {timeout} s")


def jobs_ended(admin: httpx.Client) -> bool:
    """Every job of ``admin``'s organisation has ended (done or failed): none waits or runs."""
    items = admin.get(f"{API}/jobs", params={"limit": 1000}).json()["items"]
    return all(job["state"] in ("done", "failed") for job in items)


def job_ended(client: httpx.Client, accepted: httpx.Response, timeout: float) -> dict:
    """The job a 202 answer queued, followed at its location until it is done or failed."""
    assert accepted.status_code == 202, accepted.text
    location = accepted.json()["location"]
    ended = wait_for(
        lambda: (job := client.get(location).json())["state"] in ("done", "failed") and job,
        timeout,
        "the job",
    )
    return ended  # type: ignore[return-value]


async def time_victim(
    url: str, victim: str, slow: list[asyncio.Task], at_least: float = 0.0
) -> list[tuple[float, int | None]]:
    """``GET /structures`` of another organisation (its key ``victim``), one after another while the
    slow uploads last (and ``at_least`` seconds in all, so that requests refused quickly still leave
    enough timings)."""
    timings: list[tuple[float, int | None]] = []
    headers = {"Authorization": f"Bearer {victim}"}
    until = time.monotonic() + at_least
    async with httpx.AsyncClient(base_url=url, headers=headers, timeout=10) as client:
        await asyncio.sleep(0.5)  # every slow client has sent its headers and its first bytes
        while not all(task.done() for task in slow) or time.monotonic() < until:
            started = time.monotonic()
            try:
                status: int | None = (await client.get(f"{API}/structures")).status_code
            except httpx.TimeoutException:
                status = None
            timings.append((time.monotonic() - started, status))
    return timings


def detail(response: httpx.Response) -> str:
    """The ``detail`` of an error answer as one string (validation errors are a list)."""
    value = response.json()["detail"]
    return value if isinstance(value, str) else json.dumps(value)


# --- organisations --------------------------------------------------------------------------


@dataclass
class Org:
    """An organisation's API keys; clients are opened per use so that no test inherits a
    connection another test's server error left broken."""

    server: LiveServer
    name: str
    keys: dict[str, str]

    @classmethod
    def create(cls, server: LiveServer) -> Org:
        name = f"org-{uuid.uuid4().hex[:12]}"
        return cls(server, name, {role.name: server.key(role, name) for role in Role})

    def client(self, role: str) -> httpx.Client:
        return self.server.client(self.keys[role])


@contextmanager
def clients(org: Org) -> Iterator[tuple[httpx.Client, httpx.Client, httpx.Client]]:
    """(admin, ingest, viewer) clients of ``org``, closed afterwards."""
    opened = tuple(org.client(role) for role in ("admin", "ingest", "viewer"))
    try:
        yield opened  # type: ignore[misc]
    finally:
        for client in opened:
            client.close()


# --- nothing half-written -------------------------------------------------------------------


# What the API lists of a structure and its organisation, as rows: the structures (the fleet's
# listing, with each one's standing), the structure's model versions, verdicts (the summary counts
# them), refinements, schedules, alarm rules and alarms, and the state its standing and alarm rules
# keep. Read in the server's process from its database, not over HTTP: a refusal is checked after
# every refused request, and eight listings over HTTP cost several times the request checked.
LISTED = (
    "model_versions",
    "verdicts",
    "refinements",
    "schedules",
    "alarm_rules",
    "alarms",
    "structure_states",
    "alarm_states",
)


def _state(server: LiveServer, structure_id: int) -> dict[str, list[tuple]]:
    tables = Base.metadata.tables
    structures = tables["structures"]
    with transaction(server.app.state.sessions) as session:
        organisation = select(structures.c.organisation_id).where(structures.c.id == structure_id)
        state = {
            "structures": session.execute(
                select(structures)
                .where(structures.c.organisation_id == organisation.scalar_subquery())
                .order_by(structures.c.id)
            ).all()
        }
        for name in LISTED:
            table = tables[name]
            rows = select(table).where(table.c.structure_id == structure_id)
            state[name] = session.execute(rows.order_by(*table.primary_key.columns)).all()
    return {name: [tuple(row) for row in rows] for name, rows in state.items()}


def sentinel_record(ingest: httpx.Client, structure_id: int) -> int:
    """Store a fresh record and return its id: ids are increasing, so any record stored
    between two sentinels has an id between theirs."""
    response = post_record(ingest, structure_id, json_body(300))
    assert response.status_code == 201, response.text
    return response.json()["id"]


@contextmanager
def nothing_written(org: Org, structure_id: int) -> Iterator[None]:
    """Assert that the requests made inside the block created or changed no structure, model,
    verdict, refinement, schedule or alarm: the rows the API lists are unchanged (``LISTED``), and
    every record id allocated between a sentinel record stored before and one stored after is
    unknown (404)."""
    with org.client("ingest") as ingest:
        first = sentinel_record(ingest, structure_id)
        before = _state(org.server, structure_id)
        yield
        assert _state(org.server, structure_id) == before, "a refused request changed what the API lists"
        last = sentinel_record(ingest, structure_id)
        assert first < last
        assert last - first < 200, "implausibly many record ids allocated by refused requests"
        for record_id in range(first + 1, last):
            response = ingest.post(f"{API}/records/{record_id}/inspect")
            assert response.status_code == 404, f"record {record_id} was stored: {response.text}"
