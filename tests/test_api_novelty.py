"""Baseline-only monitoring over HTTP: a structure that is not the rig (a 3-DOF chain, a
driving-point accelerometer, 1 % sensor noise on both channels, no fault experiments) is watched by
its healthy baseline alone (``models.novelty``), on SQLite; on PostgreSQL, a baseline's figures
and a queued record's judgement by ``narxwatch worker`` processes.

- Trained from a few healthy records, the baseline is fitted by output error and keeps the
  reference of its healthy free-run error; each further record gets a verdict, ``healthy`` or
  ``anomaly``, with the statistic, its threshold, p-value, α and severity, stored and listed as
  any other, and exactly the judgement ``models.novelty`` makes of it.
- Records with an 8 % loss of k2 are anomalies (the rates the judgement holds are
  tests/test_novelty.py's); the structure stands at ``anomaly`` in the fleet and its summary, and
  the persistence rule opens an alarm as for a detected fault.
- A baseline nonlinear in its output is stored, says why it cannot judge records alone, and the
  inspection is refused with that reason; a structure with fault modes keeps the chain's verdict.
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np
import pytest
from scipy import special

from harness.accelerometer import (
    ALPHA,
    FAULTY,
    FS,
    HEALTHY,
    SAMPLES,
    TERMS,
    TRAINING_SAMPLES,
    chain_baseline,
    healthy_training,
    record,
    scenario,
    upload,
)
from harness.api_helpers import (
    API,
    create_structure,
    detail,
    npz_bytes,
    post_record,
    upload_simulated,
    verdicts_of,
    wait_for,
)
from harness.live import LiveServer, Tenant
from models.narx import NARX, fit_narx
from models.novelty import NoveltyReference, judge_record, novelty_reference
from models.output_error import fit_output_error
from models.terms import parse_terms
from simulator.client.destinations import verdict_text
from simulator.simulate import simulate
from simulator.study import StudySettings


@pytest.fixture(scope="module")
def api_server(sqlite_api_server: LiveServer) -> LiveServer:
    """SQLite: what the database adds to a judgement (its figures stored, a queued inspection) is
    tested on PostgreSQL by ``test_on_postgresql_a_queued_record_is_judged_as_models_novelty_judges_it``."""
    return sqlite_api_server


@pytest.fixture(scope="module")
def training() -> list[tuple[np.ndarray, np.ndarray]]:
    return healthy_training()


def local_judge(training: list[tuple[np.ndarray, np.ndarray]]) -> tuple[NARX, NoveltyReference]:
    """The baseline and reference ``models.novelty`` makes of the same records, as the service
    should: least squares, then output error from the estimated start."""
    model = fit_output_error(fit_narx(training, parse_terms(TERMS)), training, start_from="estimated").model
    return model, novelty_reference(model, training)


@pytest.fixture(scope="module")
def judge(training) -> tuple[NARX, NoveltyReference]:
    return local_judge(training)


@dataclass
class Watched:
    tenant: Tenant
    structure_id: int
    baseline: dict
    healthy: list[dict]
    faulty: list[dict]
    local: list


@pytest.fixture(scope="module")
def watched(api_server: LiveServer, training, judge) -> Watched:
    tenant = Tenant.create(api_server)
    structure_id, baseline = chain_baseline(tenant.admin, tenant.ingest, training)
    signals = [record(scenario(), SAMPLES, 10_000 + i) for i in range(HEALTHY)]
    signals += [record(scenario("k2", 8.0), SAMPLES, 20_000 + i) for i in range(FAULTY)]
    verdicts = [upload(tenant.ingest, structure_id, x, y, inspect="true")["verdict"] for x, y in signals]
    local = [judge_record(*judge, x, y, alpha=ALPHA) for x, y in signals]
    return Watched(tenant, structure_id, baseline, verdicts[:HEALTHY], verdicts[HEALTHY:], local)


def test_the_baseline_is_fitted_by_output_error_and_judges_records_alone(watched: Watched, judge) -> None:
    novelty = watched.baseline["statistics"]["novelty"]
    assert novelty["judges_records"] is True
    assert novelty["fit"] == "output error from the estimated start"
    reference = judge[1]
    assert novelty["directions"] == reference.rank
    assert novelty["sigma2"] == pytest.approx(reference.sigma2, rel=1e-6)
    assert watched.baseline["terms"] == TERMS


def test_each_record_gets_the_judgement_of_models_novelty(watched: Watched) -> None:
    for verdict, local in zip(watched.healthy + watched.faulty, watched.local, strict=True):
        figures = verdict["novelty"]
        assert verdict["status"] == local.status
        assert verdict["fault_detected"] == (local.status == "anomaly")
        assert verdict["alpha"] == ALPHA and verdict["lags"] is None and verdict["modes"] == []
        assert (verdict["fault_mode"], verdict["k_hat"], verdict["interval"]) == (None, None, None)
        assert figures["statistic"] == pytest.approx(local.statistic, rel=1e-6)
        assert figures["severity"] == pytest.approx(local.severity, rel=1e-6)
        assert figures["free_run"] == "settled"
        # The figures agree with each other: the threshold is F's (1 − α) quantile, p its tail at T.
        dof, nu = figures["dof"], figures["residual_dof"]
        assert figures["threshold"] == pytest.approx(special.fdtri(dof, nu, 1 - ALPHA), rel=1e-9)
        assert figures["p_value"] == pytest.approx(special.fdtrc(dof, nu, figures["statistic"]), rel=1e-6)
        assert (verdict["status"] == "anomaly") == (figures["statistic"] > figures["threshold"])
        assert [m["name"] for m in verdict["model_versions"]] == ["baseline"]
        assert verdict["model_versions"][0]["id"] == watched.baseline["id"]
        fetched = watched.tenant.viewer.get(f"{API}/verdicts/{verdict['id']}").json()
        assert fetched == verdict


def test_anomalies_reach_the_fleet_the_summary_and_the_alarms(watched: Watched) -> None:
    viewer, structure_id = watched.tenant.viewer, watched.structure_id
    assert all(v["status"] == "anomaly" and v["novelty"]["severity"] > 1.0 for v in watched.faulty)
    summary = viewer.get(f"{API}/structures/{structure_id}/summary").json()
    anomalies = sum(v["status"] == "anomaly" for v in watched.healthy + watched.faulty)
    assert summary["counts"]["anomaly"] == anomalies
    assert summary["counts"]["healthy"] == HEALTHY + FAULTY - anomalies
    assert summary["latest"]["status"] == "anomaly"  # the faulty records were uploaded last
    fleet = viewer.get(f"{API}/structures", params={"status": "anomaly"}).json()
    assert [s["id"] for s in fleet] == [structure_id]
    alarms = viewer.get(f"{API}/alarms", params={"structure_id": structure_id, "limit": 1000}).json()
    assert [a["rule_kind"] for a in alarms["items"]] == ["persistence"]


def test_the_openapi_document_shows_the_anomaly_and_the_baseline_s_figures(watched: Watched) -> None:
    schemas = watched.tenant.viewer.get("/openapi.json").json()["components"]["schemas"]
    verdict = schemas["VerdictOut"]["properties"]
    assert "anomaly" in verdict["status"]["enum"]
    assert {"anyOf": [{"$ref": "#/components/schemas/NoveltyFigures"}, {"type": "null"}]}.items() <= verdict[
        "novelty"
    ].items()
    figures = schemas["NoveltyFigures"]["properties"]
    assert {"statistic", "threshold", "p_value", "severity", "free_run"} <= set(figures)
    assert "healthy" in figures["severity"]["description"]


def test_the_simulator_client_prints_the_baseline_s_figures(watched: Watched) -> None:
    """``narxwatch-sim``'s line for a verdict: the statistic against its threshold and the severity
    where the chain's verdicts show the best mode's whiteness (there is no mode)."""
    verdict = watched.faulty[-1]
    figures = verdict["novelty"]
    line = verdict_text(verdict, verdict["record_id"], "test").plain
    assert f"record {verdict['record_id']}  {verdict['status']}  T = {figures['statistic']:.2f}" in line
    assert f"severity {figures['severity']:.3f}" in line


def test_a_baseline_nonlinear_in_its_output_says_why_it_cannot_judge_records_alone(
    api_server: LiveServer,
) -> None:
    tenant = Tenant.create(api_server)
    structure_id = create_structure(tenant.admin)["id"]
    healthy = simulate(StudySettings().scenario(), 2000, np.random.SeedSequence(5))
    record_id = upload_simulated(tenant.ingest, structure_id, healthy)["id"]
    response = tenant.admin.post(
        f"{API}/structures/{structure_id}/models/baseline", json={"record_ids": [record_id]}
    )
    assert response.status_code == 201, response.text
    novelty = response.json()["statistics"]["novelty"]
    assert novelty["judges_records"] is False and "linear in its output" in novelty["reason"]
    refused = tenant.ingest.post(f"{API}/records/{record_id}/inspect")
    assert refused.status_code == 409, refused.text
    assert "cannot judge records alone" in detail(refused) and "linear in its output" in detail(refused)


def assert_queued_record_judged_as_models_novelty_judges_it(tenant: Tenant, structure_id: int, judge) -> None:
    """``?inspect=queue``: the job stores the judgement ``models.novelty`` makes."""
    x, y = record(scenario(), SAMPLES, 45_000)
    response = post_record(
        tenant.ingest, structure_id, npz_bytes(x=x, y=y, fs=FS), "application/x-npz", inspect="queue"
    )
    assert response.status_code == 202, response.text
    record_id = response.json()["id"]
    queued = wait_for(lambda: verdicts_of(tenant.viewer, structure_id, record_id), 60, "the verdict")
    (verdict,) = queued  # type: ignore[misc]
    assert verdict["novelty"]["statistic"] == pytest.approx(judge_record(*judge, x, y).statistic, rel=1e-6)


def test_a_queued_inspection_judges_as_one_on_upload(watched: Watched, judge) -> None:
    """The embedded worker's judgement."""
    assert_queued_record_judged_as_models_novelty_judges_it(watched.tenant, watched.structure_id, judge)


