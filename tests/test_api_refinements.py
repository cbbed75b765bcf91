"""Refinements through HTTP: the missing effect is named, the refined model stored as an inactive
version, every refinement listed, and bad requests leave nothing. The loop's runs are the
service's whatever the database: on SQLite; a refinement stored, listed and read back on
PostgreSQL too (``database_rig``)."""

from __future__ import annotations

from dataclasses import asdict, dataclass, replace

import httpx
import numpy as np
import pytest
from sqlalchemy import select

from harness.api_helpers import (
    API,
    RIG_TERMS,
    Org,
    clients,
    create_structure,
    detail,
    nothing_written,
    npz_bytes,
    post_record,
    train_fault_mode,
)
from harness.dashboard_helpers import logged_in
from harness.live import DATABASES, LiveServer, on_each_database
from harness.warming import warming_drive
from models.amplitude_range import amplitude_ranges
from models.coverage import coverage
from models.effects import candidate_effects, linear_terms
from models.narx import NARX, fit_narx
from models.refinement import MAX_LINEAR_ORDER
from models.terms import Term, max_lag, parse_terms, regressor_matrix
from service.domain import refinements
from service.schemas import RefinementCreate
from service.security import Principal, Role
from service.tables import Organisation
from simulator.simulate import Effects, Scenario, SimulatedRecord, simulate

# The loop's records as long as the command's tests' (tests/test_cli_refine.py): what the API is
# tested for is its wiring, the loop's findings on longer records are the models' tests'.
SAMPLES = 6000
SHORT = 6000  # the records of refinements on several records
UNKNOWN = 10**6
QUADRATIC = ["quadratic_stiffness2=3e5"]


@dataclass
class Rig:
    org: Org
    structure_id: int
    baseline: dict
    k2: dict
    clean_record: int
    effect_record: int
    other_structure_record: int
    # Records of the quadratic spring for refinements on several records: two fitted, two judged.
    fitted: list[int]
    judged: list[int]
    signals: dict[int, tuple[np.ndarray, np.ndarray]]
    other_rate_record: int  # of a structure monitored at 1000 Hz


def simulated(effects: list[str], seed: int, n: int = SAMPLES) -> SimulatedRecord:
    scenario = Scenario(disturbance_std=200.0, effects=Effects.parse(effects))
    return simulate(scenario, n, np.random.SeedSequence(seed))


def upload(ingest: httpx.Client, structure_id: int, effects: list[str], seed: int, n: int = SAMPLES) -> int:
    return upload_record(ingest, structure_id, simulated(effects, seed, n))


def upload_record(
    ingest: httpx.Client, structure_id: int, record: SimulatedRecord, fs: float | None = None
) -> int:
    body = npz_bytes(x=record.x, y=record.y, fs=fs or record.fs)
    response = post_record(ingest, structure_id, body, "application/x-npz")
    assert response.status_code == 201, response.text
    return response.json()["id"]


@pytest.fixture(scope="module")
def api_server(sqlite_api_server: LiveServer) -> LiveServer:
    return sqlite_api_server


def build_rig(api_server: LiveServer) -> Rig:
    org = Org.create(api_server)
    with clients(org) as (admin, ingest, _):
        structure_id = create_structure(admin, "rig")["id"]
        training = upload(ingest, structure_id, [], seed=1)
        response = admin.post(
            f"{API}/structures/{structure_id}/models/baseline",
            json={"record_ids": [training], "terms": RIG_TERMS},
        )
        assert response.status_code == 201, response.text
        baseline = response.json()
        k2 = train_fault_mode(admin, ingest, structure_id, "k2", seed=2)
        other = create_structure(admin, "other")["id"]
        slower = create_structure(admin, "slower", fs=1000.0)["id"]
        short = {seed: simulated(QUADRATIC, seed, SHORT) for seed in (11, 12, 13, 14)}
        ids = {seed: upload_record(ingest, structure_id, record) for seed, record in short.items()}
        return Rig(
            org,
            structure_id,
            baseline,
            k2,
            clean_record=upload(ingest, structure_id, [], seed=3),
            effect_record=upload(ingest, structure_id, QUADRATIC, seed=4),
            other_structure_record=upload(ingest, other, [], seed=5),
            fitted=[ids[11], ids[12]],
            judged=[ids[13], ids[14]],
            signals={ids[seed]: (record.x, record.y) for seed, record in short.items()},
            other_rate_record=upload_record(ingest, slower, simulated([], 6, SHORT), fs=1000.0),
        )


@pytest.fixture(scope="module")
def rig(api_server: LiveServer) -> Rig:
    return build_rig(api_server)


