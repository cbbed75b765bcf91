"""Pooled models in the service (issue 16): trained over HTTP from stored records and the
conditions they were stored with, and inspecting each uploaded record at its own conditions.

Against the real app on a real SQLite file. The records come from the simulator's 2-DOF rig
with temperature-dependent stiffness (every spring k(T) = k·(1 − 0.005·(T − 20)), so 15 %
stiffer at −10 °C than at 20 °C), as in tests/test_pooled.py; a refused request leaves nothing
behind (``api_helpers.nothing_written``).
"""

from __future__ import annotations

from dataclasses import dataclass

import pytest
from conftest import DISTURBANCE_STD

from harness import migrated
from harness.api_helpers import (
    API,
    RIG_TERMS,
    Org,
    clients,
    create_structure,
    detail,
    nothing_written,
    post_record,
    stored,
    wait_for,
)
from harness.dashboard_helpers import DASHBOARD, charts, logged_in
from harness.live import LiveServer
from models.narx import fit_narx
from models.pooled import check_baseline
from service.config import Settings
from simulator.simulate import Scenario, SimulatedRecord, simulate
from simulator.theory import EXACT_TERMS

N = 2000
TRAINING_TEMPERATURES = (-10.0, -5.0, 0.0, 5.0, 10.0, 15.0, 20.0, 25.0, 30.0)


def record_at(temperature: float, seed: int, fault: str = "none", k: float = 0.0) -> SimulatedRecord:
    scenario = Scenario(fault=fault, k=k, disturbance_std=DISTURBANCE_STD, temperature=temperature)  # type: ignore[arg-type]
    return simulate(scenario, N, seed=seed)


def body(record: SimulatedRecord, **conditions: float) -> dict:
    stated = [{"name": name, "value": value, "unit": "°C"} for name, value in conditions.items()]
    return {"x": record.x.tolist(), "y": record.y.tolist(), "fs": record.fs, "conditions": stated}


@dataclass
class Bridge:
    org: Org
    structure_id: int
    baseline: dict  # the pooled baseline's version, as the training answered
    at_one_temperature: list[int]  # records all at 20 °C
    without_temperature: int  # a record stored with no conditions


@pytest.fixture(scope="module")
def bridge(sqlite_api_server: LiveServer) -> Bridge:
    org = Org.create(sqlite_api_server)
    with clients(org) as (admin, ingest, _):
        structure_id = create_structure(admin, "bridge")["id"]
        ids = [
            stored(post_record(ingest, structure_id, body(record_at(T, 100 + i), temperature=T)))["id"]
            for i, T in enumerate(TRAINING_TEMPERATURES)
        ]
        response = admin.post(
            f"{API}/structures/{structure_id}/models/pooled-baseline",
            json={"record_ids": ids, "terms": RIG_TERMS},
        )
        assert response.status_code == 201, response.text
        same = [
            stored(post_record(ingest, structure_id, body(record_at(20.0, 200 + i), temperature=20.0)))["id"]
            for i in range(3)
        ]
        bare = stored(post_record(ingest, structure_id, body(record_at(20.0, 210))))["id"]
    return Bridge(org, structure_id, response.json(), same, bare)


def inspected(bridge: Bridge, record: SimulatedRecord, **conditions: float) -> dict:
    with bridge.org.client("ingest") as ingest:
        uploaded = stored(
            post_record(ingest, bridge.structure_id, body(record, **conditions), inspect="true")
        )
    assert uploaded["verdict"] is not None
    return uploaded["verdict"]


def test_training_reports_the_pooled_model(bridge: Bridge) -> None:
    """The version is the active baseline; its training names the variable, its statistics the
    degree BIC chose (the stiffness is linear in T, the NARX coefficients nearly so: 1 or 2),
    the trained range and one BIC row per candidate degree 0 … 2."""
    version = bridge.baseline
    assert (version["kind"], version["name"], version["active"]) == ("baseline", "baseline", True)
    assert version["training"]["variables"] == ["temperature"]
    assert version["terms"] == [term.name for term in EXACT_TERMS]
    statistics = version["statistics"]
    assert statistics["ranges"] == {"temperature": [-10.0, 30.0]}
    assert statistics["degrees"]["temperature"] in (1, 2)
    assert [row["degrees"] for row in statistics["criterion"]] == [[0], [1], [2]]
    best = min(statistics["criterion"], key=lambda row: row["bic"])
    assert best["degrees"] == [statistics["degrees"]["temperature"]]


