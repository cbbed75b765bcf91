"""No request has unbounded cost: trainings and refinements are priced before they run, large ones
are queued as jobs, model documents are bounded and never read by the history, a stored verdict
is returned without reading its record again, and one organisation's expensive requests cannot
take every thread from another.

Through HTTP against the real app. The limits are those of a server of its own with small
settings, so that small records reach them; what reads a record's signals or a model's document is
seen in the SQL the server's engine sends. The prices, refusals and reads are the service's
whatever the database: on SQLite. Queued work, which the job queue carries (Procrastinate and a
`narxwatch worker` on PostgreSQL), on both: the tests that take ``database_bounded``.
"""

from __future__ import annotations

import json
import threading
import uuid
from collections.abc import Iterator
from contextlib import ExitStack, contextmanager
from dataclasses import dataclass
from pathlib import Path

import httpx
import pytest
from sqlalchemy import event, select, text

from harness.api_helpers import (
    API,
    Org,
    clients,
    create_structure,
    detail,
    experiments,
    json_body,
    nothing_written,
    post_record,
    record_set_csv,
    train_fault_mode,
    wait_for,
)
from harness.live import DATABASES, LiveServer
from models.effects import candidate_effects
from service.config import Settings
from service.jobs.tasks import TASKS
from service.tables import Organisation
from simulator.theory import EXACT_TERMS

MAX_CELLS = 200_000
QUEUE_CELLS = 100_000
MAX_COEFFICIENTS = 60
MAX_DOCUMENT_BYTES = 20_000
EXACT = [t.name for t in EXACT_TERMS]


@dataclass
class Bounded:
    server: LiveServer
    org: Org
    rig: int  # an active k2 model and one record of each length below
    record: dict[int, int]  # samples → record id


LIMITS = {
    "max_training_cells": MAX_CELLS,
    "queue_training_cells": QUEUE_CELLS,
    "max_model_coefficients": MAX_COEFFICIENTS,
    "max_model_document_bytes": MAX_DOCUMENT_BYTES,
    "max_concurrent_expensive": 1,
}


@contextmanager
def bounded_server(request: pytest.FixtureRequest, database: str, folder: Path) -> Iterator[Bounded]:
    """A server with small limits: on SQLite with its embedded job thread, on PostgreSQL with a
    `narxwatch worker` process (the same limits) running the queued jobs."""
    with ExitStack() as stack:
        if database == "sqlite":
            server = stack.enter_context(
                LiveServer(Settings(database_url=f"sqlite:///{folder / 'narxwatch.db'}", **LIMITS))
            )
        else:
            from harness import migrated
            from harness.workers import workers

            name = f"narxwatch_bounded_{uuid.uuid4().hex[:8]}"  # may run twice per server under xdist
            url = migrated.postgresql(request.getfixturevalue("postgres_url"), name)
            server = stack.enter_context(LiveServer(Settings(database_url=url, **LIMITS)))
            stack.enter_context(workers(url, 1, folder, **{k: str(v) for k, v in LIMITS.items()}))
        org = Org.create(server)
        with clients(org) as (admin, ingest, _):
            rig = create_structure(admin, "rig")["id"]
            train_fault_mode(admin, ingest, rig, "k2", seed=21)
            record = {}
            for n in (700, 2000, 4000, 15_000, 30_000):
                response = post_record(ingest, rig, json_body(n))
                assert response.status_code == 201, response.text
                record[n] = response.json()["id"]
        yield Bounded(server, org, rig, record)


@pytest.fixture(scope="module")
def bounded(request: pytest.FixtureRequest, tmp_path_factory) -> Iterator[Bounded]:
    with bounded_server(request, "sqlite", tmp_path_factory.mktemp("bounded")) as bounded:
        yield bounded


@pytest.fixture(scope="module", params=DATABASES)
def database_bounded(request: pytest.FixtureRequest, tmp_path_factory) -> Iterator[Bounded]:
    """The server with small limits on each database, for work the job queue carries."""
    if request.param == "sqlite":
        yield request.getfixturevalue("bounded")
        return
    with bounded_server(request, request.param, tmp_path_factory.mktemp("bounded")) as bounded:
        yield bounded


