"""The dashboard end to end in a real headless browser: Debian's Chromium driven by Playwright.

A person logs in, reads the fleet, follows a structure, sees its charts drawn with one point per
verdict, follows a record and sees its fit, and logs out. Screenshots of each page are kept under
``var/test-artifacts/dashboard/`` (or ``$NARXWATCH_TEST_ARTIFACTS``) for a person to look at.

Chromium comes from ``scripts/ensure-chromium.sh`` (``make test`` runs it); Playwright's own
browser download is never used. Without Chromium these tests are skipped with the reason, and
with CI=true they fail instead: CI must run them.
"""

from __future__ import annotations

import datetime as dt
import os
from collections.abc import Iterator
from pathlib import Path

import numpy as np
import pytest

from harness.accelerometer import SAMPLES, chain_baseline, healthy_training, record, scenario, upload
from harness.api_helpers import (
    API,
    CUSUM_TRAINING_K,
    FS,
    RIG_TERMS,
    Org,
    clients,
    create_structure,
    npz_bytes,
    post_record,
    simulated,
    train_fault_mode,
    upload_simulated,
)
from harness.channel_helpers import NAMES, build_site, chain_record, channels_body
from harness.dashboard_helpers import (
    CHROMIUM,
    CHROMIUM_ARGS,
    DASHBOARD,
    FIRST_RECORD,
    RECORD_SAMPLES,
    Monitored,
    demo_structure,
    monitored_structure,
)
from harness.live import LiveServer
from harness.prerequisites import unavailable
from service.config import Settings
from simulator.simulate import Effects, Scenario, simulate

ARTIFACTS = Path(
    os.environ.get("NARXWATCH_TEST_ARTIFACTS", Path(__file__).parents[1] / "var" / "test-artifacts")
)
TIMEOUT_MS = 30_000


@pytest.fixture(scope="module")
def browser() -> Iterator[object]:
    if not CHROMIUM.exists():
        unavailable(f"{CHROMIUM} is not installed: run 'sudo bash scripts/ensure-chromium.sh'")
    from playwright.sync_api import sync_playwright

    with sync_playwright() as playwright:
        chromium = playwright.chromium.launch(executable_path=str(CHROMIUM), args=CHROMIUM_ARGS)
        yield chromium
        chromium.close()


@pytest.fixture(scope="module")
def server(tmp_path_factory: pytest.TempPathFactory) -> Iterator[LiveServer]:
    url = f"sqlite:///{tmp_path_factory.mktemp('browser') / 'narxwatch.db'}"
    with LiveServer(Settings(database_url=url)) as live:
        yield live


@pytest.fixture(scope="module")
def monitored(server: LiveServer) -> Monitored:
    return monitored_structure(server, seed=47)


@pytest.fixture
def page(browser, request: pytest.FixtureRequest):  # type: ignore[no-untyped-def]
    context = browser.new_context(viewport={"width": 1360, "height": 900})
    context.set_default_timeout(TIMEOUT_MS)
    tab = context.new_page()
    errors: list[str] = []
    tab.on("pageerror", lambda error: errors.append(str(error)))
    # What the pages' Content-Security-Policy refuses is reported on the console, not raised.
    tab.on("console", lambda note: errors.append(note.text) if "Security Policy" in note.text else None)
    yield tab
    context.close()
    assert not errors, f"the page raised in the browser or broke its security policy: {errors}"


def shot(page, name: str) -> None:  # type: ignore[no-untyped-def]
    folder = ARTIFACTS / "dashboard"
    folder.mkdir(parents=True, exist_ok=True)
    page.screenshot(path=folder / f"{name}.png", full_page=True)


def drawn(page, chart: str) -> dict:  # type: ignore[no-untyped-def]
    """Scrolls to the chart (charts are drawn as they come into view) and waits until plotly.js has
    drawn it; its traces' point counts, as plotly holds and draws them."""
    page.locator(f"#chart-{chart}").scroll_into_view_if_needed()
    page.wait_for_selector(f"#chart-{chart}[data-drawn=true]")
    return page.evaluate(
        """(id) => {
            const element = document.getElementById(id);
            return {
                points: element.data.map((trace) => trace.x.length),
                markers: element.querySelectorAll('.scatterlayer .trace .points path').length,
                bars: element.querySelectorAll('.barlayer .point').length,
                traces: element.querySelectorAll('.scatterlayer .trace').length,
            };
        }""",
        f"chart-{chart}",
    )


