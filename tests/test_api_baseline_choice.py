"""A model chosen for the structure: a baseline trained without terms has them chosen from its
healthy records, a fault mode trained without terms takes the active baseline's, and no training
falls back on the paper rig's terms.

Over HTTP against the real app, on a structure that is not the rig: a 3-DOF chain's driving-point
accelerometer with 1 % sensor noise (the novelty tests' chain), whose acceleration the force
reaches at once, so that a model without x[t] has to predict a force it has not seen.
"""

from __future__ import annotations

from collections.abc import Iterator
from dataclasses import dataclass

import pytest

from harness.accelerometer import record, scenario
from harness.api_helpers import (
    API,
    FS,
    Org,
    clients,
    create_structure,
    detail,
    nothing_written,
    npz_bytes,
    post_record,
)
from harness.live import LiveServer
from models.baseline_choice import CHOICE_COLUMNS, MAX_ORDER
from service.config import Settings
from simulator.theory import EXACT_TERMS

# The records are stored at the helpers' rate, not the chain's 1 kHz, so that the sentinel records
# of nothing_written fit the structures: the models see samples, not seconds.
HEALTHY = (2000, 2000, 2000)  # short healthy records: the choice takes seconds
# The choice costs CHOICE_COLUMNS cells a sample: the healthy records' 6000 samples fit within
# these limits, run within the request; 10 000 more do not.
LIMITS = {"max_training_cells": 3_000_000, "queue_training_cells": 3_000_000}
FAULT_K = (0.0, 10.0, 20.0)  # % loss of spring k2


@dataclass
class Chain:
    server: LiveServer
    org: Org
    structure: int
    healthy: list[int]
    baseline: dict  # the answer to the baseline trained without terms


def upload(ingest, structure_id: int, fault: str, k: float, n: int, seed: int) -> int:
    x, y = record(scenario(fault, k), n, seed)
    response = post_record(ingest, structure_id, npz_bytes(x=x, y=y, fs=FS), "application/x-npz")
    assert response.status_code == 201, response.text
    return response.json()["id"]


def models_url(structure_id: int, kind: str) -> str:
    return f"{API}/structures/{structure_id}/models/{kind}"


def fault_mode_body(ingest, structure_id: int, seed: int) -> dict:
    experiments = [
        {"record_id": upload(ingest, structure_id, "k2", k, 2000, seed + i), "k": k}
        for i, k in enumerate(FAULT_K)
    ]
    return {"name": "k2", "k_min": 0.0, "k_max": 25.0, "experiments": experiments}


@pytest.fixture(scope="module")
def chain(tmp_path_factory) -> Iterator[Chain]:
    folder = tmp_path_factory.mktemp("choice")
    with LiveServer(Settings(database_url=f"sqlite:///{folder / 'narxwatch.db'}", **LIMITS)) as server:
        org = Org.create(server)
        with clients(org) as (admin, ingest, _):
            structure = create_structure(admin, "chain")["id"]
            healthy = [upload(ingest, structure, "none", 0.0, n, 100 + i) for i, n in enumerate(HEALTHY)]
            response = admin.post(models_url(structure, "baseline"), json={"record_ids": healthy})
            assert response.status_code == 201, response.text
        yield Chain(server, org, structure, healthy, response.json())


def test_a_baseline_without_terms_is_chosen_for_the_structure(chain: Chain) -> None:
    """The acceleration's model takes x[t] (input delay 0), not the rig's eight terms, and the
    training says what it chose and how well that simulates held-out data."""
    baseline = chain.baseline
    assert "x[t]" in baseline["terms"]
    assert baseline["terms"] != [term.name for term in EXACT_TERMS]
    choice = baseline["training"]["choice"]
    assert choice["delay"] == 0
    assert choice["terms"] == baseline["terms"]
    ny, nx = choice["orders"]["ny"], choice["orders"]["nx"]
    assert 1 <= ny <= MAX_ORDER and nx == ny
    assert {f"y[t-{ny}]", f"x[t-{nx - 1}]"} <= set(baseline["terms"])
    held_out = choice["held_out"]
    # A linear model with x[t] simulates the chain's acceleration to about 1.5 % of its spread:
    # the 1 % sensor noise on the output alone is most of that.
    assert held_out["free_run_nrmse"] < 0.05
    assert held_out["free_run_rms"] > 0 and held_out["samples"] > 1000
    assert set(choice["terms_added"]) <= set(baseline["terms"])
    # The listing shows the version as the training answered it.
    with chain.org.client("viewer") as viewer:
        listed = viewer.get(f"{API}/structures/{chain.structure}/models").json()
    assert [m["training"]["choice"] for m in listed if m["id"] == baseline["id"]] == [choice]


