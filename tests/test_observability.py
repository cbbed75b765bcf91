"""Metrics, request ids and JSON logs, through HTTP against ``narxwatch serve --workers 2``.

The server runs as a user runs it: two uvicorn worker processes (so the request histogram must be
added up across them), a metrics token, JSON logs on stderr (captured to a file), and a fresh
SQLite file, so that the fleet-wide counts of ``/metrics`` can be held against what the API itself
lists. A last test writes the histogram from two plain processes into one multiprocess folder.
"""

from __future__ import annotations

import json
import os
import shutil
import signal
import subprocess
import sys
import time
import uuid
from collections import Counter
from collections.abc import Iterator
from dataclasses import dataclass
from pathlib import Path

import httpx
import pytest
from prometheus_client.parser import text_string_to_metric_families

from harness.api_helpers import (
    API,
    RIG_TERMS,
    create_structure,
    experiments,
    json_body,
    post_record,
    simulated,
    upload_simulated,
)
from harness.live import free_port, http_client, wait_until_serving
from service.db import make_engine, session_factory, transaction
from service.domain.fleet import STATUSES
from service.observability.metrics import exposition
from service.security import Role, create_key

NARXWATCH = shutil.which("narxwatch", path=str(Path(sys.executable).parent))
TOKEN = "metrics-" + uuid.uuid4().hex
LATENCY = "narxwatch_http_request_duration_seconds"
Labels = frozenset[tuple[str, str]]


@dataclass
class Served:
    url: str
    log: Path
    keys: dict[str, str]  # role -> API key of one organisation

    def client(self, key: str | None = None, **headers: str) -> httpx.Client:
        if key is not None:
            headers["Authorization"] = f"Bearer {key}"
        # A new connection per client: the kernel hands each to either worker process.
        return http_client(base_url=self.url, headers=headers, timeout=60)

    def scrape(self) -> dict[tuple[str, Labels], float]:
        """Every sample of ``/metrics``, as (name, labels) -> value."""
        with self.client(TOKEN) as client:
            response = client.get("/metrics")
        assert response.status_code == 200, response.text
        assert response.headers["content-type"].startswith("text/plain")
        return {
            (sample.name, frozenset(sample.labels.items())): sample.value
            for family in text_string_to_metric_families(response.text)
            for sample in family.samples
        }


@pytest.fixture(scope="module")
def served(tmp_path_factory) -> Iterator[Served]:
    folder = tmp_path_factory.mktemp("observed")
    url = f"sqlite:///{folder / 'narxwatch.db'}"
    env = {
        **os.environ,
        "NARXWATCH_DATABASE_URL": url,
        "NARXWATCH_METRICS_TOKEN": TOKEN,
        "NARXWATCH_LOG_FORMAT": "json",
    }
    env.pop("PROMETHEUS_MULTIPROC_DIR", None)  # serve makes its own
    port = free_port()
    log = folder / "stderr.log"
    with log.open("w") as stderr:
        server = subprocess.Popen(
            [NARXWATCH, "serve", "--port", str(port), "--workers", "2"], env=env, stderr=stderr
        )
    try:
        base = f"http://127.0.0.1:{port}"
        wait_until_serving(base, server, 120, log.read_text)
        engine = make_engine(url)
        with transaction(session_factory(engine)) as session:
            org = f"org-{uuid.uuid4().hex[:12]}"
            keys = {role.name: create_key(session, org, role) for role in Role}
        engine.dispose()
        yield Served(base, log, keys)
    finally:
        server.send_signal(signal.SIGINT)
        server.wait(timeout=30)


TENANT_MODE = "acme-gearbox-k2"


def labelled(samples: dict[tuple[str, Labels], float], name: str) -> dict[Labels, float]:
    return {labels: value for (sample, labels), value in samples.items() if sample == name}


def value(samples: dict[tuple[str, Labels], float], name: str, **labels: str) -> float:
    return samples[name, frozenset(labels.items())]