def test_healthy_record_inside_the_range_is_healthy(bridge: Bridge) -> None:
    """A healthy record at 12.5 °C, between the training temperatures. The check's size is α = 5 %:
    one healthy record in twenty is flagged (that of seed 300 is, F = 1.071 against 1.057); the
    seeds here are fixed, and the false-alarm rate itself is tests/test_pooled.py's to show."""
    verdict = inspected(bridge, record_at(12.5, 301), temperature=12.5)
    assert verdict["status"] == "healthy", verdict
    assert verdict["detected_by"] == [] and verdict["fault_detected"] is False
    assert verdict["model_versions"] == [{"id": bridge.baseline["id"], "name": "baseline", "version": 1}]
    assert verdict["z_critical"] is None and verdict["modes"] == [] and verdict["k_hat"] is None
    assert verdict["conditions"] == [{"name": "temperature", "value": 12.5, "unit": "°C"}]


def test_stored_data_uploaded_again_without_conditions_keeps_its_own(bridge: Bridge) -> None:
    """Conditions do not identify a record, its data do: the same data sent again stating no
    conditions are the stored record, judged at the conditions it was stored with, not refused
    for lacking them."""
    record = record_at(8.0, 320)
    first = inspected(bridge, record, temperature=8.0)
    with bridge.org.client("ingest") as ingest:
        for inspect in ("true", "queue"):
            again = post_record(ingest, bridge.structure_id, body(record), inspect=inspect)
            assert again.status_code == 200, again.text
            answer = again.json()
            assert answer["conditions"] == [{"name": "temperature", "value": 8.0, "unit": "°C"}]
            assert answer["verdict"]["id"] == first["id"]


def test_the_record_page_of_a_baseline_verdict(bridge: Bridge, sqlite_api_server: LiveServer) -> None:
    """The dashboard's record page of a verdict with no fault modes says what judged it rather
    than drawing a fault mode's fit."""
    verdict = inspected(bridge, record_at(17.0, 310), temperature=17.0)
    with logged_in(sqlite_api_server, bridge.org.keys["viewer"]) as viewer:
        page = viewer.get(f"{DASHBOARD}/records/{verdict['record_id']}")
    assert page.status_code == 200, page.text
    assert 'id="baseline-only"' in page.text and 'id="modes"' not in page.text


def test_healthy_where_a_one_temperature_baseline_alarms(bridge: Bridge) -> None:
    """At −8 °C the springs are 14 % stiffer than at 20 °C: a baseline identified at 20 °C (today's
    method, on as many samples as the pooled one) flags the healthy record, the service's pooled
    baseline evaluated at the record's −8 °C does not."""
    warm = record_at(20.0, 400)
    one_temperature = fit_narx([(warm.x, warm.y)], EXACT_TERMS)
    cold = record_at(-8.0, 401)
    assert check_baseline(one_temperature, cold.x, cold.y).fault_detected
    verdict = inspected(bridge, cold, temperature=-8.0)
    assert verdict["status"] == "healthy", verdict


def test_a_fault_is_detected_at_the_records_temperature(bridge: Bridge) -> None:
    """A 10 % loosening of k2 at 5 °C: the pooled baseline's check flags it, and no fault mode
    describes it, so the verdict is an unknown fault without a magnitude."""
    verdict = inspected(bridge, record_at(5.0, 500, "k2", 10.0), temperature=5.0)
    assert verdict["status"] == "unknown_fault" and verdict["fault_detected"] is True, verdict
    assert "variance" in verdict["detected_by"]
    assert verdict["k_hat"] is None and verdict["interval"] is None


@pytest.mark.parametrize(
    ("conditions", "message"),
    [
        (
            {},
            "pooled model 'baseline' needs operating variable 'temperature' (trained over [-10, 30]); "
            "the record carries none",
        ),
        (
            {"speed": 3.0},
            "needs operating variable 'temperature' (trained over [-10, 30]); the record carries speed",
        ),
        ({"temperature": 41.0}, "operating variable 'temperature' = 41 lies outside the range [-10, 30]"),
        ({"temperature": -20.0}, "operating variable 'temperature' = -20 lies outside the range [-10, 30]"),
    ],
)
def test_record_the_model_cannot_judge_is_refused_and_not_kept(bridge: Bridge, conditions, message) -> None:
    record = record_at(conditions.get("temperature", 10.0), 600)
    with nothing_written(bridge.org, bridge.structure_id), bridge.org.client("ingest") as ingest:
        for inspect in ("true", "queue"):
            response = post_record(ingest, bridge.structure_id, body(record, **conditions), inspect=inspect)
            assert response.status_code == 422, response.text
            assert message in detail(response)


def test_pooled_training_at_one_temperature_is_refused(bridge: Bridge) -> None:
    url = f"{API}/structures/{bridge.structure_id}/models/pooled-baseline"
    with nothing_written(bridge.org, bridge.structure_id), bridge.org.client("admin") as admin:
        response = admin.post(url, json={"record_ids": bridge.at_one_temperature})
        assert response.status_code == 422, response.text
        assert detail(response) == (
            "every record of this training has temperature = 20: a pooled model cannot learn how the "
            "dynamics change with it; add records acquired over its range"
        )