def log_in(page, key: str) -> None:  # type: ignore[no-untyped-def]
    page.fill("#api_key", key)
    page.click("#login")


def test_log_in_follow_a_structure_and_a_record_and_log_out(page, server: LiveServer, monitored: Monitored):
    other = Org.create(server)
    with clients(other) as (admin, _, _):
        create_structure(admin, "another organisation's rig")

    page.goto(f"{server.url}{DASHBOARD}")
    assert page.url.startswith(f"{server.url}{DASHBOARD}/login"), "a logged-out visitor is sent to log in"
    shot(page, "1-login")
    log_in(page, monitored.org.keys["viewer"])
    page.wait_for_url(f"{server.url}{DASHBOARD}")

    rows = page.locator("#fleet tbody tr")
    assert rows.count() == 1
    assert "another organisation's rig" not in page.content()
    latest = monitored.verdicts[0]
    assert rows.first.get_attribute("class") == f"status-{latest['status']}"
    shot(page, "2-fleet")

    page.click(f"text={monitored.structure['name']}")
    page.wait_for_url(f"**{DASHBOARD}/structures/{monitored.structure['id']}")
    with_magnitude = sum(v["k_hat"] is not None for v in monitored.verdicts)
    k_hat = drawn(page, "k_hat")
    assert k_hat["points"][0] == with_magnitude and k_hat["markers"] == with_magnitude
    q = drawn(page, "q")
    assert q["points"] == [len(monitored.verdicts), 2] and q["markers"] == len(monitored.verdicts)
    assert page.get_attribute("#chart-trajectories-k2", "data-drawn") is None, "below the fold: not drawn yet"
    trajectories = drawn(page, "trajectories-k2")
    assert trajectories["points"] == [65] * 24 and trajectories["traces"] == 24
    assert page.locator("#verdicts tbody tr").count() == len(monitored.verdicts)
    shot(page, "3-structure")

    record_id = monitored.verdicts[0]["record_id"]
    page.click(f"#verdicts a[href='/dashboard/records/{record_id}']")
    page.wait_for_url(f"**{DASHBOARD}/records/{record_id}")
    record = next(r for r in monitored.records if r["id"] == record_id)
    predicted = record["n_samples"] - 4  # the k2 model's longest lag is 4
    response = drawn(page, "response")
    assert response["points"] == [predicted, predicted]
    assert drawn(page, "residual")["points"] == [predicted]
    # Those 2 000-sample traces are WebGL ones, which plotly.js replaces by a notice where WebGL
    # cannot run (no GPU, or a security policy refusing regl's compiled code).
    assert page.locator("#chart-response .gl-canvas-context").count() == 1
    assert page.locator(".no-webgl").count() == 0, "the WebGL charts are drawn, not refused"
    autocorrelation = drawn(page, "autocorrelation")
    assert autocorrelation["bars"] == latest["lags"] and autocorrelation["points"] == [latest["lags"]] * 3
    assert latest["status"] in page.locator("#verdict").inner_text()
    shot(page, "4-record")

    page.click("#logout")
    page.wait_for_url(f"**{DASHBOARD}/login")
    page.goto(f"{server.url}{DASHBOARD}/records/{record_id}")
    assert "/login?next=" in page.url, "after logging out the pages are closed again"


def test_a_vector_verdict_shows_each_channels_residual(page, server: LiveServer):
    """A record of three sensors inspected by vector modes: its page draws one residual chart per
    channel, each of the residual's N − p samples, and the verdict's per-channel RMS."""
    site = build_site(server)
    x, y = chain_record("k2", 6.0, 900)
    with site.org.client("ingest") as ingest:
        uploaded = ingest.post(
            f"/api/v1/structures/{site.structure_id}/records?inspect=true", json=channels_body(x, y)
        )
    assert uploaded.status_code == 201, uploaded.text
    record_id = uploaded.json()["id"]
    page.goto(f"{server.url}{DASHBOARD}/records/{record_id}")
    log_in(page, site.org.keys["viewer"])
    page.wait_for_url(f"**{DASHBOARD}/records/{record_id}")
    for name in NAMES:
        assert drawn(page, f"residual-{name}")["points"] == [len(x) - 2]
    assert "a1, a2, a3" in page.content() and "Hosking" in page.locator("#vector-note").inner_text()
    shot(page, "6-record-channels")