@pytest.fixture(scope="module")
def api_server(sqlite_api_server: LiveServer) -> LiveServer:
    return sqlite_api_server


def baseline_url(structure_id: int) -> str:
    return f"{API}/structures/{structure_id}/models/baseline"


def assert_refused(response: httpx.Response, status: int, *fragments: str) -> None:
    assert response.status_code == status, response.text
    for fragment in fragments:
        assert fragment in detail(response), f"{fragment!r} not in {detail(response)!r}"


# --- trainings and refinements are priced before they run ----------------------------------


def test_repeated_record_ids_are_refused(bounded: Bounded):
    """Twenty copies of one record trained for 34 s at 10 GB on a 1.5 M-sample record."""
    record = bounded.record[2000]
    with nothing_written(bounded.org, bounded.rig), bounded.org.client("admin") as admin:
        response = admin.post(baseline_url(bounded.rig), json={"record_ids": [record] * 20})
        assert_refused(response, 422, f"record {record} is listed 20 times; list each record once")
        body = {
            "name": "k1",
            "k_min": -32.0,
            "k_max": 32.0,
            "experiments": [{"record_id": record, "k": -30.0}, {"record_id": record, "k": 30.0}],
        }
        response = admin.post(f"{API}/structures/{bounded.rig}/models/fault-modes", json=body)
        assert_refused(response, 422, f"record {record} is listed 2 times")


def test_training_over_the_cell_limit_is_refused(bounded: Bounded):
    cells = 30_000 * len(EXACT)
    with nothing_written(bounded.org, bounded.rig), bounded.org.client("admin") as admin:
        response = admin.post(
            baseline_url(bounded.rig), json={"record_ids": [bounded.record[30_000]], "terms": EXACT}
        )
        assert_refused(
            response,
            422,
            f"this training would fit {cells} cells (samples × coefficients); the limit is {MAX_CELLS}",
            "NARXWATCH_MAX_TRAINING_CELLS",
        )


def test_refinement_over_the_cell_limit_is_refused(bounded: Bounded):
    with bounded.org.client("admin") as admin:
        baseline = admin.post(
            baseline_url(bounded.rig), json={"record_ids": [bounded.record[2000]], "terms": EXACT}
        )
        assert baseline.status_code == 201, baseline.text
        body = {"record_id": bounded.record[30_000], "base_model_id": baseline.json()["id"]}
        with nothing_written(bounded.org, bounded.rig):
            response = admin.post(f"{API}/structures/{bounded.rig}/refinements", json=body)
            assert_refused(response, 422, "this refinement would fit", "NARXWATCH_MAX_TRAINING_CELLS")


def test_a_model_with_too_many_coefficients_is_refused(bounded: Bounded):
    terms = [f"y[t-{lag}]" for lag in range(1, 32)] + [f"x[t-{lag}]" for lag in range(1, 31)]
    with nothing_written(bounded.org, bounded.rig), bounded.org.client("admin") as admin:
        response = admin.post(
            baseline_url(bounded.rig), json={"record_ids": [bounded.record[2000]], "terms": terms}
        )
        assert_refused(
            response,
            422,
            f"would have 61 coefficients (terms × basis functions); the limit is {MAX_COEFFICIENTS}",
            "NARXWATCH_MAX_MODEL_COEFFICIENTS",
        )


def test_a_model_document_over_the_limit_is_refused(bounded: Bounded):
    """40 terms are allowed, but their covariance makes a document over the (small) byte limit."""
    terms = [f"y[t-{lag}]" for lag in range(1, 21)] + [f"x[t-{lag}]" for lag in range(1, 21)]
    with nothing_written(bounded.org, bounded.rig), bounded.org.client("admin") as admin:
        response = admin.post(
            baseline_url(bounded.rig), json={"record_ids": [bounded.record[2000]], "terms": terms}
        )
        assert_refused(
            response, 422, f"the limit is {MAX_DOCUMENT_BYTES}", "NARXWATCH_MAX_MODEL_DOCUMENT_BYTES"
        )


# --- large work is queued ---------------------------------------------------------------------