def test_on_postgresql_a_queued_record_is_judged_as_models_novelty_judges_it(
    postgresql_api_server: LiveServer, training
) -> None:
    """The baseline's figures stored in PostgreSQL, and the judgement of ``narxwatch worker``
    processes (a baseline of two records: what is tested is the storage and the workers)."""
    tenant = Tenant.create(postgresql_api_server)
    structure_id, baseline = chain_baseline(tenant.admin, tenant.ingest, training[:2])
    judge = local_judge(training[:2])
    novelty = baseline["statistics"]["novelty"]
    stored = tenant.viewer.get(f"{API}/structures/{structure_id}/models").json()
    assert [m["statistics"]["novelty"] for m in stored if m["id"] == baseline["id"]] == [novelty]
    assert novelty["judges_records"] is True
    assert novelty["sigma2"] == pytest.approx(judge[1].sigma2, rel=1e-6)
    assert_queued_record_judged_as_models_novelty_judges_it(tenant, structure_id, judge)


@pytest.mark.parametrize("inspect", ["true", "queue"])
def test_a_record_too_short_to_judge_is_refused(watched: Watched, inspect: str) -> None:
    """The free run's initial outputs and ``MIN_SAMPLES`` after them: shorter is a 422 saying so,
    whether the judgement runs on upload or is queued (its job could not judge it)."""
    x, y = record(scenario(), 100, 46_000)
    summary = f"{API}/structures/{watched.structure_id}/summary"
    before = watched.tenant.viewer.get(summary).json()
    body = npz_bytes(x=x, y=y, fs=FS)
    response = post_record(
        watched.tenant.ingest, watched.structure_id, body, "application/x-npz", inspect=inspect
    )
    assert response.status_code == 422, response.text
    assert "100 samples is too short; this needs at least 108" in detail(response)
    assert watched.tenant.viewer.get(summary).json() == before