@pytest.fixture(scope="module", params=DATABASES)
def database_rig(request: pytest.FixtureRequest) -> Rig:
    """The rig on each database, for what the database stores and lists."""
    return on_each_database(request, "rig", build_rig)


def refinements_url(structure_id: int) -> str:
    return f"{API}/structures/{structure_id}/refinements"


def test_a_missing_effect_is_named_and_the_refined_model_stored_inactive(database_rig: Rig):
    rig = database_rig
    with clients(rig.org) as (admin, _, viewer):
        body = {"record_id": rig.effect_record, "base_model_id": rig.baseline["id"]}
        response = admin.post(refinements_url(rig.structure_id), json=body)
        assert response.status_code == 201, response.text
        refinement = response.json()
        report = refinement["report"]
        assert report["effects_added"][0]["name"] == "quadratic_stiffness"
        # Each round's choice: the candidates it compared, the fall it saw against the fall needed.
        first = report["rounds"][0]
        assert first["added"] == "quadratic_stiffness" and first["candidates_tried"] >= 1
        assert first["gain"] >= first["threshold"] > 0 and isinstance(first["pruned"], list)
        assert report["after"]["one_step_rms"] <= report["before"]["one_step_rms"] / 2
        assert report["data"]["estimation"] == [0, 4000] and report["data"]["test"] == [4000, SAMPLES]
        # Kept because it simulates the estimation part's last 800 samples, which no choice saw,
        # better than the baseline beyond the comparison's uncertainty.
        held_out = report["held_out"]
        assert held_out["samples"] == 800 and held_out["refined_returned"] and held_out["best_tried"] is None
        assert held_out["refined_free_run_rms"] < held_out["start_free_run_rms"]
        assert report["tests"][0]["verdict"] == "better" and not report["after"]["diverged"]
        assert refinement["base_model"]["id"] == rig.baseline["id"]
        refined = refinement["refined_model"]
        assert refined["name"] == "baseline" and refined["version"] == rig.baseline["version"] + 1

        models = {m["id"]: m for m in viewer.get(f"{API}/structures/{rig.structure_id}/models").json()}
        assert models[refined["id"]]["active"] is False, "a refined model waits to be activated"
        assert models[rig.baseline["id"]]["active"] is True
        assert models[refined["id"]]["terms"] == report["refined"]["terms"]
        assert models[refined["id"]]["training"]["refined_from"] == rig.baseline["id"]

        listed = viewer.get(refinements_url(rig.structure_id)).json()
        assert listed[0] == refinement
        assert viewer.get(f"{API}/refinements/{refinement['id']}").json() == refinement


def test_with_no_base_model_the_loop_chooses_linear_orders_and_stores_their_model(api_server: LiveServer):
    """A structure no baseline describes yet (issue 14, deliverable 5, as ``narxwatch refine``
    without ``--declared``): the loop starts from the linear orders it chooses and reports them;
    the refined model is stored as the structure's first baseline, inactive; the dashboard says
    where the loop started. The record fitted starts before the system settled: where the loop
    leaves out its first samples, the model stored was fitted without them, and its training
    says which, as the report does. (What the loop chooses and adds on such records is
    tests/test_refinement.py's: here, one run of the route end to end.)"""
    org = Org.create(api_server)
    with clients(org) as (admin, ingest, viewer):
        structure_id = create_structure(admin, "drive")["id"]
        warming, settled = (
            post_record(ingest, structure_id, npz_bytes(x=x, y=y), "application/x-npz").json()["id"]
            for x, y in (warming_drive(1500, 1), warming_drive(600, 101, settled=True))
        )
        body = {"record_ids": [warming], "test_record_ids": [settled]}
        response = admin.post(refinements_url(structure_id), json=body)
        assert response.status_code == 201, response.text
        refinement = response.json()
        report = refinement["report"]
        assert refinement["base_model"] is None
        ny, nx, delay = report["orders_chosen"]
        # The start may carry a constant where the output's mean is off zero.
        assert report["declared"]["terms"] in (
            [term.name for term in linear_terms(ny, nx, delay, constant)] for constant in (False, True)
        )
        left_out = report["settled_from"]
        assert len(left_out) == 1 and left_out[0] > 0, left_out
        refined = refinement["refined_model"]
        assert (refined["name"], refined["version"]) == ("baseline", 1)
        (model,) = viewer.get(f"{API}/structures/{structure_id}/models").json()
        assert (model["id"], model["active"], model["terms"]) == (
            refined["id"],
            False,
            report["refined"]["terms"],
        )
        assert model["training"]["refined_from"] is None
        assert model["training"]["orders_chosen"] == [ny, nx, delay]
        assert model["training"]["settled_from"] == left_out
        assert model["statistics"]["n_obs"] == 1500 - left_out[0] - max_lag(parse_terms(model["terms"]))
        assert viewer.get(f"{API}/refinements/{refinement['id']}").json() == refinement
    with logged_in(api_server, org.keys["viewer"]) as client:
        page = client.get(f"/dashboard/refinements/{refinement['id']}")
        structure_page = client.get(f"/dashboard/structures/{structure_id}")
    assert page.status_code == 200
    started = f"from the linear model whose orders the loop chose, ny = {ny}, nx = {nx}, input delay {delay}"
    assert started in page.text and f"to baseline v{refined['version']}" in page.text
    # A row a round, each naming what it added, and where the pruning or the held-out tails took it out.
    assert page.text.count('<tr class="round">') == len(report["rounds"]) > 0
    for step in report["rounds"]:
        said = (
            (step["added"] or "nothing added")
            + (" (pruned whole after the rounds)" if step["pruned_whole"] else "")
            + (" (set aside on the held-out tails)" if step["set_aside"] else "")
        )
        assert f"<td>{said}</td>" in page.text
    assert structure_page.status_code == 200
    assert f"linear ({ny}, {nx}), delay {delay}: orders chosen" in structure_page.text