def test_a_structure_judged_by_its_baseline_alone_trends_its_severity(page, server: LiveServer):
    """A chain structure with a healthy baseline and no fault mode: its page shows it standing at
    anomaly and draws each verdict's severity against the healthy level 1; a record's page shows the
    baseline's figures."""
    org = Org.create(server)
    with clients(org) as (admin, ingest, _):
        structure_id, _ = chain_baseline(admin, ingest, healthy_training())
        judged = [record(scenario(), SAMPLES, 50_000 + i) for i in range(3)]
        judged += [record(scenario("k2", 8.0), SAMPLES, 60_000 + i) for i in range(3)]
        uploaded = [upload(ingest, structure_id, x, y, inspect="true") for x, y in judged]
    assert uploaded[-1]["verdict"]["status"] == "anomaly"
    page.goto(f"{server.url}{DASHBOARD}/structures/{structure_id}")
    log_in(page, org.keys["viewer"])
    page.wait_for_url(f"**{DASHBOARD}/structures/{structure_id}")
    assert page.locator("#standing .badge").inner_text() == "anomaly"
    assert "severity (healthy: 1)" in page.locator("#standing").inner_text().lower()
    # No k̂ and no fault mode's Q to draw: those charts are left out, not drawn empty.
    assert page.locator("#chart-k_hat, #chart-q").count() == 0
    severity = drawn(page, "severity")
    assert severity["points"][:2] == [6, 2]  # a point per verdict, the healthy level's two ends
    assert "healthy level (1)" in page.locator("#chart-severity").inner_text()
    shot(page, "7-structure-severity")
    page.goto(f"{server.url}{DASHBOARD}/records/{uploaded[-1]['id']}")
    figures = page.locator("#novelty").inner_text()
    assert "severity (healthy: 1)" in figures.lower() and "settled" in figures
    assert "healthy baseline's judgement alone" in page.locator("#baseline-only").inner_text()


def test_the_demo_structure_s_first_screen_shows_its_status_then_its_charts(browser, server: LiveServer):
    """On a 1280×800 screen the demo's structure page opens on its status and its k̂ and Q charts,
    drawn with the CUSUM's threshold and k̂ = 0 named; its alarms (several, for one k2 fault) come
    after the charts instead of pushing them off the first screen."""
    org, structure_id = demo_structure(server)
    context = browser.new_context(viewport={"width": 1280, "height": 800})
    context.set_default_timeout(TIMEOUT_MS)
    page = context.new_page()
    try:
        page.goto(f"{server.url}{DASHBOARD}/structures/{structure_id}")
        log_in(page, org.keys["viewer"])
        page.wait_for_url(f"**{DASHBOARD}/structures/{structure_id}")
        for chart in ("k_hat", "q"):  # drawn without scrolling: they are on the first screen
            page.wait_for_selector(f"#chart-{chart}[data-drawn=true]")
        box = {
            name: page.locator(f"#{name}").bounding_box()
            for name in ("standing", "chart-k_hat", "chart-q", "alarms")
        }
        assert box["standing"]["y"] + box["standing"]["height"] <= box["chart-k_hat"]["y"]
        assert box["chart-k_hat"]["y"] == box["chart-q"]["y"] < 800 / 2, (
            "the charts start in the first screen's upper half"
        )
        assert box["alarms"]["y"] >= box["chart-k_hat"]["y"] + box["chart-k_hat"]["height"]
        drawn_text = page.locator("#chart-k_hat").inner_text()
        assert "CUSUM threshold h =" in drawn_text and "k̂ = 0 (no fault)" in drawn_text
        assert "Q critical (α = 0.05)" in page.locator("#chart-q").inner_text()
        folder = ARTIFACTS / "dashboard"
        folder.mkdir(parents=True, exist_ok=True)
        page.screenshot(path=folder / "10-demo-first-screen.png")  # the first screen only
        shot(page, "10-demo-structure")
    finally:
        context.close()


def test_a_wrong_key_stays_on_the_login_page_with_the_reason(page, server: LiveServer):
    page.goto(f"{server.url}{DASHBOARD}/login")
    log_in(page, "nw_000000000000_not-a-real-key")
    page.wait_for_selector(".error")
    assert "not valid" in page.locator(".error").inner_text()
    assert page.context.cookies() == [], "no session cookie for a refused key"
    shot(page, "5-refused")