def assert_queued(response: httpx.Response) -> int:
    """The job id of a 202 answer, after checking that it says where to follow the job."""
    assert response.status_code == 202, response.text
    job = response.json()
    assert isinstance(job["job_id"], int)
    assert response.headers["location"] == job["location"] == f"{API}/jobs/{job['job_id']}"
    assert "NARXWATCH_QUEUE_TRAINING_CELLS" in job["detail"]
    return job["job_id"]


def run_again(server: LiveServer, job_id: int) -> None:
    """Run a finished job once more, as a redelivery would (every job runs at least once)."""
    if server.app.state.jobs.name == "embedded":
        query = "SELECT task, args, status FROM jobs WHERE id = :id"
    else:
        query = "SELECT task_name, args, status::text FROM procrastinate_jobs WHERE id = :id"

    def finished() -> tuple[str, dict] | None:
        with server.app.state.sessions() as session:
            task, args, status = session.execute(text(query), {"id": job_id}).one()
        assert status != "failed", f"job {job_id} failed"
        if status not in ("done", "succeeded"):
            return None
        return task, args if isinstance(args, dict) else json.loads(args)  # SQLite's JSON is text

    task, args = wait_for(finished, 30, f"job {job_id} done")
    args.pop("organisation_id", None)  # Procrastinate's jobs carry it for GET /jobs, not for the task
    with server.app.state.sessions() as session:
        TASKS[task](session, server.settings, **args)


def test_a_large_training_is_queued_and_its_job_stores_the_version(database_bounded: Bounded):
    bounded = database_bounded
    record = bounded.record[15_000]  # 120 000 cells: over the queueing threshold, under the limit
    with clients(bounded.org) as (admin, _, viewer):
        response = admin.post(baseline_url(bounded.rig), json={"record_ids": [record], "terms": EXACT})
        job_id = assert_queued(response)

        def trained() -> list[dict]:
            models = viewer.get(f"{API}/structures/{bounded.rig}/models").json()
            return [m for m in models if m["kind"] == "baseline" and m["training"]["record_ids"] == [record]]

        (version,) = wait_for(trained, 60, "the queued training's version")
        assert version["active"] is True and version["terms"] == EXACT
        assert version["statistics"]["n_obs"] == 15_000 - 4
        job = wait_for(
            lambda: (j := admin.get(f"{API}/jobs/{job_id}").json())["state"] == "done" and j, 30, "done"
        )
        # The job names what it made, in its listing too; other tasks' jobs name no model.
        made = {"id": version["id"], "name": "baseline", "version": version["version"]}
        assert job["model"] == made, job  # type: ignore[index]
        listed = admin.get(f"{API}/jobs", params={"limit": 1000}).json()["items"]
        assert {j["id"]: j["model"] for j in listed if j["model"] is not None} == {job_id: made}
        run_again(bounded.server, job_id)
        assert trained() == [version], "the job run again stored a second version"


