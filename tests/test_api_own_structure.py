"""Someone else's structure, watched by its baseline alone, as a new user meets it over HTTP: a
3-DOF chain's driving-point accelerometer with 1 % sensor noise on both channels and no fault
experiments, declared as force [N] in and acceleration [m/s²] out, ten healthy records uploaded,
the baseline trained WITHOUT terms (chosen for the structure; the training queued, as the choice's
cost asks at the service's defaults), then new records uploaded with ``inspect=true``.

- The choice is a linear model with x[t] (the accelerometer feels the force at once), orders
  ≤ ``MAX_ORDER``, and the baseline judges records alone.
- 200 further healthy records are flagged within the binomial bounds of the designed rate α
  (two-sided, at ``TEST_LEVEL``), with mean severity 1; at least 90 % of records with an 8 % loss
  of k2 are flagged.
- The structure's summary counts them, and the dashboard's structure page shows its anomalies.
"""

from __future__ import annotations

import re
import uuid
from dataclasses import dataclass

import numpy as np
import pytest
from scipy import stats

from harness.accelerometer import ALPHA, FS, TEST_LEVEL, record, scenario, upload
from harness.api_helpers import API, wait_for
from harness.dashboard_helpers import DASHBOARD, logged_in
from harness.live import LiveServer, Tenant
from models.baseline_choice import MAX_ORDER
from service.security import Role

# Ten healthy records of 2000 samples train the chosen baseline, and records of 1000 are judged:
# from 600-sample training records the rate varies more from one training to the next.
TRAINING, TRAINING_SAMPLES, SAMPLES = 10, 2000, 1000
HEALTHY, FAULTY = 200, 40


@pytest.fixture(scope="module")
def api_server(sqlite_api_server: LiveServer) -> LiveServer:
    return sqlite_api_server


@dataclass
class Watched:
    server: LiveServer
    tenant: Tenant
    structure: dict
    baseline: dict
    healthy: list[dict]
    faulty: list[dict]


def trained_baseline(tenant: Tenant, structure_id: int, record_ids: list[int]) -> dict:
    """The baseline trained from ``record_ids`` without terms: run within the request, or queued
    (202) and followed to its end, as a user would; the active version either way."""
    response = tenant.admin.post(
        f"{API}/structures/{structure_id}/models/baseline", json={"record_ids": record_ids}
    )
    assert response.status_code in (201, 202), response.text
    if response.status_code == 202:
        location = response.json()["location"]
        job = wait_for(
            lambda: (j := tenant.admin.get(location).json())["state"] in ("done", "failed") and j,
            300,
            "the queued training",
        )
        assert job["state"] == "done", job  # type: ignore[index]
    models = tenant.viewer.get(f"{API}/structures/{structure_id}/models").json()
    (baseline,) = [m for m in models if m["kind"] == "baseline" and m["active"]]
    return baseline


@pytest.fixture(scope="module")
def watched(api_server: LiveServer) -> Watched:
    tenant = Tenant.create(api_server)
    declared = {
        "name": f"chain-{uuid.uuid4().hex[:8]}",
        "fs": FS,
        "excitation": {"quantity": "force", "unit": "N"},
        "response": {"quantity": "acceleration", "unit": "m/s²"},
    }
    created = tenant.admin.post(f"{API}/structures", json=declared)
    assert created.status_code == 201, created.text
    structure = created.json()
    training = [record(scenario(), TRAINING_SAMPLES, 100 + i) for i in range(TRAINING)]
    ids = [upload(tenant.ingest, structure["id"], x, y)["id"] for x, y in training]
    baseline = trained_baseline(tenant, structure["id"], ids)

    def judged(fault: str, count: int, seed: int) -> list[dict]:
        signals = [record(scenario(fault, 8.0), SAMPLES, seed + i) for i in range(count)]
        return [upload(tenant.ingest, structure["id"], x, y, inspect="true")["verdict"] for x, y in signals]

    healthy = judged("none", HEALTHY, 10_000)
    faulty = judged("k2", FAULTY, 20_000)
    return Watched(api_server, tenant, structure, baseline, healthy, faulty)


def test_the_baseline_s_terms_are_chosen_for_the_structure_and_it_judges_alone(watched: Watched) -> None:
    baseline = watched.baseline
    choice = baseline["training"]["choice"]
    assert choice["terms"] == baseline["terms"]
    assert choice["delay"] == 0 and "x[t]" in baseline["terms"]
    assert 1 <= choice["orders"]["ny"] <= MAX_ORDER
    novelty = baseline["statistics"]["novelty"]
    assert novelty["judges_records"] is True and novelty["marginal"] is False
    assert watched.structure["response"] == {"quantity": "acceleration", "unit": "m/s²"}


def test_healthy_records_flagged_at_the_designed_rate(watched: Watched) -> None:
    verdicts = watched.healthy
    assert all(v["novelty"] is not None and v["alpha"] == ALPHA for v in verdicts)
    flagged = sum(v["status"] == "anomaly" for v in verdicts)
    low, high = stats.binom.ppf([TEST_LEVEL, 1 - TEST_LEVEL], HEALTHY, ALPHA)
    assert low <= flagged <= high, flagged
    severities = [v["novelty"]["severity"] for v in verdicts]
    assert abs(np.mean(severities) - 1.0) < 3 * np.std(severities) / np.sqrt(HEALTHY) + 0.01


def test_an_8_percent_stiffness_loss_is_flagged(watched: Watched) -> None:
    verdicts = watched.faulty
    assert sum(v["status"] == "anomaly" for v in verdicts) >= 0.9 * FAULTY
    assert np.median([v["novelty"]["severity"] for v in verdicts]) > 1.0


def test_the_summary_and_the_dashboard_show_the_anomalies(watched: Watched) -> None:
    viewer, structure_id = watched.tenant.viewer, watched.structure["id"]
    everything = watched.healthy + watched.faulty
    anomalies = sum(v["status"] == "anomaly" for v in everything)
    summary = viewer.get(f"{API}/structures/{structure_id}/summary").json()
    assert summary["counts"]["anomaly"] == anomalies
    assert summary["counts"]["healthy"] == len(everything) - anomalies
    with logged_in(watched.server, watched.server.key(Role.viewer, watched.tenant.name)) as browser:
        page = browser.get(f"{DASHBOARD}/structures/{structure_id}")
    assert page.status_code == 200, page.text
    standing = re.search(r'id="standing".*?class="badge[^"]*">([^<]+)<', page.text, re.S)
    assert standing and standing.group(1).strip() == summary["latest"]["status"]