def test_a_refinement_without_a_base_is_priced_as_the_widest_linear_start(rig: Rig, api_server: LiveServer):
    """The cells bound and the queue see the widest start the loop may choose (ny = nx = 10, delay
    0, with every family offered for it), not a cheaper guess; with a base, its own terms."""
    fitted, judged = [rig.effect_record, rig.clean_record], rig.judged[:1]
    samples = 2 * SAMPLES + SHORT

    def regressors(terms: tuple[Term, ...]) -> int:
        return len(terms) + sum(effect.regressors for effect in candidate_effects(terms))

    with api_server.app.state.sessions() as session:
        organisation = session.scalar(select(Organisation.id).where(Organisation.name == rig.org.name))
        principal = Principal(organisation, Role.admin, key_id=0)
        for base, terms in (
            (None, linear_terms(MAX_LINEAR_ORDER, MAX_LINEAR_ORDER, 0)),
            (rig.baseline["id"], parse_terms(rig.baseline["terms"])),
        ):
            body = RefinementCreate(record_ids=fitted, test_record_ids=judged, base_model_id=base)
            cells = refinements.refinement_cells(
                session, principal, rig.structure_id, body, api_server.app.state.settings
            )
            assert cells == samples * regressors(terms)


def test_a_clean_record_adds_nothing_and_stores_no_model(rig: Rig):
    with clients(rig.org) as (admin, _, viewer):
        before = viewer.get(f"{API}/structures/{rig.structure_id}/models").json()
        body = {"record_id": rig.clean_record, "base_model_id": rig.baseline["id"], "test": [3000, SAMPLES]}
        response = admin.post(refinements_url(rig.structure_id), json=body)
        assert response.status_code == 201, response.text
        refinement = response.json()
        assert refinement["report"]["effects_added"] == [] and refinement["refined_model"] is None
        assert refinement["report"]["before"] == refinement["report"]["after"]
        assert viewer.get(f"{API}/structures/{rig.structure_id}/models").json() == before


def test_estimation_parts_leave_out_a_glitch_between_them(rig: Rig):
    # The effect record's signals (the same seed) with one sample of y at ten times their largest.
    record = simulated(QUADRATIC, seed=4)
    glitched = record.y.copy()
    glitched[2000] = 10 * np.abs(record.y).max()
    parts = [[0, 1990], [2010, 4000]]
    with clients(rig.org) as (admin, ingest, _):
        glitch_id = upload_record(ingest, rig.structure_id, replace(record, y=glitched))
        body = {"record_id": glitch_id, "base_model_id": rig.baseline["id"], "estimation": parts}
        response = admin.post(refinements_url(rig.structure_id), json=body)
        assert response.status_code == 201, response.text
    report = response.json()["report"]
    assert report["data"]["estimation"] == parts and report["data"]["test"] == [4000, SAMPLES]
    # Each part a record of its own: no lag reaches across the gap into the glitch, and the
    # glitch is not named. (That the parts then refine as the record without the glitch is
    # tests/test_refinement_protocol.py's.)
    terms = parse_terms(report["declared"]["terms"])
    apart = fit_narx([(record.x[a:b], record.y[a:b]) for a, b in parts], terms)
    np.testing.assert_allclose(report["declared"]["theta"], apart.theta, rtol=1e-9)
    assert not [note for note in report["notes"] if "glitch" in note]