def test_a_refinement_on_several_records_shows_each_test_record_and_each_criterion(page, server: LiveServer):
    """Two records fitted, two judged: the page names the records fitted, gives each judged record
    its declared and refined errors and whether it lies within the data fitted, and says which
    criterion decided each effect. Records of 3000 samples: what the page shows of the loop, not
    what the loop finds on longer ones, is checked."""
    org = Org.create(server)
    with clients(org) as (admin, ingest, _):
        structure_id = create_structure(admin, "rig refined on several records")["id"]
        ids = []
        for seed in range(4):
            # The last record judged is driven twice as hard as those fitted.
            scenario = Scenario(
                excitation_std=50e3 if seed == 3 else 25e3,
                disturbance_std=200.0,
                effects=Effects.parse(["quadratic_stiffness2=3e5"]),
            )
            record = simulate(scenario, 3000, np.random.SeedSequence([53, seed]))
            body = npz_bytes(x=record.x, y=record.y, fs=record.fs)
            ids.append(post_record(ingest, structure_id, body, "application/x-npz").json()["id"])
        baseline = admin.post(
            f"{API}/structures/{structure_id}/models/baseline",
            json={"record_ids": ids[:1], "terms": RIG_TERMS},
        )
        body = {"record_ids": ids[:2], "test_record_ids": ids[2:], "base_model_id": baseline.json()["id"]}
        response = admin.post(f"{API}/structures/{structure_id}/refinements", json=body)
        assert response.status_code == 201, response.text
        refinement = response.json()
    report = refinement["report"]
    assert report["effects_added"]
    page.goto(f"{server.url}{DASHBOARD}/login")
    log_in(page, org.keys["viewer"])
    page.wait_for_url(f"{server.url}{DASHBOARD}")
    page.goto(f"{server.url}{DASHBOARD}/refinements/{refinement['id']}")
    for record_id in ids[:2]:
        assert page.locator(f"p.muted a[href='/dashboard/records/{record_id}']").count() == 1
    rows = page.locator("#errors tbody tr")
    assert rows.count() == 4, "a declared and a refined row for each record judged"
    # The report's notes, here that two records were fitted and no periodic disturbance sought.
    assert report["notes"] and page.locator("#notes li").all_inner_texts() == report["notes"]
    for number, (record_id, test) in enumerate(zip(ids[2:], report["tests"], strict=True)):
        declared, refined = rows.nth(2 * number), rows.nth(2 * number + 1)
        assert f"record {record_id}" in declared.inner_text()
        for row, figures in ((declared, test["before"]), (refined, test["after"])):
            assert f"{figures['free_run_rms']:.4g}" in row.inner_text()
    coverage = page.locator("#errors td.coverage").all_inner_texts()
    assert [test["coverage"]["extrapolates"] for test in report["tests"]] == [False, True]
    assert coverage == [
        "within the estimation records' band and range",
        f"extrapolates: {report['tests'][1]['coverage']['description']}",
    ]
    criteria = page.locator("#effects td.criterion").all_inner_texts()
    assert criteria == [effect["decided_by"] for effect in report["effects_added"]]
    drawn(page, "errors")
    shot(page, "6-refinement")


def test_a_refinement_on_a_periodic_record_states_the_noise_floor(page, server: LiveServer):
    """A record that repeats a multisine six times through a second-order system with white
    output noise 0.3, refined from the right linear model: the page says, in view, what noise no
    model can simulate, the noise floor the refinement found on its estimation part (four
    periods, the first left out), with its figure, and that the check figure is at it. (A record
    that does not repeat shows none: tests/test_dashboard.py.)"""
    from harness.multisines import PERIOD, measured

    org = Org.create(server)
    x, _, y = measured(periods=6, sigma=0.3, seed=12)
    with clients(org) as (admin, ingest, _):
        structure_id = create_structure(admin, "periodic rig")["id"]
        body = npz_bytes(x=x, y=y, fs=FS)
        record_id = post_record(ingest, structure_id, body, "application/x-npz").json()["id"]
        baseline = admin.post(
            f"{API}/structures/{structure_id}/models/baseline",
            json={"record_ids": [record_id], "terms": ["y[t-1]", "y[t-2]", "x[t-1]", "x[t-2]"]},
        )
        body = {"record_id": record_id, "base_model_id": baseline.json()["id"]}
        refinement = admin.post(f"{API}/structures/{structure_id}/refinements", json=body).json()
    figures = refinement["report"]["noise_floor"]
    assert (figures["periods"], figures["period"]) == (3, PERIOD)
    page.goto(f"{server.url}{DASHBOARD}/login")
    log_in(page, org.keys["viewer"])
    page.wait_for_url(f"{server.url}{DASHBOARD}")
    page.goto(f"{server.url}{DASHBOARD}/refinements/{refinement['id']}")
    floor = page.locator("#noise-floor")
    assert floor.is_visible()
    text = " ".join(floor.inner_text().split())
    assert f"the checked records' periods (3 of {PERIOD} samples)" in text, text
    assert f"is {figures['rms']:.4g} ± {figures['standard_error']:.2g}" in text, text
    assert "the check figure is at that floor" in text, text
    shot(page, "6-refinement-noise-floor")


