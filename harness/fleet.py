"""What the fleet's state rows and counters must equal, computed from the tables themselves.

``/metrics``, the summary and the fleet views read each structure's state row and the ended-job
counts instead of the history; these compute the same figures without them, for the tests that
hold one against the other.
"""

from __future__ import annotations

import datetime as dt
from collections import Counter
from dataclasses import dataclass

from prometheus_client.parser import text_string_to_metric_families
from sqlalchemy import Engine, func, select

from harness.live import LiveServer, http_client
from service.config import Settings
from service.domain.fleet import STATUSES
from service.tables import Job, Record, StructureState, Verdict

SKEW = dt.timedelta(seconds=Settings.model_fields["max_clock_skew_seconds"].default)  # the servers' here
FUTURE = dt.datetime(9999, 12, 31, tzinfo=dt.UTC)


@dataclass
class Fleet:
    server: LiveServer
    engine: Engine  # the test's own connection to the server's database


# --- what the tables hold, computed without the state rows ------------------------------------


def counted(engine: Engine) -> dict[str, object]:
    """Records, verdicts by status and jobs by state, each a ``COUNT(*)`` of its table."""
    with engine.connect() as connection:
        records = connection.scalar(select(func.count()).select_from(Record))
        verdicts = dict(
            connection.execute(select(Verdict.status, func.count()).group_by(Verdict.status)).all()
        )
        jobs = dict(connection.execute(select(Job.status, func.count()).group_by(Job.status)).all())
    return {
        "records": records,
        "verdicts": {status: verdicts.get(status, 0) for status in STATUSES},
        "jobs": {state: jobs.get(state, 0) for state in ("queued", "running", "done", "failed")},
    }


def scraped(server: LiveServer) -> dict[str, object]:
    with http_client(base_url=server.url) as client:
        response = client.get("/metrics")
    assert response.status_code == 200, response.text
    samples = {
        (sample.name, tuple(sorted(sample.labels.items()))): sample.value
        for family in text_string_to_metric_families(response.text)
        for sample in family.samples
    }
    return {
        "records": samples["narxwatch_records_received_total", ()],
        "verdicts": {s: samples["narxwatch_verdicts_total", (("status", s),)] for s in STATUSES},
        "jobs": {
            state: samples["narxwatch_jobs", (("state", state),)]
            for state in ("queued", "running", "done", "failed")
        },
    }


def walked(engine: Engine, structure_id: int) -> dict[str, object]:
    """A structure's standing walked from its verdicts in Python: the newest (by acquisition,
    then id) of those acquired up to the server's clock plus the skew allowed, and the
    acquisition time of the first of the unbroken run of its status at the end; counts of all."""
    limit = dt.datetime.now(dt.UTC) + SKEW
    with engine.connect() as connection:
        rows = connection.execute(
            select(Verdict.id, Verdict.acquired_at, Verdict.status).where(
                Verdict.structure_id == structure_id
            )
        ).all()
        records = connection.scalar(
            select(func.count()).select_from(Record).where(Record.structure_id == structure_id)
        )
    ordered = sorted(
        (row for row in rows if row.acquired_at <= limit), key=lambda row: (row.acquired_at, row.id)
    )
    latest = ordered[-1] if ordered else None
    since = None
    for row in reversed(ordered):
        if row.status != latest.status:
            break
        since = row.acquired_at
    counts = Counter(row.status for row in rows)
    return {
        "latest_verdict_id": latest.id if latest else None,
        "status": latest.status if latest else None,
        "since": since,
        "records": records,
        **{status: counts[status] for status in STATUSES},
    }


def kept(engine: Engine, structure_id: int) -> dict[str, object]:
    with engine.connect() as connection:
        state = connection.execute(
            select(StructureState).where(StructureState.structure_id == structure_id)
        ).one()
    return {
        key: getattr(state, key) for key in ("latest_verdict_id", "status", "since", "records", *STATUSES)
    }