@pytest.mark.parametrize(
    ("change", "status", "fragment"),
    [
        ({"record_id": UNKNOWN}, 404, f"record {UNKNOWN}"),
        ({"base_model_id": UNKNOWN}, 404, f"model version {UNKNOWN}"),
        ({"base_model_id": "k2"}, 422, "baseline NARX"),
        ({"record_id": "other"}, 422, "another structure"),
        ({"estimation": [0, 10**9]}, 422, "do not lie within"),
        ({"estimation": [[0, 3000], [2000, 4000]]}, 422, "2000:4000 starts before 0:3000 ends"),
        ({"estimation": [[0, 2000], [3000]]}, 422, "estimation"),
        ({"test": [500, 100]}, 422, "do not lie within"),
        ({"estimation": [0, 30]}, 422, "the estimation records have 24 equations (30 samples)"),
        ({"test": [4000, 4004]}, 422, "the test part has 4 samples"),
        ({"alpha": 1.5}, 422, "alpha"),
        ({"initial": -1}, 422, "initial"),
        ({"method": "magic"}, 422, "method"),
    ],
)
def test_bad_refinement_requests_are_refused_and_write_nothing(rig: Rig, change, status, fragment):
    body = {"record_id": rig.effect_record, "base_model_id": rig.baseline["id"], **change}
    if body["base_model_id"] == "k2":
        body["base_model_id"] = rig.k2["id"]
    if body["record_id"] == "other":
        body["record_id"] = rig.other_structure_record
    with nothing_written(rig.org, rig.structure_id), clients(rig.org) as (admin, _, _):
        response = admin.post(refinements_url(rig.structure_id), json=body)
        assert response.status_code == status, response.text
        assert fragment in detail(response)


def test_a_glitch_in_one_of_several_records_is_named_by_the_record(rig: Rig):
    # Two records of 2000 samples fitted: the loop's length is not what is checked.
    record = simulated(QUADRATIC, seed=31, n=2000)
    glitched = replace(record, y=record.y.copy())
    glitched.y[1234] = 10 * np.abs(record.y).max()
    with clients(rig.org) as (admin, ingest, _):
        clean_id = upload(ingest, rig.structure_id, QUADRATIC, seed=32, n=2000)
        glitch_id = upload_record(ingest, rig.structure_id, glitched)
        body = {"record_ids": [clean_id, glitch_id], "test_record_ids": rig.judged[:1]}
        response = admin.post(
            refinements_url(rig.structure_id), json=body | {"base_model_id": rig.baseline["id"]}
        )
        assert response.status_code == 201, response.text
    (note,) = [note for note in response.json()["report"]["notes"] if "as a glitch does" in note]
    assert note.startswith(
        f"y[1234] of record {glitch_id} = {glitched.y[1234]:.4g} lies more than 6 times as far"
    )


