"""Fault modes under sensor noise over HTTP: the accelerometer chain (1 % noise on the measured
force and response) has a k2 fault mode trained with ``"noise": "sensor"``, which the service fits
for its free run (``models.free_run_inspection``) and inspects records with by that chain.

- The training stores a free-run mode (its fit's healthy error level and the modes fitted with
  it), its terms the baseline's.
- A record of k2 loosened is ``faulty``, localised to k2 with an interval around the loosening; a
  healthy record is ``healthy``, also when its inspection is queued; no Ljung–Box test is made.
- The dashboard's record page shows the verdict without a one-step fit.
- A record whose free-run inspection costs more cells than a request runs is refused with
  inspect=true (stored by nothing) and sent to inspect=queue.
- A second sensor-noise mode refits the first with it (one healthy model; the training queued by
  its cost), and the loosened k2 is told from k3; modes not fitted together (an older version
  activated) are refused at inspection (409).
- Active modes of both noise kinds are refused at inspection (409, saying what to do); a bad
  ``noise`` (422) or a sensor-noise training the free-run fit cannot give (422) writes nothing.
"""

from __future__ import annotations

from dataclasses import dataclass

import pytest

from harness.accelerometer import ALPHA, FS, record, scenario, upload
from harness.api_helpers import (
    API,
    create_structure,
    detail,
    job_ended,
    npz_bytes,
    post_record,
    verdicts_of,
    wait_for,
)
from harness.dashboard_helpers import DASHBOARD, logged_in
from harness.live import LiveServer, Tenant
from harness.noisy_modes import MAGNITUDES, TERMS
from service.config import Settings
from service.security import Role

# Shorter experiments than harness/noisy_modes.py's: the training then costs less than
# NARXWATCH_QUEUE_TRAINING_CELLS and answers at once (the fit's time grows with them).
EXPERIMENT_SAMPLES, SAMPLES = 5000, 4000
LOOSENED = 10.0  # percent, inside the trained range


@dataclass
class Trained:
    tenant: Tenant
    structure_id: int
    baseline: dict
    mode: dict
    faulty: dict
    healthy: dict
    queued: dict


def upload_chain(
    tenant: Tenant, structure_id: int, fault: str, k: float, n: int, seed: int, **params
) -> dict:
    return upload(tenant.ingest, structure_id, *record(scenario(fault, k), n, seed), **params)


def sensor_mode_body(tenant: Tenant, structure_id: int, spring: str) -> dict:
    """A training body of ``spring``'s sensor-noise mode, its experiments uploaded."""
    seed = 30_000 + 100 * int(spring[1:])
    uploaded = [
        upload_chain(tenant, structure_id, spring, k, EXPERIMENT_SAMPLES, seed + i)
        for i, k in enumerate(MAGNITUDES)
    ]
    experiments = [{"record_id": r["id"], "k": k} for r, k in zip(uploaded, MAGNITUDES, strict=True)]
    body = {"name": spring, "k_min": MAGNITUDES[0], "k_max": MAGNITUDES[-1], "experiments": experiments}
    return body | {"noise": "sensor"}


@pytest.fixture(scope="module")
def trained(sqlite_api_server: LiveServer) -> Trained:
    tenant = Tenant.create(sqlite_api_server)
    structure_id = create_structure(tenant.admin, fs=FS)["id"]
    healthy_ids = [
        upload_chain(tenant, structure_id, "none", 0.0, SAMPLES, 40_000 + i)["id"] for i in range(2)
    ]
    models = f"{API}/structures/{structure_id}/models"
    baseline = tenant.admin.post(f"{models}/baseline", json={"record_ids": healthy_ids, "terms": TERMS})
    assert baseline.status_code == 201, baseline.text
    mode = tenant.admin.post(f"{models}/fault-modes", json=sensor_mode_body(tenant, structure_id, "k2"))
    assert mode.status_code == 201, mode.text
    faulty = upload_chain(tenant, structure_id, "k2", LOOSENED, SAMPLES, 50_000, inspect="true")
    healthy = upload_chain(tenant, structure_id, "none", 0.0, SAMPLES, 60_000, inspect="true")
    x, y = record(scenario(), SAMPLES, 70_000)
    response = post_record(
        tenant.ingest, structure_id, npz_bytes(x=x, y=y, fs=FS), "application/x-npz", inspect="queue"
    )
    assert response.status_code == 202, response.text
    queued = response.json()
    found = wait_for(
        lambda: verdicts_of(tenant.viewer, structure_id, queued["id"]), 60, "the queued inspection's verdict"
    )
    return Trained(tenant, structure_id, baseline.json(), mode.json(), faulty, healthy, found[0])  # type: ignore[index]