def test_a_fault_mode_without_terms_takes_the_active_baselines(chain: Chain) -> None:
    with clients(chain.org) as (admin, ingest, _):
        body = fault_mode_body(ingest, chain.structure, 200)
        response = admin.post(models_url(chain.structure, "fault-modes"), json=body)
    assert response.status_code == 201, response.text
    mode = response.json()
    assert mode["terms"] == chain.baseline["terms"]
    assert mode["training"]["terms_from"] == {
        "model_id": chain.baseline["id"],
        "name": "baseline",
        "version": chain.baseline["version"],
    }


def test_a_fault_mode_without_terms_or_a_baseline_is_refused(chain: Chain) -> None:
    with clients(chain.org) as (admin, ingest, _):
        structure = create_structure(admin, "chain without a baseline")["id"]
        body = fault_mode_body(ingest, structure, 300)
        with nothing_written(chain.org, structure):
            response = admin.post(models_url(structure, "fault-modes"), json=body)
        assert response.status_code == 409, response.text
        assert "has no active baseline to take the terms from" in detail(response)
        assert "train a baseline first" in detail(response) and "or give terms" in detail(response)
        # Given terms, the same request trains.
        given = admin.post(models_url(structure, "fault-modes"), json=body | {"terms": ["y[t-1]", "x[t]"]})
        assert given.status_code == 201, given.text
        assert given.json()["terms"] == ["y[t-1]", "x[t]"] and "terms_from" not in given.json()["training"]


def test_a_choice_over_the_cost_bound_is_refused_before_it_starts(chain: Chain) -> None:
    """Choosing terms costs far more than fitting given ones: it is priced as such, and refused
    whole before any signal is read, as is a record too short to hold out part of; with its terms
    given, the same baseline trains."""
    with clients(chain.org) as (admin, ingest, _):
        structure = create_structure(admin, "long chain records")["id"]
        ids = [upload(ingest, structure, "none", 0.0, n, 400 + i) for i, n in enumerate((2000, 10_000))]
        with nothing_written(chain.org, structure):
            response = admin.post(models_url(structure, "baseline"), json={"record_ids": ids})
        assert response.status_code == 422, response.text
        message = detail(response)
        assert message.startswith(f"choosing this baseline's terms would fit {12_000 * CHOICE_COLUMNS} cells")
        assert "NARXWATCH_MAX_TRAINING_CELLS" in message and "or give the baseline's terms" in message
        short = upload(ingest, structure, "none", 0.0, 500, 402)
        with nothing_written(chain.org, structure):
            response = admin.post(models_url(structure, "baseline"), json={"record_ids": [ids[0], short]})
        assert response.status_code == 422, response.text
        assert detail(response) == (
            f"record {short} has 500 samples; choosing a baseline's terms holds out part of each record and "
            "needs at least 600: use longer records, or give the baseline's terms"
        )
        given = admin.post(
            models_url(structure, "baseline"), json={"record_ids": ids, "terms": ["y[t-1]", "x[t]"]}
        )
        assert given.status_code == 201, given.text
        assert "choice" not in given.json()["training"]


def test_the_openapi_document_says_what_a_training_without_terms_does(chain: Chain) -> None:
    with chain.org.client("viewer") as viewer:
        schemas = viewer.get("/openapi.json").json()["components"]["schemas"]
    assert (
        "chosen for the structure from these healthy records"
        in schemas["BaselineTrain"]["properties"]["terms"]["description"]
    )
    for body in ("FaultModeTrain", "PooledBaselineTrain", "PooledFaultModeTrain"):
        assert "the structure's active baseline's" in schemas[body]["properties"]["terms"]["description"]
    assert "choice" in schemas["ModelOut"]["properties"]["training"]["description"]