def test_several_records_are_fitted_at_once_and_each_test_record_judged_whole(rig: Rig):
    body = {
        "record_ids": rig.fitted,
        "test_record_ids": rig.judged,
        "base_model_id": rig.baseline["id"],
        "transient": 500,
        "initial": 10,
    }
    with clients(rig.org) as (admin, _, viewer):
        response = admin.post(refinements_url(rig.structure_id), json=body)
        assert response.status_code == 201, response.text
        refinement = response.json()
        assert refinement["record_ids"] == rig.fitted and refinement["test_record_ids"] == rig.judged
        assert refinement["record_id"] == rig.fitted[0]
        report = refinement["report"]
        assert report["data"] | {"job": None} == {
            "record_ids": rig.fitted,
            "test_record_ids": rig.judged,
            "transient": 500,
            "initial": 10,
            "alpha": 0.01,
            "job": None,
        }
        # The base model's structure fitted on both records at once, whole (through the
        # transient): least squares on the two, computed here from the simulated signals.
        declared = fit_narx([rig.signals[i] for i in rig.fitted], rig.baseline["terms"])
        np.testing.assert_allclose(report["declared"]["theta"], declared.theta, rtol=1e-9)
        # Each test record judged whole: its free run from its first 10 measured outputs, through
        # the transient, scored after it.
        assert [(t["record_id"], t["samples"]) for t in report["tests"]] == [
            (i, [500, SHORT]) for i in rig.judged
        ]
        for test, record_id in zip(report["tests"], rig.judged, strict=True):
            x, y = rig.signals[record_id]
            start = 10 - declared.max_lag
            run = declared.simulate(x[start:], y[start:])[500 - start :]
            assert test["before"]["free_run_rms"] == pytest.approx(
                np.sqrt(np.mean((run - y[500:]) ** 2)), rel=1e-9
            )
            assert test["after"]["one_step_rms"] <= test["before"]["one_step_rms"] / 2
            # Its scored samples against the records fitted, whole.
            shares = coverage([rig.signals[i] for i in rig.fitted], x[500:], y[500:])
            assert test["coverage"] == asdict(shares) | {
                "extrapolates": shares.extrapolates,
                "description": shares.describe(),
            }
        assert report["effects_added"][0]["name"] == "quadratic_stiffness"
        # The noise model, where the residual needs one, comes after the rounds (models.noise_model).
        decided = ("one-step", "simulation", "whiteness")
        assert all(effect["decided_by"] in decided for effect in report["effects_added"])
        # The spring's part of each step of the refined model's free run on the first test
        # record, started and scored as that record was judged (models.explanation).
        refined = report["refined"]
        model = NARX(
            parse_terms(refined["terms"]), np.array(refined["theta"]), np.zeros((len(refined["theta"]),) * 2)
        )
        x, y = rig.signals[rig.judged[0]]
        start = 10 - model.max_lag
        regressors, _ = regressor_matrix(model.terms, x[start:], model.simulate(x[start:], y[start:]))
        spring = report["effects_added"][0]
        columns = [refined["terms"].index(term) for term in spring["terms"]]
        part = regressors[500 - 10 :, columns] @ model.theta[columns]
        assert report["explanation"]["output_rms"] == pytest.approx(np.sqrt(np.mean(y[500:] ** 2)), rel=1e-12)
        assert spring["contribution"]["share"] == pytest.approx(
            np.sqrt(np.mean(part**2)) / report["explanation"]["output_rms"], rel=1e-9
        )
        assert spring["contribution"]["coefficients"] == [refined["theta"][i] for i in columns]
        # Both models' amplitude ranges over the records fitted, whole (models.amplitude_range).
        base = NARX(parse_terms(report["declared"]["terms"]), declared.theta, declared.covariance)
        ranges = amplitude_ranges(base, model, [rig.signals[i] for i in rig.fitted])
        assert report["amplitude_range"] == ranges.to_dict()
        models = {m["id"]: m for m in viewer.get(f"{API}/structures/{rig.structure_id}/models").json()}
        training = models[refinement["refined_model"]["id"]]["training"]
        assert training["record_ids"] == rig.fitted and training["transient"] == 500
        assert training["estimator"] == report["refined"]["estimator"]
        assert viewer.get(f"{API}/refinements/{refinement['id']}").json() == refinement


@pytest.mark.parametrize(
    ("change", "status", "fragment"),
    [
        ({"record_ids": ["fitted", UNKNOWN]}, 404, f"record {UNKNOWN}"),
        ({"test_record_ids": [UNKNOWN]}, 404, f"record {UNKNOWN}"),
        ({"test_record_ids": ["other"]}, 422, "belongs to another structure"),
        ({"record_ids": ["other rate"]}, 422, "belongs to another structure"),
        ({"test_record_ids": ["fitted"]}, 422, "is listed to fit and to judge"),
        ({"record_ids": ["fitted", "fitted"]}, 422, "is listed 2 times; list each record once"),
        ({"test_record_ids": None}, 422, "give test_record_ids"),
        ({"estimation": [0, 3000]}, 422, "estimation and test parts go with record_id"),
        ({"record_id": "fitted"}, 422, "give record_id (one record"),
        ({"record_ids": None}, 422, "give record_id (one record"),
        ({"transient": SHORT}, 422, f"has {SHORT} samples; a transient of {SHORT} leaves nothing of it"),
        ({"initial": SHORT}, 422, "test record"),
        ({"test_record_ids": []}, 422, "test_record_ids"),
    ],
)
def test_bad_requests_on_several_records_are_refused_and_write_nothing(rig: Rig, change, status, fragment):
    named = {
        "fitted": rig.fitted[0],
        "other": rig.other_structure_record,
        "other rate": rig.other_rate_record,
    }

    def resolve(value):
        if isinstance(value, list):
            return [named.get(item, item) if isinstance(item, str) else item for item in value]
        return named.get(value, value) if isinstance(value, str) else value

    body = {"record_ids": rig.fitted, "test_record_ids": rig.judged, "base_model_id": rig.baseline["id"]}
    body = {
        key: value
        for key, value in (body | {k: resolve(v) for k, v in change.items()}).items()
        if value is not None
    }
    with nothing_written(rig.org, rig.structure_id), clients(rig.org) as (admin, _, _):
        response = admin.post(refinements_url(rig.structure_id), json=body)
        assert response.status_code == status, response.text
        assert fragment in detail(response)