def test_pooled_training_on_a_record_without_the_variable_is_refused(bridge: Bridge) -> None:
    url = f"{API}/structures/{bridge.structure_id}/models/pooled-baseline"
    ids = [*bridge.at_one_temperature, bridge.without_temperature]
    with nothing_written(bridge.org, bridge.structure_id), bridge.org.client("admin") as admin:
        response = admin.post(url, json={"record_ids": ids})
        assert response.status_code == 422, response.text
        assert detail(response) == (
            f"record {bridge.without_temperature} carries no operating variable 'temperature' (it carries "
            "none); a pooled training needs it on every record"
        )
        response = admin.post(url, json={"record_ids": ids[:2], "variables": ["wind"]})
        assert response.status_code == 422, response.text
        assert "carries no operating variable 'wind' (it carries temperature)" in detail(response)


def test_pooled_fault_mode_estimates_k_at_the_records_temperature(sqlite_api_server: LiveServer) -> None:
    """A pooled k2 fault mode from nine experiments (−10, 10, 30 °C × k = −8, 0, 8 %), trained over
    HTTP; a record with k2 loosened by 6 % at 0 °C is inspected at 0 °C: k̂ near 6 %, the
    interval holding it. Its version is a fault mode like any other, with its degrees per
    argument reported; the structure's dashboard page draws k̂ against temperature."""
    org = Org.create(sqlite_api_server)
    with clients(org) as (admin, ingest, _):
        structure_id = create_structure(admin, "pooled-k2")["id"]
        cases = [(T, k) for T in (-10.0, 10.0, 30.0) for k in (-8.0, 0.0, 8.0)]
        experiments = [
            {
                "record_id": stored(
                    post_record(ingest, structure_id, body(record_at(T, 700 + i, "k2", k), temperature=T))
                )["id"],
                "k": k,
            }
            for i, (T, k) in enumerate(cases)
        ]
        response = admin.post(
            f"{API}/structures/{structure_id}/models/pooled-fault-modes",
            json={"name": "k2", "experiments": experiments, "max_degree": 1, "terms": RIG_TERMS},
        )
        assert response.status_code == 201, response.text
        version = response.json()
        assert version["kind"] == "fault_mode" and version["training"]["variables"] == ["temperature"]
        assert set(version["statistics"]["degrees"]) == {"temperature", "k"}
        assert version["statistics"]["ranges"] == {"temperature": [-10.0, 30.0], "k": [-8.0, 8.0]}
        record = record_at(0.0, 800, "k2", 6.0)
        uploaded = stored(post_record(ingest, structure_id, body(record, temperature=0.0), inspect="true"))
    verdict = uploaded["verdict"]
    assert verdict["status"] == "faulty" and verdict["fault_mode"] == "k2", verdict
    low, high = verdict["interval"]
    assert low <= 6.0 <= high and abs(verdict["k_hat"] - 6.0) < 1.5, verdict
    assert verdict["z_critical"] is not None
    # The dashboard draws k̂ against the temperature the record states, beside k̂ against time.
    with logged_in(sqlite_api_server, org.keys["viewer"]) as viewer:
        page = viewer.get(f"{DASHBOARD}/structures/{structure_id}")
    assert page.status_code == 200, page.text
    (trace, *_) = charts(page)["k_hat-temperature"]["data"]
    assert (trace["x"], trace["y"]) == ([0.0], [verdict["k_hat"]])
    assert trace["error_y"]["arrayminus"] == [pytest.approx(verdict["k_hat"] - low)]


def test_a_large_pooled_training_is_queued_and_its_job_stores_the_version(tmp_path) -> None:
    """Over the queueing threshold the training answers 202 and the job, run by the embedded
    worker, stores the same kind of version a training in the request would."""
    settings = Settings(database_url=migrated.sqlite(tmp_path / "narxwatch.db"), queue_training_cells=1000)
    with LiveServer(settings) as server:
        org = Org.create(server)
        with clients(org) as (admin, ingest, viewer):
            structure_id = create_structure(admin, "queued")["id"]
            ids = [
                stored(post_record(ingest, structure_id, body(record_at(T, 900 + i), temperature=T)))["id"]
                for i, T in enumerate((-10.0, 0.0, 10.0, 20.0, 30.0))
            ]
            url = f"{API}/structures/{structure_id}/models/pooled-baseline"
            response = admin.post(url, json={"record_ids": ids, "max_degree": 1, "terms": RIG_TERMS})
            assert response.status_code == 202, response.text

            def trained() -> list[dict]:
                return viewer.get(f"{API}/structures/{structure_id}/models").json()

            (version,) = wait_for(trained, 60, "the queued pooled training's version")  # type: ignore[misc]
    assert version["kind"] == "baseline" and version["training"]["variables"] == ["temperature"]
    assert version["training"]["job"] and version["statistics"]["ranges"] == {"temperature": [-10.0, 30.0]}