def test_a_refinement_of_a_long_record_is_queued_and_its_job_stores_the_report(database_bounded: Bounded):
    bounded = database_bounded
    with clients(bounded.org) as (admin, _, viewer):
        baseline = admin.post(
            baseline_url(bounded.rig), json={"record_ids": [bounded.record[2000]], "terms": EXACT}
        )
        assert baseline.status_code == 201, baseline.text
        body = {"record_id": bounded.record[4000], "base_model_id": baseline.json()["id"]}
        response = admin.post(f"{API}/structures/{bounded.rig}/refinements", json=body)
        job_id = assert_queued(response)

        def refined() -> list[dict]:
            listed = viewer.get(f"{API}/structures/{bounded.rig}/refinements").json()
            return [r for r in listed if r["record_id"] == body["record_id"]]

        (refinement,) = wait_for(refined, 120, "the queued refinement")
        assert refinement["base_model"]["id"] == baseline.json()["id"]
        assert refinement["report"]["data"]["test"] == [2 * 4000 // 3, 4000]
        run_again(bounded.server, job_id)
        assert refined() == [refinement], "the job run again stored a second refinement"


def test_a_refinement_on_several_records_is_priced_on_all_of_them(database_bounded: Bounded):
    """The records judged cost too: a refinement from the rig's eight terms prices every sample at
    the terms and the regressors of every family offered for them (44); 2000 samples fitted
    (88 000 cells alone) with 4000 judged is 264 000 cells, over the limit; 2000 + 700 fitted with
    1000 judged, 162 800 cells, is queued though no record alone would be, and the job stores
    every record's role."""
    bounded = database_bounded
    regressors = len(EXACT_TERMS) + sum(effect.regressors for effect in candidate_effects(EXACT_TERMS))
    assert 2000 * regressors < QUEUE_CELLS < (2000 + 700 + 1000) * regressors < MAX_CELLS < 6000 * regressors
    with clients(bounded.org) as (admin, ingest, viewer):
        baseline = admin.post(
            baseline_url(bounded.rig), json={"record_ids": [bounded.record[2000]], "terms": EXACT}
        )
        assert baseline.status_code == 201, baseline.text
        base = baseline.json()["id"]
        with nothing_written(bounded.org, bounded.rig):
            body = {"record_ids": [bounded.record[2000]], "test_record_ids": [bounded.record[4000]]}
            response = admin.post(
                f"{API}/structures/{bounded.rig}/refinements", json=body | {"base_model_id": base}
            )
            assert_refused(response, 422, f"this refinement would fit {6000 * regressors} cells")
        judged = post_record(ingest, bounded.rig, json_body(1000, seed=77))
        assert judged.status_code == 201, judged.text
        body = {
            "record_ids": [bounded.record[2000], bounded.record[700]],
            "test_record_ids": [judged.json()["id"]],
            "base_model_id": base,
        }
        job_id = assert_queued(admin.post(f"{API}/structures/{bounded.rig}/refinements", json=body))

        def refined() -> list[dict]:
            listed = viewer.get(f"{API}/structures/{bounded.rig}/refinements").json()
            return [r for r in listed if r["test_record_ids"] == body["test_record_ids"]]

        (refinement,) = wait_for(refined, 120, "the queued refinement")
        assert (
            refinement["record_ids"] == body["record_ids"] and refinement["record_id"] == bounded.record[2000]
        )
        assert [test["record_id"] for test in refinement["report"]["tests"]] == body["test_record_ids"]
        run_again(bounded.server, job_id)
        assert refined() == [refinement], "the job run again stored a second refinement"


def test_what_queued_work_would_fail_on_is_refused_before_it_is_queued(bounded: Bounded):
    record = bounded.record[15_000]  # large enough to be queued
    fault_mode = {"k_min": -32.0, "k_max": 32.0, "experiments": [{"record_id": record, "k": 0.0}] * 2}
    refusals = [
        ("baseline", {"record_ids": [record], "terms": ["y[t-1]", "z[t-1]"]}, "cannot read term 'z[t-1]'"),
        ("fault-modes", {**fault_mode, "name": "baseline"}, "'baseline' names the healthy model"),
        ("fault-modes", {**fault_mode, "name": "k1", "k_min": 40.0}, "k_min (40.0) must be below k_max"),
    ]
    with bounded.org.client("admin") as admin:
        baseline = admin.post(
            baseline_url(bounded.rig), json={"record_ids": [bounded.record[2000]], "terms": EXACT}
        )
        assert baseline.status_code == 201, baseline.text
        refinement = {"record_id": bounded.record[4000], "base_model_id": baseline.json()["id"]}
        with nothing_written(bounded.org, bounded.rig):
            for kind, body, message in refusals:
                response = admin.post(f"{API}/structures/{bounded.rig}/models/{kind}", json=body)
                assert_refused(response, 422, message)
            response = admin.post(
                f"{API}/structures/{bounded.rig}/refinements", json={**refinement, "test": [3000, 5000]}
            )
            assert_refused(response, 422, "the test samples 3000:5000 do not lie within the record's 4000")


# --- a short record's refinement says what it needs -----------------------------------------


def test_refinement_of_a_record_too_short_for_its_test_part(bounded: Bounded):
    """A test part must start any model the loop may reach (lags up to 6 from SPEC §2's
    structure, missing lags) and leave a sample to score; one too short for the residual tests
    and spectrum (234 samples, which answered "smoothing_bins must be odd … got 31") is judged by
    its errors, the tests skipped (models.assessment.assess)."""
    with bounded.org.client("admin") as admin:
        baseline = admin.post(
            baseline_url(bounded.rig), json={"record_ids": [bounded.record[2000]], "terms": EXACT}
        )
        assert baseline.status_code == 201, baseline.text
        body = {
            "record_id": bounded.record[700],
            "base_model_id": baseline.json()["id"],
            "estimation": [0, 694],
            "test": [694, 700],
        }
        with nothing_written(bounded.org, bounded.rig):
            response = admin.post(f"{API}/structures/{bounded.rig}/refinements", json=body)
            assert_refused(response, 422, "the test part has 6 samples; judging a model needs at least 7")
        del body["estimation"], body["test"]
        response = admin.post(f"{API}/structures/{bounded.rig}/refinements", json=body)
        assert response.status_code == 201, response.text
        assert "smoothing_bins" not in response.text


# --- one organisation's expensive requests cannot crowd out another's --------------------------


def test_expensive_requests_are_capped_per_organisation(bounded: Bounded):
    """With one expensive request allowed per organisation at once, ours are 429 with Retry-After
    while one of ours holds the slot (taken here as a long inspection of ours would take it, so
    that the moment is certain), and another organisation's training runs meanwhile. A request
    gives its slot back however it ends."""
    other = Org.create(bounded.server)
    with bounded.server.app.state.sessions() as session:
        organisation_id = session.scalar(select(Organisation.id).where(Organisation.name == bounded.org.name))
    body = {"record_ids": [bounded.record[2000]], "terms": EXACT}
    with clients(bounded.org) as (admin, ingest, _), clients(other) as (other_admin, other_ingest, _):
        other_rig = create_structure(other_admin, "rig")["id"]
        fault_mode = {"name": "k2", "k_min": -32.0, "k_max": 32.0, "terms": EXACT}
        fault_mode["experiments"] = experiments(other_ingest, other_rig, "k2", seed=22)
        inspected = post_record(ingest, bounded.rig, json_body(300), inspect="true").json()
        with bounded.server.app.state.expensive.held(organisation_id):
            with nothing_written(bounded.org, bounded.rig):
                refused = admin.post(baseline_url(bounded.rig), json=body)
                assert_refused(
                    refused, 429, "at once as this server allows (1, NARXWATCH_MAX_CONCURRENT_EXPENSIVE)"
                )
                assert int(refused.headers["retry-after"]) > 0
                refused = ingest.post(f"{API}/records/{inspected['id']}/inspect")
                assert_refused(refused, 429, "NARXWATCH_MAX_CONCURRENT_EXPENSIVE")
            theirs = other_admin.post(f"{API}/structures/{other_rig}/models/fault-modes", json=fault_mode)
            assert theirs.status_code == 201, theirs.text
        failed = admin.post(baseline_url(bounded.rig), json={**body, "terms": ["y[t-0]"]})
        assert failed.status_code == 422, failed.text
        assert admin.post(baseline_url(bounded.rig), json=body).status_code == 201
        again = ingest.post(f"{API}/records/{inspected['id']}/inspect")
        assert again.status_code == 200 and again.json() == inspected["verdict"]


# --- what reads what: seen in the SQL the server sends ------------------------------------------


@contextmanager
def statements(server: LiveServer) -> Iterator[list[str]]:
    """The SQL the server's engine runs for requests within the block (not for the embedded job
    thread, which may still be running another test's queued inspections)."""
    seen: list[str] = []

    def record(conn, cursor, statement, parameters, context, executemany) -> None:
        if threading.current_thread().name != "narxwatch-jobs":
            seen.append(statement)

    engine = server.app.state.engine
    event.listen(engine, "before_cursor_execute", record)
    try:
        yield seen
    finally:
        event.remove(engine, "before_cursor_execute", record)


def test_inspecting_again_returns_the_stored_verdict_without_reading_the_record(api_server: LiveServer):
    """A 1.5 M-sample record was inspected again for 32 s at 6.4 GB, only to keep its verdict."""
    org = Org.create(api_server)
    with clients(org) as (admin, ingest, _):
        rig = create_structure(admin)["id"]
        train_fault_mode(admin, ingest, rig, "k2", seed=23)
        uploaded = post_record(ingest, rig, json_body(1000), inspect="true").json()
        with statements(api_server) as seen:
            again = ingest.post(f"{API}/records/{uploaded['id']}/inspect")
        assert again.status_code == 200, again.text
        assert again.json() == uploaded["verdict"]
        read = [s for s in seen if "records.x" in s or "records.y" in s]
        assert not read, f"the record's signals were read: {read}"
        # A new model set is a new inspection: then the signals are read, and a verdict added.
        train_fault_mode(admin, ingest, rig, "k2", seed=24)
        with statements(api_server) as seen:
            fresh = ingest.post(f"{API}/records/{uploaded['id']}/inspect")
        assert fresh.status_code == 200 and fresh.json()["id"] != uploaded["verdict"]["id"]
        assert any("records.x" in s for s in seen)


def test_history_and_verdicts_never_read_model_documents(api_server: LiveServer):
    """A 500-term model's 24 MB document made every history page take 3 s."""
    org = Org.create(api_server)
    terms = EXACT + [f"y[t-{lag}]" for lag in range(5, 21)] + [f"x[t-{lag}]" for lag in range(1, 4)]
    with clients(org) as (admin, ingest, viewer):
        rig = create_structure(admin)["id"]
        model = train_fault_mode(admin, ingest, rig, "k2", seed=25, terms=terms)
        assert len(model["terms"]) == len(terms)
        verdict = post_record(ingest, rig, json_body(1000), inspect="true").json()["verdict"]
        records = [post_record(ingest, rig, json_body(1000)).json()["id"] for _ in range(2)]
        # The refinement's base is the rig's own structure, for which the loop has little to add:
        # from the 27-term model it ran for a minute, and timed out on a busy machine.
        baseline = admin.post(baseline_url(rig), json={"record_ids": records[:1], "terms": EXACT})
        assert baseline.status_code == 201, baseline.text
        body = {"record_id": records[1], "base_model_id": baseline.json()["id"]}
        refinement = admin.post(f"{API}/structures/{rig}/refinements", json=body)
        assert refinement.status_code == 201, refinement.text
        pages = [
            f"{API}/structures/{rig}/verdicts",
            f"{API}/structures/{rig}/summary",
            f"{API}/verdicts/{verdict['id']}",
            f"{API}/structures/{rig}/models",
            f"{API}/structures/{rig}/refinements",
            f"{API}/refinements/{refinement.json()['id']}",
        ]
        with statements(api_server) as seen:
            answers = [viewer.get(page) for page in pages]
        assert [a.status_code for a in answers] == [200] * len(pages), [a.text for a in answers]
        assert answers[0].json()["items"][0]["model_versions"] == [
            {"id": model["id"], "name": "k2", "version": model["version"]}
        ]
        assert any("model_versions" in s for s in seen)
        read = [s for s in seen if "model_versions.document" in s]
        assert not read, f"a model document was read: {read}"


def test_a_record_set_reads_the_structure_and_its_models_once_however_many_records_it_holds(
    api_server: LiveServer,
):
    """A set of k records looked the structure and its active models up once a record: a hundred
    identical reads of the models for a set of a hundred, while the first records' inserts held
    the write lock. Every record is now checked before the first is written, against one read."""
    org = Org.create(api_server)
    with clients(org) as (admin, ingest, _):
        rig = create_structure(admin)["id"]
        train_fault_mode(admin, ingest, rig, "k2", seed=26)
        reads = []
        # The first set reads the models' documents too, which the server then keeps.
        for records, seed in ((2, 1), (2, 2), (6, 3)):
            with statements(api_server) as seen:
                stored = ingest.post(
                    f"{API}/structures/{rig}/record-sets",
                    content=record_set_csv(records, 500, seed),
                    headers={"Content-Type": "text/csv"},
                )
            assert stored.status_code == 201, stored.text
            assert len(stored.json()) == records
            reads.append(sum("model_versions" in s for s in seen))
            inserts = [s for s in seen if s.lstrip().upper().startswith("INSERT INTO RECORDS")]
            assert len(inserts) == records, inserts
            first_insert = seen.index(inserts[0])
            assert not any("model_versions" in s for s in seen[first_insert:]), "models read after a write"
        assert reads[1] == reads[2] > 0, reads