def test_business_metrics_equal_what_the_api_lists(served: Served):
    with served.client(served.keys["admin"]) as admin, served.client(served.keys["ingest"]) as ingest:
        sid = create_structure(admin)["id"]
        training = experiments(ingest, sid, "k2", seed=71)
        response = admin.post(
            f"{API}/structures/{sid}/models/fault-modes",
            json={
                "name": TENANT_MODE,
                "k_min": -32.0,
                "k_max": 32.0,
                "experiments": training,
                "terms": RIG_TERMS,
            },
        )
        assert response.status_code == 201, response.text
        records = {experiment["record_id"] for experiment in training}
        for index, (fault, k) in enumerate([("none", 0.0), ("none", 0.0), ("k2", 20.0), ("k2", -20.0)]):
            record = simulated(fault, k, [71, 10 + index])
            records.add(upload_simulated(ingest, sid, record, inspect="true")["id"])
        unexplained = post_record(ingest, sid, json_body(2000, seed=71), inspect="true")  # unknown_fault
        stored_only = post_record(ingest, sid, json_body(300, seed=72))
        again = post_record(ingest, sid, json_body(300, seed=72))  # the same data: the same record
        queued = post_record(ingest, sid, json_body(2000, seed=73), inspect="queue")
        assert [r.status_code for r in (unexplained, stored_only, again, queued)] == [201, 201, 200, 202]
        assert again.json()["id"] == stored_only.json()["id"]
        records |= {r.json()["id"] for r in (unexplained, stored_only, queued)}

        def listed() -> list[dict]:
            response = admin.get(f"{API}/structures/{sid}/verdicts", params={"limit": 1000})
            assert response.status_code == 200, response.text
            return response.json()["items"]

        deadline = time.monotonic() + 60
        while len(listed()) < 6:  # five inspected at once, one by the job queue
            assert time.monotonic() < deadline, "the queued inspection did not run"
            time.sleep(0.2)
        verdicts = Counter(v["status"] for v in listed())
        assert TENANT_MODE in {v["fault_mode"] for v in listed()}

    samples = served.scrape()
    assert value(samples, "narxwatch_records_received_total") == len(records) == 10
    counted = {
        dict(labels)["status"]: count
        for labels, count in labelled(samples, "narxwatch_verdicts_total").items()
    }
    # Every status has its series, a status no verdict has yet at zero.
    assert counted == {status: verdicts[status] for status in STATUSES}
    assert sum(verdicts.values()) == 6
    assert {"faulty", "unknown_fault"} <= set(counted)
    # A fault mode's name is the tenant's to choose: it is no label value (unbounded, and it tells
    # whoever reads the metrics what an organisation monitors).
    assert not any(TENANT_MODE in value for _, labels in samples for _, value in labels)
    assert value(samples, "narxwatch_jobs", state="done") == 1
    assert (
        value(samples, "narxwatch_jobs", state="queued")
        == value(samples, "narxwatch_jobs", state="running")
        == 0
    )
    assert value(samples, "narxwatch_job_latency_seconds_count") == 1
    latency = value(samples, "narxwatch_job_latency_seconds_sum")
    assert 0 < latency < 60
    assert value(samples, "narxwatch_job_latency_seconds", quantile="0.5") == latency
    assert value(samples, "narxwatch_job_latency_window_seconds") == 300


def test_request_latency_is_labelled_by_route_template(served: Served):
    """Twelve 404s for ids of nothing and a path of no route, spread over both workers by their
    connections: every scrape, whichever worker answers it, counts them all, under templates."""
    missing = [10**6 + n for n in range(12)]
    for structure_id in missing:
        with served.client(served.keys["viewer"]) as client:
            assert client.get(f"{API}/structures/{structure_id}").status_code == 404
    with served.client() as client:
        assert client.get(f"/no/such/path/{missing[0]}").status_code == 404
        templates = set(client.get("/openapi.json").json()["paths"])
    for _ in range(3):
        samples = served.scrape()
        counts = labelled(samples, f"{LATENCY}_count")
        assert (
            value(
                samples,
                f"{LATENCY}_count",
                method="GET",
                route=f"{API}/structures/{{structure_id}}",
                status="404",
            )
            == 12
        )
        assert value(samples, f"{LATENCY}_count", method="GET", route="other", status="404") == 1
        routes = {dict(labels)["route"] for labels in counts}
        assert f"{API}/structures/{{structure_id}}" in routes
        assert routes <= templates | {"/openapi.json", "other"}
        assert not any(str(structure_id) in route for route in routes for structure_id in missing)