def test_an_alarm_appears_after_uploads_is_acknowledged_then_resolved(page, server: LiveServer):
    """Healthy records, then a k2 fault: the persistence and CUSUM rules raise alarms that an admin
    sees at the top of the fleet page, acknowledges there with a note, and resolves on the
    structure's page, whose k̂ chart draws the CUSUM, its threshold and where the alarms began."""
    org = Org.create(server)
    rules = [{"kind": "persistence", "k": 2, "m": 3}, {"kind": "cusum"}]
    with clients(org) as (admin, ingest, _):
        structure = create_structure(admin, "rig that develops a fault")
        train_fault_mode(admin, ingest, structure["id"], "k2", seed=71, magnitudes=CUSUM_TRAINING_K)
        response = admin.put(f"{API}/structures/{structure['id']}/alarm-rules", json={"rules": rules})
        assert response.status_code == 200, response.text
        for index, k in enumerate([0.0] * 3 + [25.0] * 3):
            acquired = FIRST_RECORD + dt.timedelta(hours=6 * index)
            record = simulated("k2", k, [71, 200 + index], RECORD_SAMPLES)
            upload_simulated(
                ingest, structure["id"], record, inspect="true", acquired_at=acquired.isoformat()
            )
    page.goto(f"{server.url}{DASHBOARD}/login")
    log_in(page, org.keys["admin"])
    page.wait_for_url(f"{server.url}{DASHBOARD}")

    alarms = page.locator("#alarm-table tbody tr")
    assert alarms.count() == 2, "one alarm per rule, however many records fired"
    persistence = page.locator("#alarm-table tr", has_text="of the last 3 verdicts")
    assert persistence.get_attribute("class") == "alarm-open"
    shot(page, "7-fleet-alarms")
    persistence.locator("form.acknowledge input[name=note]").fill("crew sent to bay 3")
    persistence.locator("form.acknowledge button").click()
    page.wait_for_url(f"{server.url}{DASHBOARD}")
    persistence = page.locator("#alarm-table tr", has_text="of the last 3 verdicts")
    assert persistence.get_attribute("class") == "alarm-acknowledged"
    assert "crew sent to bay 3" in persistence.inner_text()
    assert persistence.locator("form.acknowledge").count() == 0, "acknowledged once"

    page.click(f"#fleet a:text('{structure['name']}')")
    page.wait_for_url(f"**{DASHBOARD}/structures/{structure['id']}")
    chart = drawn(page, "k_hat")
    names = page.evaluate("() => document.getElementById('chart-k_hat').data.map((t) => t.name)")
    assert "CUSUM (k2)" in names and any(n.startswith("CUSUM threshold") for n in names)
    assert {"alarm raised (open)", "alarm raised (acknowledged)", "drift began (CUSUM)"} <= set(names)
    legend = page.locator("#chart-k_hat .legend").text_content() or ""
    for entry in ("healthy", "faulty", "unknown fault", "alarm raised (open)", "alarm raised (acknowledged)"):
        assert entry in legend, f"the legend explains {entry!r}"
    assert chart["points"][0] == 6, "six k̂ markers"
    shot(page, "8-structure-alarms")
    for _ in range(2):
        row = page.locator("#alarm-table tbody tr").first
        row.locator("form.resolve input[name=note]").fill("stiffener replaced")
        row.locator("form.resolve button").click()
        page.wait_for_url(f"**{DASHBOARD}/structures/{structure['id']}")
    assert page.locator("#no-alarms").is_visible()
    with org.client("viewer") as viewer:
        listed = viewer.get(f"{API}/alarms", params={"structure_id": structure["id"]}).json()["items"]
    assert [(a["state"], a["resolution"], a["resolution_note"]) for a in listed] == [
        ("resolved", "by_hand", "stiffener replaced")
    ] * 2
    shot(page, "9-structure-resolved")
