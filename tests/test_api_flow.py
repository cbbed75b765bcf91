"""Upload → verdict → history through HTTP, on SQLite and on PostgreSQL.

A structure is trained through the API from simulated experiments; the paper's four cases are
then uploaded with ``inspect=true`` and must get the statuses the paper gives them (SPEC §6).
"""

from __future__ import annotations

import io
from dataclasses import dataclass

import numpy as np
import pytest

from harness.api_helpers import RIG_TERMS
from harness.live import LiveServer, Tenant
from recordfiles.writer import dump_csv
from simulator.simulate import simulate
from simulator.study import StudySettings

SETTINGS = StudySettings()
MAGNITUDES = [float(k) for k in range(-32, 33, 8)]
CASES = [
    ("I", "none", 0.0, "healthy", None),
    ("II", "k2", 3.0, "faulty", "k2"),
    ("III", "k2", 29.0, "faulty", "k2"),
    ("IV", "k1", 30.0, "faulty", "k1"),
]


@dataclass
class Trained:
    tenant: Tenant
    structure_id: int
    models: dict[str, dict]


def upload_json(client, structure_id: int, record, **params):
    body = {"x": record.x.tolist(), "y": record.y.tolist(), "fs": record.fs}
    return client.post(f"/api/v1/structures/{structure_id}/records", json=body, params=params)


def upload_npz(client, structure_id: int, record, **params):
    buffer = io.BytesIO()
    np.savez(buffer, x=record.x, y=record.y, fs=record.fs)
    return client.post(
        f"/api/v1/structures/{structure_id}/records",
        content=buffer.getvalue(),
        headers={"Content-Type": "application/x-npz"},
        params=params,
    )


@pytest.fixture(scope="module")
def trained(api_server: LiveServer) -> Trained:
    tenant = Tenant.create(api_server)
    response = tenant.admin.post("/api/v1/structures", json={"name": "rig", "fs": 1500.0})
    assert response.status_code == 201, response.text
    structure_id = response.json()["id"]
    seeds = iter(np.random.SeedSequence(7).spawn(100))
    healthy = simulate(SETTINGS.scenario(), 10_000, next(seeds))
    record_id = upload_npz(tenant.ingest, structure_id, healthy).json()["id"]
    models = {}
    response = tenant.admin.post(
        f"/api/v1/structures/{structure_id}/models/baseline",
        json={"record_ids": [record_id], "terms": RIG_TERMS},
    )
    assert response.status_code == 201, response.text
    models["baseline"] = response.json()
    for mode in ("k2", "k1"):
        experiments = []
        for k in MAGNITUDES:
            run = simulate(SETTINGS.scenario(mode, k), 2000, next(seeds))
            experiments.append(
                {"record_id": upload_npz(tenant.ingest, structure_id, run).json()["id"], "k": k}
            )
        response = tenant.admin.post(
            f"/api/v1/structures/{structure_id}/models/fault-modes",
            json={"name": mode, "k_min": -32.0, "k_max": 32.0, "experiments": experiments},
        )
        assert response.status_code == 201, response.text
        models[mode] = response.json()
    return Trained(tenant, structure_id, models)


def test_trained_models_are_listed_active_with_versions(trained: Trained):
    listed = trained.tenant.viewer.get(f"/api/v1/structures/{trained.structure_id}/models").json()
    assert {(m["name"], m["version"], m["active"]) for m in listed} == {
        ("baseline", 1, True),
        ("k1", 1, True),
        ("k2", 1, True),
    }
    k2 = next(m for m in listed if m["name"] == "k2")
    assert k2["kind"] == "fault_mode" and len(k2["terms"]) == 8
    assert k2["training"]["k_min"] == -32.0 and len(k2["training"]["experiments"]) == len(MAGNITUDES)


@pytest.mark.parametrize(("case", "fault", "k", "status", "mode"), CASES, ids=[c[0] for c in CASES])
def test_paper_cases_get_their_statuses(trained: Trained, case, fault, k, status, mode):
    record = simulate(SETTINGS.scenario(fault, k), 2000, np.random.SeedSequence([11, ord(case[-1])]))
    response = upload_json(trained.tenant.ingest, trained.structure_id, record, inspect="true")
    assert response.status_code == 201, response.text
    verdict = response.json()["verdict"]
    assert verdict["status"] == status
    assert verdict["fault_mode"] == mode
    assert [m["name"] for m in verdict["modes"]] == ["k1", "k2"]
    assert {m["name"] for m in verdict["model_versions"]} == {"k1", "k2"}
    if mode is not None:
        low, high = verdict["interval"]
        # Within 5 interval half-widths of the truth: generous, since the models are estimated.
        assert abs(verdict["k_hat"] - k) < 5 * (high - low) / 2
    fetched = trained.tenant.viewer.get(f"/api/v1/verdicts/{verdict['id']}").json()
    assert fetched == verdict


def test_reupload_returns_the_same_record_and_verdict(trained: Trained):
    record = simulate(SETTINGS.scenario("k2", 10.0), 2000, 404)
    first = upload_json(trained.tenant.ingest, trained.structure_id, record, inspect="true")
    again = upload_json(trained.tenant.ingest, trained.structure_id, record, inspect="true")
    assert (first.status_code, again.status_code) == (201, 200)
    assert first.json()["id"] == again.json()["id"] and again.json()["created"] is False
    assert first.json()["verdict"]["id"] == again.json()["verdict"]["id"]
    inspected = trained.tenant.ingest.post(f"/api/v1/records/{first.json()['id']}/inspect")
    assert inspected.status_code == 200 and inspected.json()["id"] == first.json()["verdict"]["id"]


def test_csv_upload_with_acquisition_time(trained: Trained):
    record = simulate(SETTINGS.scenario(), 2000, 505)
    response = trained.tenant.ingest.post(
        f"/api/v1/structures/{trained.structure_id}/records",
        content=dump_csv(record.x, record.y, record.fs),
        headers={"Content-Type": "text/csv"},
        params={"acquired_at": "2026-01-02T03:04:05Z", "inspect": "true"},
    )
    assert response.status_code == 201, response.text
    assert response.json()["acquired_at"].startswith("2026-01-02T03:04:05")
    assert response.json()["n_samples"] == 2000
