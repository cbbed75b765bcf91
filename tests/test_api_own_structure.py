"""Someone else's structure, watched by its baseline alone, as a new user meets it over HTTP: a
3-DOF chain's driving-point accelerometer with 1 % sensor noise on both channels and no fault
experiments, declared as force [N] in and acceleration [m/s²] out, four healthy records uploaded,
the baseline trained WITHOUT terms (chosen for the structure; the training queued, as the choice's
cost asks at the service's defaults), then new records uploaded with ``inspect=true``.

- The choice is the one ``models.baseline_choice`` makes of the same records, a linear model with
  x[t] (the accelerometer feels the force at once), orders ≤ ``MAX_ORDER``, and the baseline judges
  records alone.
- Each further record, healthy or with an 8 % loss of k2, gets the judgement ``models.novelty``
  makes of it with that baseline. That this baseline holds the designed rate α and finds the loss
  is the models' to show, on the same records: tests/test_novelty.py's
  ``test_a_baseline_whose_terms_are_chosen_for_the_structure_holds_the_rate``.
- The structure's summary counts them, and the dashboard's structure page shows its anomalies.
"""

from __future__ import annotations

import re
import uuid
from dataclasses import dataclass

import pytest

from harness.accelerometer import ALPHA, FS, record, scenario, upload
from harness.api_helpers import API, wait_for
from harness.dashboard_helpers import DASHBOARD, logged_in
from harness.live import LiveServer, Tenant
from models.baseline_choice import MAX_ORDER, BaselineChoice, choose_baseline_terms
from models.narx import fit_narx
from models.novelty import NoveltyVerdict, judge_record, novelty_reference
from models.output_error import fit_output_error
from service.security import Role

# Four healthy records of 2000 samples train the chosen baseline (the choice's cost at the service's
# defaults queues the training), and records of 1000 are judged. Through the API what is tested is
# that the service chooses and judges as the models do; the rate the baseline holds is
# tests/test_novelty.py's, on its own records. The service's choice and jackknife and the test's
# again grow with the records (the jackknife with their square) and would test nothing more.
TRAINING, TRAINING_SAMPLES, SAMPLES = 4, 2000, 1000
HEALTHY, FAULTY = 10, 5  # judged as models.novelty judges them, so a few of each


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
    choice: BaselineChoice  # models.baseline_choice's of the same training records
    local: list[NoveltyVerdict]  # models.novelty's judgement of each record, healthy then faulty


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
    choice = choose_baseline_terms(training)
    model = fit_output_error(fit_narx(training, list(choice.terms)), training, start_from="estimated").model
    reference = novelty_reference(model, training)
    signals = [record(scenario(), SAMPLES, 10_000 + i) for i in range(HEALTHY)]
    signals += [record(scenario("k2", 8.0), SAMPLES, 20_000 + i) for i in range(FAULTY)]
    verdicts = [upload(tenant.ingest, structure["id"], x, y, inspect="true")["verdict"] for x, y in signals]
    local = [judge_record(model, reference, x, y, alpha=ALPHA) for x, y in signals]
    return Watched(
        api_server, tenant, structure, baseline, verdicts[:HEALTHY], verdicts[HEALTHY:], choice, local
    )


def test_the_baseline_s_terms_are_chosen_for_the_structure_and_it_judges_alone(watched: Watched) -> None:
    baseline = watched.baseline
    choice = baseline["training"]["choice"]
    assert choice["terms"] == baseline["terms"] == [term.name for term in watched.choice.terms]
    assert choice["delay"] == 0 and "x[t]" in baseline["terms"]
    assert 1 <= choice["orders"]["ny"] <= MAX_ORDER
    novelty = baseline["statistics"]["novelty"]
    assert novelty["judges_records"] is True and novelty["marginal"] is False
    assert watched.structure["response"] == {"quantity": "acceleration", "unit": "m/s²"}


def test_each_record_gets_the_judgement_of_models_novelty(watched: Watched) -> None:
    for verdict, local in zip(watched.healthy + watched.faulty, watched.local, strict=True):
        assert verdict["status"] == local.status and verdict["alpha"] == ALPHA
        assert verdict["novelty"]["statistic"] == pytest.approx(local.statistic, rel=1e-6)
        assert verdict["novelty"]["severity"] == pytest.approx(local.severity, rel=1e-6)


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
