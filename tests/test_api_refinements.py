"""Refinements through HTTP on SQLite and PostgreSQL: the missing effect is named, the refined
model stored as an inactive version, every refinement listed, and bad requests leave nothing."""

from __future__ import annotations

from dataclasses import dataclass

import httpx
import numpy as np
import pytest
from api_helpers import (
    API,
    Org,
    clients,
    create_structure,
    detail,
    nothing_written,
    npz_bytes,
    post_record,
    train_fault_mode,
)
from live import LiveServer

from simulator.simulate import Effects, Scenario, simulate

SAMPLES = 12_000
UNKNOWN = 10**6


@dataclass
class Rig:
    org: Org
    structure_id: int
    baseline: dict
    k2: dict
    clean_record: int
    effect_record: int
    other_structure_record: int


def upload(ingest: httpx.Client, structure_id: int, effects: list[str], seed: int) -> int:
    scenario = Scenario(disturbance_std=200.0, effects=Effects.parse(effects))
    record = simulate(scenario, SAMPLES, np.random.SeedSequence(seed))
    body = npz_bytes(x=record.x, y=record.y, fs=record.fs)
    response = post_record(ingest, structure_id, body, "application/x-npz")
    assert response.status_code == 201, response.text
    return response.json()["id"]


@pytest.fixture(scope="module")
def rig(api_server: LiveServer) -> Rig:
    org = Org.create(api_server)
    with clients(org) as (admin, ingest, _):
        structure_id = create_structure(admin, "rig")["id"]
        training = upload(ingest, structure_id, [], seed=1)
        response = admin.post(
            f"{API}/structures/{structure_id}/models/baseline", json={"record_ids": [training]}
        )
        assert response.status_code == 201, response.text
        baseline = response.json()
        k2 = train_fault_mode(admin, ingest, structure_id, "k2", seed=2)
        other = create_structure(admin, "other")["id"]
        return Rig(
            org,
            structure_id,
            baseline,
            k2,
            clean_record=upload(ingest, structure_id, [], seed=3),
            effect_record=upload(ingest, structure_id, ["quadratic_stiffness2=3e5"], seed=4),
            other_structure_record=upload(ingest, other, [], seed=5),
        )


def refinements_url(structure_id: int) -> str:
    return f"{API}/structures/{structure_id}/refinements"


def test_a_missing_effect_is_named_and_the_refined_model_stored_inactive(rig: Rig):
    with clients(rig.org) as (admin, _, viewer):
        body = {"record_id": rig.effect_record, "base_model_id": rig.baseline["id"]}
        response = admin.post(refinements_url(rig.structure_id), json=body)
        assert response.status_code == 201, response.text
        refinement = response.json()
        report = refinement["report"]
        assert report["effects_added"][0]["name"] == "quadratic_stiffness"
        assert report["after"]["one_step_rms"] <= report["before"]["one_step_rms"] / 2
        assert report["data"]["estimation"] == [0, 8000] and report["data"]["test"] == [8000, SAMPLES]
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


def test_a_clean_record_adds_nothing_and_stores_no_model(rig: Rig):
    with clients(rig.org) as (admin, _, viewer):
        before = viewer.get(f"{API}/structures/{rig.structure_id}/models").json()
        body = {"record_id": rig.clean_record, "base_model_id": rig.baseline["id"], "test": [6000, SAMPLES]}
        response = admin.post(refinements_url(rig.structure_id), json=body)
        assert response.status_code == 201, response.text
        refinement = response.json()
        assert refinement["report"]["effects_added"] == [] and refinement["refined_model"] is None
        assert refinement["report"]["before"] == refinement["report"]["after"]
        assert viewer.get(f"{API}/structures/{rig.structure_id}/models").json() == before


@pytest.mark.parametrize(
    ("change", "status", "fragment"),
    [
        ({"record_id": UNKNOWN}, 404, f"record {UNKNOWN}"),
        ({"base_model_id": UNKNOWN}, 404, f"model version {UNKNOWN}"),
        ({"base_model_id": "k2"}, 422, "baseline NARX"),
        ({"record_id": "other"}, 422, "another structure"),
        ({"estimation": [0, 10**9]}, 422, "do not lie within"),
        ({"test": [500, 100]}, 422, "do not lie within"),
        ({"estimation": [0, 30]}, 422, "the estimation part has 30 samples"),
        ({"test": [8000, 8100]}, 422, "the test part has 100 samples"),
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


def test_roles_and_organisations(rig: Rig, api_server: LiveServer):
    body = {"record_id": rig.effect_record, "base_model_id": rig.baseline["id"]}
    with nothing_written(rig.org, rig.structure_id), clients(rig.org) as (_, ingest, viewer):
        for client in (ingest, viewer):
            response = client.post(refinements_url(rig.structure_id), json=body)
            assert response.status_code == 403 and "admin" in detail(response)
    stranger = Org.create(api_server)
    with clients(stranger) as (admin, _, viewer):
        assert admin.post(refinements_url(rig.structure_id), json=body).status_code == 404
        assert viewer.get(refinements_url(rig.structure_id)).status_code == 404
        own = viewer.get(refinements_url(rig.structure_id)).json()
        assert "structure" in own["detail"]
        with clients(rig.org) as (_, _, owner):
            refinement_id = owner.get(refinements_url(rig.structure_id)).json()[0]["id"]
        assert viewer.get(f"{API}/refinements/{refinement_id}").status_code == 404
    with clients(rig.org) as (_, _, viewer):
        assert viewer.get(f"{API}/refinements/{UNKNOWN}").status_code == 404