def test_a_sensor_noise_training_stores_a_free_run_mode(trained: Trained) -> None:
    mode = trained.mode
    assert mode["kind"] == "fault_mode" and mode["active"]
    assert mode["training"]["noise"] == "sensor"
    assert mode["training"]["fitted_with"] == ["k2"]
    assert mode["terms"] == TERMS and mode["training"]["terms_from"]["model_id"] == trained.baseline["id"]
    # The free-run fit's healthy error level and its degrees of freedom, which the paper's fit has not.
    assert mode["statistics"]["sigma2"] > 0 and mode["statistics"]["dof"] > 0
    assert mode["statistics"]["scale"] >= 1
    assert len(mode["statistics"]["experiment_sigma2"]) == len(MAGNITUDES)


def test_a_loosened_spring_is_localised_and_sized_by_the_free_run_chain(trained: Trained) -> None:
    verdict = trained.faulty["verdict"]
    assert verdict["status"] == "faulty" and verdict["fault_mode"] == "k2"
    low, high = verdict["interval"]
    assert low <= verdict["k_hat"] <= high
    # k̂ within four of its standard errors of the truth: a right chain misses by more 1 time in 15 000.
    assert abs(verdict["k_hat"] - LOOSENED) < 4 * verdict["sigma_k"]
    # The free-run chain's verdict: no Ljung–Box test; the adequacy test is an F test.
    assert verdict["lags"] is None and verdict["alpha"] == ALPHA
    (k2,) = verdict["modes"]
    assert k2["accepted"] and k2["q"] <= k2["q_critical"]
    assert [m["id"] for m in verdict["model_versions"]] == [trained.mode["id"]]
    fetched = trained.tenant.viewer.get(f"{API}/verdicts/{verdict['id']}").json()
    assert fetched == verdict


def test_the_dashboard_shows_a_free_run_verdict(trained: Trained, sqlite_api_server: LiveServer) -> None:
    """Its record page names the mode and its interval; no one-step fit is drawn (none was made)."""
    key = sqlite_api_server.key(Role.viewer, trained.tenant.name)
    with logged_in(sqlite_api_server, key) as client:
        page = client.get(f"{DASHBOARD}/records/{trained.faulty['id']}")
    assert page.status_code == 200, page.text
    assert 'id="free-run-note"' in page.text and 'id="chart-response"' not in page.text


def test_healthy_records_are_healthy_inspected_at_once_or_queued(trained: Trained) -> None:
    for verdict in (trained.healthy["verdict"], trained.queued):
        assert verdict["status"] == "healthy" and not verdict["fault_detected"]
        assert verdict["lags"] is None and verdict["fault_mode"] is None
        assert [m["id"] for m in verdict["model_versions"]] == [trained.mode["id"]]


def test_a_bad_noise_or_a_training_the_free_run_fit_cannot_give_is_refused(trained: Trained) -> None:
    tenant, structure_id = trained.tenant, trained.structure_id
    url = f"{API}/structures/{structure_id}/models/fault-modes"
    body = trained.mode["training"]
    given = {"name": "k2", "k_min": body["k_min"], "k_max": body["k_max"], "experiments": body["experiments"]}
    refusals = [
        (given | {"noise": "wind"}, "noise"),
        (given | {"noise": "sensor", "degree": 2}, "linear in k"),
        (given | {"noise": "sensor", "k_max": 30.0}, "give k_min 0 and k_max 15"),
        (given | {"noise": "sensor", "experiments": body["experiments"][:2]}, "three magnitudes"),
    ]
    versions = f"{API}/structures/{structure_id}/models"
    before = tenant.viewer.get(versions).json()
    for refused, why in refusals:
        response = tenant.admin.post(url, json=refused)
        assert response.status_code == 422, response.text
        assert why in detail(response)
    assert tenant.viewer.get(versions).json() == before


