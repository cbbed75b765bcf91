"""`GET /jobs`: an organisation's admins see its queued work, what failed and why; no one else
sees it. Over HTTP on SQLite (embedded backend) and PostgreSQL (Procrastinate), with the jobs run
by a worker the test starts when it chooses."""

from __future__ import annotations

from pathlib import Path

import pytest

from harness.api_helpers import (
    API,
    Org,
    clients,
    create_structure,
    npz_bytes,
    post_record,
    simulated,
    train_fault_mode,
)
from harness.job_helpers import LONG_LAG_TERMS, TOO_SHORT, database_url, run_jobs
from harness.live import LiveServer
from service.config import Settings

JOBS = f"{API}/jobs"


@pytest.fixture(params=["sqlite", "postgresql"])
def server(request, tmp_path: Path):
    """The app with no worker running: jobs stay queued until ``run_jobs``."""
    settings = Settings(database_url=database_url(request.param, tmp_path, request), embedded_worker=False)
    with LiveServer(settings) as live:
        yield live


def queue(ingest, structure_id: int, n: int, seed: int) -> int:
    record = simulated("k2", 10.0, [seed], n)
    body = npz_bytes(x=record.x, y=record.y, fs=record.fs)
    response = post_record(ingest, structure_id, body, "application/x-npz", inspect="queue")
    assert response.status_code == 202, response.text
    return response.json()["id"]


def test_admins_list_their_organisations_jobs_with_the_reason_of_those_that_failed(server: LiveServer):
    owner = Org.create(server)
    with clients(owner) as (admin, ingest, _):
        sid = create_structure(admin)["id"]
        train_fault_mode(admin, ingest, sid, "k2", seed=87)
        valid = [queue(ingest, sid, 2000, seed) for seed in (88, 89)]
        # Storable, and long enough for today's model; too short for the one trained next.
        short = queue(ingest, sid, TOO_SHORT, 90)
        train_fault_mode(admin, ingest, sid, "k2", seed=91, terms=LONG_LAG_TERMS)
        run_jobs(server)

        listed = admin.get(JOBS)
        assert listed.status_code == 200, listed.text
        jobs = listed.json()["items"]
        assert [job["args"] for job in jobs] == [{"record_id": r} for r in (short, *reversed(valid))]
        assert {job["task"] for job in jobs} == {"inspect_record"}
        failed = admin.get(JOBS, params={"state": "failed"}).json()["items"]
        assert [(job["args"]["record_id"], job["attempts"]) for job in failed] == [(short, 1)]
        assert "InputError" in failed[0]["error"] and "too short" in failed[0]["error"]
        done = admin.get(JOBS, params={"state": "done"}).json()["items"]
        assert sorted(job["args"]["record_id"] for job in done) == valid
        assert admin.get(JOBS, params={"state": "queued"}).json()["items"] == []

        one = admin.get(f"{JOBS}/{failed[0]['id']}")
        assert one.status_code == 200 and one.json() == failed[0]

        # Pages, newest first, that put together give the whole list.
        pages, cursor = [], None
        while True:
            page = admin.get(JOBS, params={"limit": 2, **({"cursor": cursor} if cursor else {})}).json()
            pages.append(page["items"])
            cursor = page["next_cursor"]
            if cursor is None:
                break
        assert [len(p) for p in pages] == [2, 1] and [job for page in pages for job in page] == jobs

        unknown = admin.get(JOBS, params={"state": "stuck"})
        assert unknown.status_code == 422 and "failed" in unknown.text
