"""A monitored structure with a history worth looking at, and a logged-in dashboard client.

The history is a rig (its k2 model trained on nine experiments) that was healthy for four records
and then developed a k2 fault of 25 %:
every record is simulated (simulator.simulate) and inspected by the service on upload.
"""

from __future__ import annotations

import datetime as dt
import re
from dataclasses import dataclass
from pathlib import Path
from typing import Any

import httpx

from harness.api_helpers import (
    CUSUM_TRAINING_K,
    Org,
    create_structure,
    simulated,
    train_fault_mode,
    upload_simulated,
    verdicts,
)
from harness.live import LiveServer, http_client
from service.db import transaction
from service.security import Role

DASHBOARD = "/dashboard"
COOKIE = "narxwatch_session"
FIRST_RECORD = dt.datetime(2026, 11, 1, 6, 0, tzinfo=dt.UTC)
HEALTHY_RECORDS = 4
FAULTY_RECORDS = 4
FAULT_K = 25.0
RECORD_SAMPLES = 2000
CHROMIUM = Path("/usr/bin/chromium")
# Chromium as root needs --no-sandbox; the others keep it off a network this machine does not have.
CHROMIUM_ARGS = [
    "--no-sandbox",
    "--disable-gpu",
    "--disable-background-networking",
    "--disable-component-update",
    "--disable-sync",
    "--no-first-run",
]
CHARTS = re.compile(r'<script type="application/json" id="charts">(.*?)</script>', re.S)


@dataclass
class Monitored:
    """An organisation with one structure, its k2 model and its inspected records, oldest first."""

    org: Org
    structure: dict[str, Any]
    records: list[dict[str, Any]]
    verdicts: list[dict[str, Any]]  # as the history API gives them, newest first


def monitored_structure(
    server: LiveServer, seed: int, healthy: int = HEALTHY_RECORDS, faulty: int = FAULTY_RECORDS
) -> Monitored:
    org = Org.create(server)
    admin, ingest, viewer = org.client("admin"), org.client("ingest"), org.client("viewer")
    with admin, ingest, viewer:
        structure = create_structure(admin, "rig with a k2 fault")
        train_fault_mode(admin, ingest, structure["id"], "k2", seed=seed, magnitudes=CUSUM_TRAINING_K)
        records = []
        magnitudes = [0.0] * healthy + [FAULT_K] * faulty
        for index, k in enumerate(magnitudes):
            record = simulated("k2", k, [seed, 100 + index], RECORD_SAMPLES)
            acquired = FIRST_RECORD + dt.timedelta(hours=index)
            records.append(
                upload_simulated(
                    ingest, structure["id"], record, inspect="true", acquired_at=acquired.isoformat()
                )
            )
        return Monitored(org, structure, records, verdicts(viewer, structure["id"]))


def demo_structure(server: LiveServer) -> tuple[Org, int]:
    """The demo organisation with a key of each role, and its structure, seeded in the server's
    database as ``narxwatch demo-seed`` seeds it (once: seeding again finds it)."""
    from service.demo import ORGANISATION, seed_demo

    with transaction(server.app.state.sessions) as session:
        structure_id = seed_demo(session, server.settings).id
    return Org(
        server, ORGANISATION, {role.name: server.key(role, ORGANISATION) for role in Role}
    ), structure_id


def logged_in(server: LiveServer, key: str) -> httpx.Client:
    """A client holding a dashboard session opened with ``key``.

    The cookie is Secure. Browsers send such cookies to http://127.0.0.1 (a secure context);
    httpx sends them over HTTPS only, so it is handed over here as a browser would.
    """
    with http_client(base_url=server.url) as anonymous:
        response = anonymous.post(f"{DASHBOARD}/login", data={"api_key": key, "next": DASHBOARD})
    assert response.status_code == 303, response.text
    return http_client(base_url=server.url, cookies={COOKIE: response.cookies[COOKIE]}, timeout=60)


def charts(page: httpx.Response) -> dict[str, Any]:
    """The figures a page embeds for plotly.js."""
    import json

    found = CHARTS.search(page.text)
    assert found is not None, "the page embeds no charts"
    return json.loads(found.group(1))