def test_a_record_too_long_to_inspect_by_free_run_within_a_request_is_sent_to_the_queue(
    trained: Trained,
) -> None:
    """The free-run chain costs samples × the modes' coefficients cells: over
    NARXWATCH_QUEUE_TRAINING_CELLS an upload that asks for the verdict at once is refused, storing
    nothing, and so is inspecting such a stored record; storing it alone is not refused."""
    tenant, structure_id = trained.tenant, trained.structure_id
    coefficients = 2 * len(TERMS)  # one mode, degree 1
    n = Settings.model_fields["queue_training_cells"].default // coefficients + 1000
    x, y = record(scenario(), n, 90_000)
    body = npz_bytes(x=x, y=y, fs=FS)
    refused = post_record(tenant.ingest, structure_id, body, "application/x-npz", inspect="true")
    assert refused.status_code == 422, refused.text
    assert f"would cost {n * coefficients} cells" in detail(refused) and "inspect=queue" in detail(refused)
    stored = upload(tenant.ingest, structure_id, x, y)
    assert stored["created"], "the refused upload stored the record"
    inspected = tenant.ingest.post(f"{API}/records/{stored['id']}/inspect")
    assert inspected.status_code == 422, inspected.text
    assert "inspect=queue" in detail(inspected)


def test_a_second_sensor_noise_mode_is_fitted_jointly_with_the_first(trained: Trained) -> None:
    """Training k3 refits k2 with it around one healthy model: a new version of each, k2's
    training as it was. Both modes' experiments and a jackknife refit for each cost more than
    NARXWATCH_QUEUE_TRAINING_CELLS: the training is queued. The loosened k2 is then told from k3."""
    tenant, structure_id = trained.tenant, trained.structure_id
    body = sensor_mode_body(tenant, structure_id, "k3")
    response = tenant.admin.post(f"{API}/structures/{structure_id}/models/fault-modes", json=body)
    ended = job_ended(tenant.admin, response, 120)
    assert ended["state"] == "done", ended
    listed = tenant.viewer.get(f"{API}/structures/{structure_id}/models").json()
    active = {m["name"]: m for m in listed if m["active"] and m["kind"] == "fault_mode"}
    assert active["k2"]["version"] == trained.mode["version"] + 1
    assert active["k2"]["training"] == trained.mode["training"] | {"fitted_with": ["k2", "k3"]}
    assert active["k3"]["training"]["fitted_with"] == ["k2", "k3"]
    verdict = tenant.ingest.post(f"{API}/records/{trained.faulty['id']}/inspect").json()
    assert verdict["status"] == "faulty" and verdict["fault_mode"] == "k2"
    assert sorted(m["id"] for m in verdict["model_versions"]) == sorted(m["id"] for m in active.values())
    assert [m["name"] for m in verdict["modes"]] == ["k2", "k3"]
    # k2's first version, fitted alone, beside k3 fitted with its second: refused until refitted.
    activated = tenant.admin.post(f"{API}/structures/{structure_id}/models/{trained.mode['id']}/activate")
    assert activated.status_code == 200, activated.text
    refused = tenant.ingest.post(f"{API}/records/{trained.healthy['id']}/inspect")
    assert refused.status_code == 409, refused.text
    assert "not fitted together" in detail(refused)


def test_active_modes_of_both_noise_kinds_are_refused_at_inspection(trained: Trained) -> None:
    """Last: it leaves the structure with a process-noise mode beside the sensor-noise one."""
    tenant, structure_id = trained.tenant, trained.structure_id
    experiments = [
        {"record_id": upload_chain(tenant, structure_id, "k3", k, SAMPLES, 80_000 + i)["id"], "k": k}
        for i, k in enumerate((0.0, 15.0))
    ]
    body = {"name": "k3", "k_min": 0.0, "k_max": 15.0, "experiments": experiments}
    response = tenant.admin.post(f"{API}/structures/{structure_id}/models/fault-modes", json=body)
    assert response.status_code == 201, response.text
    assert response.json()["training"]["noise"] == "process"
    inspected = tenant.ingest.post(f"{API}/records/{trained.healthy['id']}/inspect")
    assert inspected.status_code == 409, inspected.text
    message = detail(inspected)
    assert "k2 trained with noise 'sensor'" in message and "k3 with noise 'process'" in message
    assert 'train k3 again with "noise": "sensor"' in message