def test_metrics_need_the_token(served: Served):
    for headers in (
        {},
        {"Authorization": "Bearer wrong"},
        {"Authorization": f"Bearer {TOKEN}x"},
        {"Authorization": f"Bearer {served.keys['admin']}"},  # an API key is not the metrics token
        {"Authorization": f"Basic {TOKEN}"},
    ):
        with served.client(**headers) as client:
            response = client.get("/metrics")
        assert response.status_code == 401, (headers, response.text)
        assert response.headers["www-authenticate"] == "Bearer"
        assert "narxwatch_" not in response.text
    assert served.scrape()  # with it


def log_lines(served: Served) -> list[dict]:
    """The server's stderr so far, every line a JSON object."""
    return [json.loads(line) for line in served.log.read_text().splitlines() if line.strip()]


def test_logs_are_json_lines_with_the_request_id_and_never_a_key(served: Served):
    viewer = served.keys["viewer"]
    prefix, secret = viewer.split("_")[1], viewer.split("_", 2)[2]
    bogus = f"nw_{prefix}_{uuid.uuid4().hex}"  # a real key's prefix with a wrong secret
    marker = uuid.uuid4().hex  # in a query string, which no line may carry either
    with served.client(viewer, **{"X-Request-ID": "test-123"}) as client:
        response = client.get(f"{API}/structures", params={"probe": marker})
    assert response.status_code == 200 and response.headers["x-request-id"] == "test-123"
    with served.client(bogus, **{"X-Request-ID": "test-456"}) as client:
        refused = client.get(f"{API}/structures")
    assert refused.status_code == 401 and refused.headers["x-request-id"] == "test-456"
    with served.client(**{"X-Request-ID": 'forged" "request_id": "x'}) as client:
        replaced = client.get("/healthz").headers["x-request-id"]
    assert replaced != 'forged" "request_id": "x' and len(replaced) == 32

    lines = log_lines(served)
    for line in lines:
        assert {"timestamp", "level", "logger", "message", "request_id"} <= set(line), line
    assert any(line["logger"] == "uvicorn.error" for line in lines)  # uvicorn's own lines, as JSON
    (ok,) = [line for line in lines if line["request_id"] == "test-123"]
    assert ok["logger"] == "narxwatch.access"
    assert (ok["method"], ok["route"], ok["status"]) == ("GET", f"{API}/structures", 200)
    assert ok["duration_ms"] >= 0
    denied = [line for line in lines if line["request_id"] == "test-456"]
    assert sorted((line["logger"], line["level"]) for line in denied) == [
        ("narxwatch.access", "INFO"),
        ("narxwatch.auth", "WARNING"),  # logged in the thread pool, still with its request's id
    ]
    assert any(line["request_id"] == replaced for line in lines)

    text = served.log.read_text()
    for secret_text in (viewer, secret, prefix, bogus, bogus.split("_", 2)[2], TOKEN, marker):
        assert secret_text not in text


WRITER = """
import sys
from service.observability.metrics import REQUEST_SECONDS
for _ in range(int(sys.argv[1])):
    REQUEST_SECONDS.labels("GET", "/healthz", "200").observe(0.02)
"""


def test_multiprocess_mode_adds_up_every_process(tmp_path: Path, monkeypatch: pytest.MonkeyPatch):
    """Two processes write the request histogram into one PROMETHEUS_MULTIPROC_DIR; a scrape
    from a third sees both."""
    env = {**os.environ, "PROMETHEUS_MULTIPROC_DIR": str(tmp_path)}
    writers = [subprocess.Popen([sys.executable, "-c", WRITER, str(n)], env=env) for n in (3, 4)]
    assert [writer.wait(timeout=60) for writer in writers] == [0, 0]
    assert len(list(tmp_path.glob("histogram_*.db"))) == 2

    monkeypatch.setenv("PROMETHEUS_MULTIPROC_DIR", str(tmp_path))
    families = {f.name: f for f in text_string_to_metric_families(exposition().decode())}
    samples = {(sample.name, sample.labels.get("le")): sample.value for sample in families[LATENCY].samples}
    assert samples[f"{LATENCY}_count", None] == 7
    assert samples[f"{LATENCY}_sum", None] == pytest.approx(0.14)
    assert samples[f"{LATENCY}_bucket", "0.01"] == 0
    assert samples[f"{LATENCY}_bucket", "0.025"] == 7