def test_fault_modes_keep_the_chain_s_verdict(watched: Watched) -> None:
    """With a fault mode trained beside the baseline, a record gets the chain's verdict, not the
    baseline's judgement."""
    admin, ingest, structure_id = watched.tenant.admin, watched.tenant.ingest, watched.structure_id
    magnitudes = (-8.0, 0.0, 8.0)
    signals = [record(scenario("k2", k), TRAINING_SAMPLES, 30_000 + i) for i, k in enumerate(magnitudes)]
    experiments = [
        {"record_id": upload(ingest, structure_id, x, y)["id"], "k": k}
        for (x, y), k in zip(signals, magnitudes, strict=True)
    ]
    body = {"name": "k2", "k_min": -10.0, "k_max": 10.0, "experiments": experiments, "terms": TERMS}
    response = admin.post(f"{API}/structures/{structure_id}/models/fault-modes", json=body)
    assert response.status_code == 201, response.text
    verdict = upload(ingest, structure_id, *record(scenario(), SAMPLES, 40_000), inspect="true")["verdict"]
    assert verdict["novelty"] is None and verdict["status"] in ("healthy", "faulty", "unknown_fault")
    assert [m["name"] for m in verdict["modes"]] == ["k2"] and verdict["lags"] is not None
    assert [m["name"] for m in verdict["model_versions"]] == ["k2"]
