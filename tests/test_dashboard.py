"""The dashboard over HTTP: logins, isolation between organisations, and pages whose figures
agree with the history API and with an independent recomputation. On SQLite; what the database
keeps for a page (the sessions a logout ends, the verdicts' times and figures charted) on
PostgreSQL too (``database_monitored``).

The structure watched was healthy, then developed a k2 fault (harness/dashboard_helpers.py); every
record went through the real inspection chain on upload.
"""

from __future__ import annotations

import datetime as dt
import re
from pathlib import Path

import httpx
import numpy as np
import plotly
import pytest
from markupsafe import escape
from sqlalchemy import update

from harness.api_helpers import (
    API,
    FS,
    RIG_TERMS,
    Org,
    clients,
    create_structure,
    simulated,
    train_fault_mode,
    upload_simulated,
)
from harness.dashboard_helpers import (
    COOKIE,
    DASHBOARD,
    FAULT_K,
    Monitored,
    charts,
    demo_structure,
    logged_in,
    monitored_structure,
)
from harness.live import DATABASES, LiveServer, http_client, on_each_database
from models.alarms import DESIGN_SHIFT, in_control_arl
from recordfiles.quantities import SignalDeclaration
from service.dashboard.auth import form_token
from service.dashboard.figures import channel_figures, refinement_figure
from service.dashboard.views import STRUCTURE_ALARMS
from service.domain.alarms import MAX_THRESHOLD
from service.tables import ApiKey, utcnow

PAGE_SIZE = 25  # service.dashboard.views.HISTORY_PAGE


@pytest.fixture(scope="module")
def api_server(sqlite_api_server: LiveServer) -> LiveServer:
    return sqlite_api_server


@pytest.fixture(scope="module")
def monitored(api_server: LiveServer) -> Monitored:
    return monitored_structure(api_server, seed=41)


@pytest.fixture(scope="module", params=DATABASES)
def database_monitored(request: pytest.FixtureRequest) -> Monitored:
    """The monitored structure on each database."""
    return on_each_database(request, "monitored", lambda server: monitored_structure(server, seed=41))


@pytest.fixture
def viewer(api_server: LiveServer, monitored: Monitored) -> httpx.Client:
    with logged_in(api_server, monitored.org.keys["viewer"]) as client:
        yield client


def parse(text: str) -> dt.datetime:
    return dt.datetime.fromisoformat(text.replace("Z", "+00:00"))


def ms(text: str) -> float:
    return parse(text).timestamp() * 1000.0


def row_ids(page: httpx.Response | str, attribute: str) -> list[int]:
    text = page if isinstance(page, str) else page.text
    return [int(found) for found in re.findall(rf'{attribute}="(\d+)"', text)]


# --- logging in and out ---------------------------------------------------------------------


def test_a_logged_out_visitor_is_sent_to_the_login_page(api_server: LiveServer, monitored: Monitored):
    structure_id, record_id = monitored.structure["id"], monitored.records[0]["id"]
    with http_client(base_url=api_server.url) as anonymous:
        for path in (
            DASHBOARD,
            f"{DASHBOARD}/structures/{structure_id}?status=faulty",
            f"{DASHBOARD}/records/{record_id}",
            f"{DASHBOARD}/refinements/1",
        ):
            response = anonymous.get(path)
            assert response.status_code == 303, path
            location = httpx.URL(response.headers["location"])
            assert location.path == f"{DASHBOARD}/login"
            assert location.params["next"] == path, "after logging in the visitor comes back here"
            assert structure_id and monitored.structure["name"] not in response.text
        anonymous.cookies.set(COOKIE, "forged-or-expired")
        response = anonymous.get(DASHBOARD)
        assert response.status_code == 303 and "/login" in response.headers["location"]
        login_page = anonymous.get(f"{DASHBOARD}/login")
        assert login_page.status_code == 200 and 'name="api_key"' in login_page.text


def test_logging_in_sets_a_secure_http_only_cookie_that_is_not_the_key(
    api_server: LiveServer, monitored: Monitored
):
    key = monitored.org.keys["viewer"]
    with http_client(base_url=api_server.url) as client:
        wanted = f"{DASHBOARD}/structures/{monitored.structure['id']}"
        response = client.post(f"{DASHBOARD}/login", data={"api_key": key, "next": wanted})
    assert response.status_code == 303 and response.headers["location"] == wanted
    cookie = response.headers["set-cookie"]
    attributes = {part.strip().split("=")[0].lower() for part in cookie.split(";")}
    assert {"httponly", "secure", "samesite", "path", "max-age"} <= attributes
    assert "samesite=lax" in cookie.lower() and f"path={DASHBOARD}" in cookie.lower()
    token = response.cookies[COOKIE]
    assert len(token) >= 40 and token not in key and key.split("_", 2)[2] not in cookie


@pytest.mark.parametrize(
    "key",
    ["", "nw_deadbeef0000_" + "x" * 43, "not a key at all", "Bearer nw_x_y", "nw_" + "x" * 5000],
    ids=["empty", "unknown", "malformed", "header", "oversize"],
)
def test_a_bad_key_is_refused_with_a_message_and_no_session(api_server: LiveServer, key: str):
    with http_client(base_url=api_server.url) as client:
        response = client.post(f"{DASHBOARD}/login", data={"api_key": key, "next": DASHBOARD})
        assert response.status_code in (401, 422)
        assert COOKIE not in response.cookies
        assert "API key" in response.text or "api_key" in response.text
        assert client.get(DASHBOARD).status_code == 303


def test_every_role_may_log_in(api_server: LiveServer, monitored: Monitored):
    for role in ("viewer", "ingest", "admin"):
        with logged_in(api_server, monitored.org.keys[role]) as client:
            page = client.get(DASHBOARD)
            assert page.status_code == 200 and f"· {role}" in page.text


def test_next_never_leads_off_the_dashboard(api_server: LiveServer, monitored: Monitored):
    key = monitored.org.keys["viewer"]
    with http_client(base_url=api_server.url) as client:
        for target in (
            "https://evil.example/dashboard",
            "//evil.example/x",
            "/api/v1/structures",
            "/dashboardx",
        ):
            response = client.post(f"{DASHBOARD}/login", data={"api_key": key, "next": target})
            assert response.status_code == 303 and response.headers["location"] == DASHBOARD, target


def test_logging_out_ends_the_session_on_the_server(database_monitored: Monitored):
    api_server = database_monitored.org.server
    client = logged_in(api_server, database_monitored.org.keys["viewer"])
    token = client.cookies[COOKIE]
    with client:
        assert client.get(DASHBOARD).status_code == 200
        response = client.post(f"{DASHBOARD}/logout")
        assert response.status_code == 303 and response.headers["location"] == f"{DASHBOARD}/login"
        assert (
            f"{COOKIE}=" in response.headers["set-cookie"]
            and "max-age=0" in response.headers["set-cookie"].lower()
        )
    with http_client(base_url=api_server.url, cookies={COOKIE: token}) as replay:
        assert replay.get(DASHBOARD).status_code == 303, "a cookie kept after logout opens nothing"


def test_a_form_posted_from_another_site_is_refused(api_server: LiveServer, monitored: Monitored):
    with logged_in(api_server, monitored.org.keys["viewer"]) as client:
        response = client.post(f"{DASHBOARD}/logout", headers={"Origin": "https://evil.example"})
        assert response.status_code == 403 and "dashboard itself" in response.text
        assert client.get(DASHBOARD).status_code == 200, "the refused logout ended nothing"


def test_revoking_the_key_ends_its_logins(api_server: LiveServer):
    org = Org.create(api_server)
    with logged_in(api_server, org.keys["viewer"]) as client:
        assert client.get(DASHBOARD).status_code == 200
        prefix = org.keys["viewer"].split("_")[1]
        with api_server.app.state.sessions() as session:
            session.execute(update(ApiKey).where(ApiKey.prefix == prefix).values(revoked_at=utcnow()))
            session.commit()
        assert client.get(DASHBOARD).status_code == 303


def test_plotly_js_is_served_from_the_installed_package(api_server: LiveServer):
    with http_client(base_url=api_server.url) as anonymous:
        response = anonymous.get(f"{DASHBOARD}/static/plotly.min.js")
    assert response.status_code == 200 and "javascript" in response.headers["content-type"]
    assert response.content == (Path(plotly.__file__).parent / "package_data" / "plotly.min.js").read_bytes()


# --- what a page may load, where it may lead, and who may frame or keep it ---------------------

FORGED_HOST = "attacker.example"
LINKS = re.compile(r'(?:href|src|action)="([^"]*)"')
SCRIPTS = re.compile(r"<script([^>]*)>", re.S)


def dashboard_pages(monitored: Monitored) -> list[str]:
    return [
        DASHBOARD,
        f"{DASHBOARD}/structures/{monitored.structure['id']}",
        f"{DASHBOARD}/records/{monitored.records[-1]['id']}",
        f"{DASHBOARD}/records/999999999",  # the error page
    ]


def assert_relative_links(page: httpx.Response) -> None:
    assert FORGED_HOST not in page.text
    for url in LINKS.findall(page.text):
        assert not httpx.URL(url).is_absolute_url and not url.startswith("//"), url


def test_a_forged_host_header_never_becomes_a_link_or_a_redirect(
    api_server: LiveServer, monitored: Monitored, viewer: httpx.Client
):
    forged = {"Host": FORGED_HOST}
    with http_client(base_url=api_server.url, headers=forged) as anonymous:
        redirect = anonymous.get(DASHBOARD)
        assert redirect.status_code == 303 and redirect.headers["location"].startswith(f"{DASHBOARD}/login")
        assert_relative_links(anonymous.get(f"{DASHBOARD}/login"))
        login = anonymous.post(
            f"{DASHBOARD}/login", data={"api_key": monitored.org.keys["viewer"], "next": DASHBOARD}
        )
        assert login.status_code == 303 and login.headers["location"] == DASHBOARD
    for path in dashboard_pages(monitored):
        assert_relative_links(viewer.get(path, headers=forged))
    logout = viewer.post(f"{DASHBOARD}/logout", headers=forged)
    assert logout.status_code == 303 and logout.headers["location"] == f"{DASHBOARD}/login"


def test_pages_forbid_framing_caching_inline_and_foreign_scripts(
    api_server: LiveServer, monitored: Monitored, viewer: httpx.Client
):
    with http_client(base_url=api_server.url) as anonymous:
        pages = [anonymous.get(f"{DASHBOARD}/login")] + [viewer.get(p) for p in dashboard_pages(monitored)]
    for page in pages:
        policy = {
            directive.split()[0]: directive.split()[1:]
            for directive in page.headers["content-security-policy"].split(";")
            if directive.strip()
        }
        webgl = '"scattergl"' in page.text  # regl compiles WebGL programs with new Function
        assert policy["script-src"] == (["'self'", "'unsafe-eval'"] if webgl else ["'self'"]), page.url
        assert policy["default-src"] == ["'self'"] and policy["object-src"] == ["'none'"]
        assert policy["frame-ancestors"] == ["'none'"] and policy["base-uri"] == ["'none'"]
        assert policy["form-action"] == ["'self'"]
        assert page.headers["x-frame-options"] == "DENY"
        assert page.headers["cache-control"] == "no-store"
        assert page.headers["referrer-policy"] == "same-origin"
        assert page.headers["x-content-type-options"] == "nosniff"
        for attributes in SCRIPTS.findall(page.text):
            assert "src=" in attributes or 'type="application/json"' in attributes, "no inline script runs"
    record_page = pages[3]
    assert '"scattergl"' in record_page.text, "the record page's 2000 samples are drawn with WebGL"


# --- organisations ----------------------------------------------------------------------------


def test_another_organisations_structures_never_appear(api_server: LiveServer, monitored: Monitored):
    other = Org.create(api_server)
    with clients(other) as (admin, _, _):
        theirs = create_structure(admin, "their secret rig")
    with logged_in(api_server, other.keys["viewer"]) as client:
        fleet = client.get(DASHBOARD)
        assert "their secret rig" in fleet.text and monitored.structure["name"] not in fleet.text
        assert row_ids(fleet, "data-structure-id") == [theirs["id"]]
        for path in (
            f"/structures/{monitored.structure['id']}",
            f"/records/{monitored.records[0]['id']}",
        ):
            response = client.get(DASHBOARD + path)
            assert response.status_code == 404, path
            assert monitored.structure["name"] not in response.text and "not found" in response.text.lower()


# --- pages ----------------------------------------------------------------------------------


def test_the_fleet_page_shows_each_structure_where_it_stands(viewer: httpx.Client, monitored: Monitored):
    page = viewer.get(DASHBOARD)
    assert page.status_code == 200
    assert row_ids(page, "data-structure-id") == [monitored.structure["id"]]
    latest = monitored.verdicts[0]
    row = page.text[page.text.index("data-structure-id") :]
    assert f'class="status-{latest["status"]}"' in page.text[: page.text.index("data-structure-id") + 40]
    low, high = latest["interval"]
    assert f"{latest['k_hat']:.3g} %" in row and f"[{low:.3g}, {high:.3g}]" in row
    assert latest["fault_mode"] == "k2" and ">k2<" in row
    assert _since(monitored.verdicts).strftime("%Y-%m-%d %H:%M:%S UTC") in row


def _since(verdicts: list[dict]) -> dt.datetime:
    """When the current status began, worked out from the history API's list (newest first)."""
    current = verdicts[0]["status"]
    run = []
    for verdict in verdicts:
        if verdict["status"] != current:
            break
        run.append(verdict)
    return parse(run[-1]["acquired_at"])


def test_the_structure_page_charts_every_verdict(database_monitored: Monitored):
    monitored = database_monitored
    with logged_in(monitored.org.server, monitored.org.keys["viewer"]) as viewer:
        page = viewer.get(f"{DASHBOARD}/structures/{monitored.structure['id']}")
    assert page.status_code == 200
    figures = charts(page)
    oldest_first = monitored.verdicts[::-1]
    # An unknown fault has no magnitude: it is left off the k̂ chart, and only that chart.
    estimated = [v for v in oldest_first if v["k_hat"] is not None]
    traces = {trace["name"]: trace for trace in figures["k_hat"]["data"]}
    k_hat = traces["k̂ (k2 model)"]  # one reference mode: k2
    assert k_hat["x"] == [ms(v["acquired_at"]) for v in estimated]
    assert k_hat["y"] == [v["k_hat"] for v in estimated]
    np.testing.assert_allclose(k_hat["error_y"]["array"], [v["interval"][1] - v["k_hat"] for v in estimated])
    np.testing.assert_allclose(
        k_hat["error_y"]["arrayminus"], [v["k_hat"] - v["interval"][0] for v in estimated]
    )
    assert max(k_hat["y"]) == pytest.approx(FAULT_K, abs=2.0)
    # The markers' colours are explained: a legend entry (without points) per status.
    for status in ("healthy", "faulty", "unknown fault"):
        assert traces[status]["x"] == [None] and traces[status]["legendgroup"] == "status"
    # The default CUSUM on z = k̂/σ̂k, as Page defined it, restarted after each signal (its design
    # assumes the restart), against the threshold the alarm rules' API reports.
    with monitored.org.client("viewer") as api:
        design = api.get(f"{API}/structures/{monitored.structure['id']}/alarm-rules").json()["cusum_design"]
        alarms = api.get(f"{API}/alarms", params={"structure_id": monitored.structure["id"]}).json()["items"]
    statistic, upper, lower = [], 0.0, 0.0
    for verdict in oldest_first:
        z = verdict["modes"][0]["k_hat"] / verdict["modes"][0]["sigma_k"]
        upper, lower = max(0.0, upper + z - design["reference"]), max(0.0, lower - z - design["reference"])
        statistic.append(max(upper, lower))
        if statistic[-1] > design["threshold"]:
            upper = lower = 0.0
    cusum = traces["CUSUM (k2)"]
    assert cusum["x"] == [ms(v["acquired_at"]) for v in oldest_first] and cusum["yaxis"] == "y2"
    np.testing.assert_allclose(cusum["y"], statistic)
    threshold = traces[f"CUSUM threshold h = {design['threshold']:.2f} σ"]
    assert threshold["y"] == [design["threshold"]] * 2
    # Each alarm's line stands where it was raised, in its state's colour; the CUSUM's where its drift began.
    assert {a["state"] for a in alarms} == {"open"} and {a["rule_kind"] for a in alarms} >= {"cusum"}
    raised = traces["alarm raised (open)"]
    assert sorted(x for x in raised["x"] if x is not None)[::2] == sorted(
        ms(a["triggered_at"]) for a in alarms
    )
    drifts = [ms(a["drift_started_at"]) for a in alarms if a["drift_started_at"]]
    assert sorted(x for x in traces["drift began (CUSUM)"]["x"] if x is not None)[::2] == sorted(drifts)
    q, critical = figures["q"]["data"]
    assert q["x"] == [ms(v["acquired_at"]) for v in oldest_first]
    assert q["y"] == [v["modes"][0]["q"] for v in oldest_first]
    assert critical["y"] == [oldest_first[0]["modes"][0]["q_critical"]] * 2
    trajectories = figures["trajectories-k2"]["data"]
    assert len(trajectories) == 3 * 8, "band edges and estimate for each of the eight terms"
    assert "Since" in page.text and _since(monitored.verdicts).strftime("%Y-%m-%d %H:%M:%S") in page.text


def test_the_trajectories_are_the_models_coefficients(viewer: httpx.Client, monitored: Monitored, api_server):
    from models.fnarx import FNARX
    from service.tables import ModelVersion

    figures = charts(viewer.get(f"{DASHBOARD}/structures/{monitored.structure['id']}"))
    with api_server.app.state.sessions() as session:
        version = (
            session.query(ModelVersion).filter_by(structure_id=monitored.structure["id"], name="k2").one()
        )
        model = FNARX.from_document(version.document)
    estimate = figures["trajectories-k2"]["data"][2::3]
    for index, trace in enumerate(estimate):
        k = np.array(trace["x"])
        assert k[0] == model.basis.k_min and k[-1] == model.basis.k_max
        theta = model.theta[index] @ np.array([model.basis.values(kk) for kk in k]).T
        np.testing.assert_allclose(trace["y"], theta, rtol=1e-12)


# --- the structure page: its status first, alarms that say why ------------------------------


def _between(text: str, start: str, end: str) -> str:
    """The page's text from the element with id ``start`` to the next ``end`` after it ("" for none)."""
    opening = text.find(f'id="{start}"')
    return "" if opening < 0 else text[opening : text.index(end, opening)]


def test_the_structure_page_opens_on_its_status_then_charts_then_alarms_that_say_why(
    api_server: LiveServer,
):
    """The demo's growing k2 fault, then records of a k1 fault: alarms of both modes. The page gives
    the status first (with the alarms' count and the declared signals), then the charts, then the
    alarms: a few in view, open ones first, the rest folded; the k2 CUSUM's row and a line below
    the table say, in the rules' own words, why the newest record (localised to k1) does not step
    it."""
    org, structure_id = demo_structure(api_server)
    with org.client("ingest") as ingest:
        k1 = [
            upload_simulated(ingest, structure_id, simulated("k1", 10.0, [71, i]), inspect="true")
            for i in range(3)
        ]
    newest = k1[-1]["verdict"]
    assert (newest["status"], newest["fault_mode"]) == ("faulty", "k1"), newest
    with logged_in(api_server, org.keys["viewer"]) as client:
        page = client.get(f"{DASHBOARD}/structures/{structure_id}")
    assert page.status_code == 200
    with org.client("viewer") as api:
        rules = api.get(f"{API}/structures/{structure_id}/alarm-rules").json()
        listed = api.get(f"{API}/alarms", params={"structure_id": structure_id}).json()["items"]
    text = page.text
    places = [
        text.index(f'id="{name}"') for name in ("standing", "chart-k_hat", "chart-q", "alarms", "verdicts")
    ]
    assert places == sorted(places), "status, charts, alarms, verdicts: in that order"
    standing = _between(text, "standing", "</section>")
    unresolved = sorted((a for a in listed if a["state"] != "resolved"), key=lambda a: a["id"])
    assert len(unresolved) > STRUCTURE_ALARMS and {a["state"] for a in unresolved} == {"open"}
    assert f"{len(unresolved)} open · 0 acknowledged" in standing
    assert 'id="signals"' in standing and "force x [N]" in standing
    # A few alarms in view, the oldest first; the rest folded below them, none left out.
    shown = row_ids(_between(text, "alarm-table", "</table>"), "data-alarm-id")
    folded = row_ids(_between(text, "folded-alarms", "</details>"), "data-alarm-id")
    assert shown == [a["id"] for a in unresolved[:STRUCTURE_ALARMS]]
    assert folded == [a["id"] for a in unresolved[STRUCTURE_ALARMS:]]
    # The newest record is localised to k1: k2's CUSUM is not stepped, and the rules and page say why.
    assert (
        list(rules["cusum_skipped"]) == ["k2"]
        and "localised to fault mode 'k1'" in rules["cusum_skipped"]["k2"]
    )
    reasons = _between(text, "alarm-reasons", "</ul>")
    assert 'data-fault-mode="k2"' in reasons and str(escape(rules["cusum_skipped"]["k2"])) in reasons
    (k2,) = [a for a in unresolved if a["rule_kind"] == "cusum" and a["fault_mode"] == "k2"]
    row = text[text.index(f'data-alarm-id="{k2["id"]}"') :]
    assert "does not step this CUSUM" in row[: row.index("</tr>")]


def test_every_reference_line_is_named_in_its_chart(api_server: LiveServer):
    """A threshold or reference line is named where it runs (an annotation on its own axis, at its
    level), as in the legend: the CUSUM's threshold, on its axis, no longer reads as k̂ = 0, which is
    named too; and each axis says its unit."""
    org, structure_id = demo_structure(api_server)
    with logged_in(api_server, org.keys["viewer"]) as client:
        figures = charts(client.get(f"{DASHBOARD}/structures/{structure_id}"))
    with org.client("viewer") as api:
        design = api.get(f"{API}/structures/{structure_id}/alarm-rules").json()["cusum_design"]
    levels = 0
    for name, figure in figures.items():
        layout = figure["layout"]
        labels = [(a["text"], a["yref"], a["y"]) for a in layout.get("annotations", []) if "yref" in a]
        for trace in figure["data"]:
            y = trace["y"]
            if trace.get("mode") != "lines" or len(y) != 2 or y[0] != y[1] or y[0] is None:
                continue
            axis = trace.get("yaxis", "y")
            on_log = layout[axis.replace("y", "yaxis")].get("type") == "log"
            level = np.log10(y[0]) if on_log else y[0]
            assert any(
                text == trace["name"] and yref == axis and at == pytest.approx(level)
                for text, yref, at in labels
            ), f"{name}: the line {trace['name']!r} is not named in the chart"
            levels += 1
    assert levels == 2, "the CUSUM threshold and the Q critical value"
    k_hat = figures["k_hat"]["layout"]
    threshold = f"CUSUM threshold h = {design['threshold']:.2f} σ"
    assert ("k̂ = 0 (no fault)", "y", 0.0) in [(a["text"], a["yref"], a["y"]) for a in k_hat["annotations"]]
    assert (threshold, "y2", design["threshold"]) in [
        (a["text"], a["yref"], a["y"]) for a in k_hat["annotations"]
    ]
    assert k_hat["yaxis"]["title"]["text"] == "k̂ [%]"
    assert k_hat["yaxis2"]["title"]["text"] == "CUSUM [σ]"
    # k̂ and the CUSUM in panels of their own: the threshold's scale never lies over k̂'s.
    assert k_hat["yaxis2"]["domain"][1] < k_hat["yaxis"]["domain"][0] and "overlaying" not in k_hat["yaxis2"]
    # k1's and k2's Q have one critical value (the same lags): one line, named once.
    assert [t["name"] for t in figures["q"]["data"] if t["mode"] == "lines"] == ["Q critical (α = 0.05)"]


def test_an_alarm_whose_rule_stopped_running_is_listed_resolved_with_the_reason(api_server: LiveServer):
    """Open alarms come before acknowledged ones. When the CUSUM can no longer be designed for the
    structure's models, its alarm is resolved as ``rule_not_running``: the page says the CUSUM does
    not run and why, and lists the alarm among the resolved ones with that reason in words."""
    monitored = monitored_structure(api_server, seed=43)
    structure_id = monitored.structure["id"]
    url = f"{API}/structures/{structure_id}/alarm-rules"
    with clients(monitored.org) as (admin, _, viewer):
        unresolved = viewer.get(f"{API}/alarms", params={"structure_id": structure_id}).json()["items"]
        oldest = min(a["id"] for a in unresolved if a["rule_kind"] != "cusum")  # the CUSUM's stops
        assert admin.post(f"{API}/alarms/{oldest}/acknowledge", json={"note": "on it"}).status_code == 200
        answer = viewer.get(url).json()
        reach = in_control_arl(MAX_THRESHOLD, DESIGN_SHIFT / 2, answer["cusum_design"]["common_share"])
        rules = [r for r in answer["rules"] if r["kind"] != "cusum"]
        strict = {"kind": "cusum", "false_alarms_per_year": 365 * 4.0 / (10 * reach)}
        stored = admin.put(url, json={"rules": [*rules, strict]})
        assert stored.status_code == 200, stored.text
        problem = stored.json()["cusum_problem"]
    with logged_in(api_server, monitored.org.keys["viewer"]) as client:
        text = client.get(f"{DASHBOARD}/structures/{structure_id}").text
    in_view = _between(text, "alarm-table", "</table>")
    states = re.findall(r'<tr class="alarm-(\w+)"', in_view)
    assert states and states == sorted(states, key=lambda state: state != "open"), states
    assert f'data-alarm-id="{oldest}"' in in_view and states[-1] == "acknowledged"
    assert str(escape(problem)) in _between(text, "cusum-problem", "</li>")
    resolved = _between(text, "resolved-alarms", "</details>")
    (row,) = re.findall(
        r'<tr data-alarm-id="\d+" data-resolution="rule_not_running">.*?</tr>', resolved, re.S
    )
    assert f"its rule stopped running: {escape(problem)}" in row


def test_the_verdict_table_filters_and_pages_like_the_history_api(
    api_server: LiveServer, monitored: Monitored, viewer: httpx.Client
):
    structure_id = monitored.structure["id"]
    url = f"{DASHBOARD}/structures/{structure_id}"
    everything = viewer.get(url)
    assert row_ids(everything, "data-verdict-id") == [v["id"] for v in monitored.verdicts]
    with clients(monitored.org) as (_, _, api):
        for status in ("healthy", "faulty"):
            page = viewer.get(url, params={"status": status})
            expected = api.get(f"{API}/structures/{structure_id}/verdicts", params={"status": status}).json()
            assert row_ids(page, "data-verdict-id") == [v["id"] for v in expected["items"]]
            assert row_ids(page, "data-verdict-id"), f"the history has {status} verdicts"
    middle = parse(monitored.verdicts[3]["acquired_at"])
    page = viewer.get(url, params={"start": middle.strftime("%Y-%m-%dT%H:%M"), "fault_mode": "k2"})
    assert row_ids(page, "data-verdict-id") == [
        v["id"] for v in monitored.verdicts if parse(v["acquired_at"]) >= middle and v["fault_mode"] == "k2"
    ]


def test_the_verdict_table_pages_through_a_long_history(api_server: LiveServer):
    many = monitored_structure(api_server, seed=43, healthy=15, faulty=PAGE_SIZE - 10)
    with logged_in(api_server, many.org.keys["viewer"]) as client:
        url = f"{DASHBOARD}/structures/{many.structure['id']}"
        first = client.get(url)
        assert row_ids(first, "data-verdict-id") == [v["id"] for v in many.verdicts[:PAGE_SIZE]]
        older = re.search(r'href="\?([^"]+)" id="older"', first.text)
        assert older is not None
        second = client.get(f"{url}?{older.group(1).replace('&amp;', '&')}")
        assert row_ids(second, "data-verdict-id") == [v["id"] for v in many.verdicts[PAGE_SIZE:]]
        assert 'id="older"' not in second.text and 'id="newest"' in second.text


@pytest.mark.parametrize(
    ("params", "fragment"),
    [
        ({"status": "broken"}, "status must be one of"),
        ({"start": "yesterday"}, "not a date and time"),
        ({"end": "0001-01-01T00:00:00+05:00"}, "outside the years 1 to 9999"),
        ({"fault_mode": "k2; drop table"}, "fault mode name"),
        ({"cursor": "bm90LWEtY3Vyc29y"}, "cursor"),
    ],
    ids=["status", "start", "end-out-of-range", "fault-mode", "cursor"],
)
def test_bad_filters_get_a_page_that_says_why(viewer: httpx.Client, monitored: Monitored, params, fragment):
    response = viewer.get(f"{DASHBOARD}/structures/{monitored.structure['id']}", params=params)
    assert response.status_code == 422
    assert "text/html" in response.headers["content-type"] and fragment in response.text


@pytest.mark.parametrize("path", ["/structures/999999", "/records/999999", "/refinements/999999", "/nowhere"])
def test_unknown_ids_get_a_404_page(viewer: httpx.Client, path: str):
    response = viewer.get(DASHBOARD + path)
    assert response.status_code == 404 and "text/html" in response.headers["content-type"]
    assert "Back to the fleet" in response.text


def test_the_record_page_shows_the_fit_the_verdict_was_judged_on(viewer: httpx.Client, monitored: Monitored):
    """The residual drawn is the one whose Ljung–Box Q the verdict holds: Q recomputed here from
    the page's autocorrelation, Q = N(N+2)·Σ ρ̂²(τ)/(N − τ), equals the stored Q."""
    verdict = monitored.verdicts[0]
    page = viewer.get(f"{DASHBOARD}/records/{verdict['record_id']}")
    assert page.status_code == 200
    figures = charts(page)
    measured, predicted = figures["response"]["data"]
    (residual,) = figures["residual"]["data"]
    np.testing.assert_allclose(np.subtract(measured["y"], predicted["y"]), residual["y"], atol=1e-15)
    acf, upper, lower = figures["autocorrelation"]["data"]
    rho = np.array(acf["y"])
    n = len(residual["y"])
    tau = np.arange(1, len(rho) + 1)
    q = n * (n + 2) * np.sum(rho**2 / (n - tau))
    (mode,) = verdict["modes"]
    assert len(rho) == verdict["lags"]
    # The page recomputes e = y − ŷ at the stored k̂ by another product order than the inspection:
    # e is far smaller than y, so each sample carries y's rounding error, ε‖y‖/‖e‖ relative, and
    # Q (a sum of squares of e's autocorrelation) about twice that, summed over the lags.
    cancellation = np.linalg.norm(measured["y"]) / np.linalg.norm(residual["y"])
    assert q == pytest.approx(mode["q"], rel=4 * len(rho) * np.finfo(float).eps * cancellation)
    assert upper["y"] == pytest.approx([1.959963984540054 / np.sqrt(n)] * len(rho))
    assert lower["y"] == pytest.approx([-b for b in upper["y"]])
    assert f"{mode['k_hat']:.4g}" in page.text and verdict["status"] in page.text


def test_the_record_page_labels_y_and_e_as_the_structure_declares_them(
    api_server: LiveServer, monitored: Monitored, viewer: httpx.Client
):
    """A structure that declares its response (acceleration in m/s²) has its record charts'
    axes say so, y with its quantity and e in its unit, and its page says what x and y are; one
    that declares nothing has plain "y" and "e", never the simulated rig's metres."""

    def axes(page: httpx.Response) -> list[str]:
        figures = charts(page)
        return [figures[name]["layout"]["yaxis"]["title"]["text"] for name in ("response", "residual")]

    assert axes(viewer.get(f"{DASHBOARD}/records/{monitored.verdicts[0]['record_id']}")) == ["y", "e"]
    org = Org.create(api_server)
    declared = {
        "excitation": {"quantity": "force", "unit": "N"},
        "response": {"quantity": "acceleration", "unit": "m/s²"},
    }
    with clients(org) as (admin, ingest, _):
        created = admin.post(f"{API}/structures", json={"name": "declared", "fs": FS, **declared})
        assert created.status_code == 201, created.text
        structure_id = created.json()["id"]
        train_fault_mode(admin, ingest, structure_id, "k2", seed=43)
        record = upload_simulated(ingest, structure_id, simulated("k2", 10.0, [43, 7]), inspect="true")
    with logged_in(api_server, org.keys["viewer"]) as client:
        assert axes(client.get(f"{DASHBOARD}/records/{record['id']}")) == [
            "acceleration y [m/s²]",
            "e [m/s²]",
        ]
        structure_page = client.get(f"{DASHBOARD}/structures/{structure_id}")
    assert "force x [N], acceleration y [m/s²]" in structure_page.text


@pytest.mark.parametrize(
    ("declared", "channel", "rms"),
    [
        (SignalDeclaration("strain", "µε"), "e_s1 [µε]", "RMS error of y [µε]"),
        (SignalDeclaration("other"), "e_s1", "RMS error of y"),  # a quantity with no unit stated
        (None, "e_s1", "RMS error of y"),
    ],
)
def test_channel_and_refinement_charts_are_in_the_unit_of_the_response(declared, channel, rms):
    """A vector verdict's channel residuals and a refinement's errors are in the unit the structure
    declares its response (every channel) in, and in none where it states none."""
    residual = np.array([[3.0, 1.0], [-3.0, 1.0]])
    drawn = channel_figures(residual, ["s1", "s2"], FS, 2, 10, "k3 model", declared)["residual-s1"]
    errors = refinement_figure({"one_step_rms": 1.0}, {"one_step_rms": 0.5}, declared)
    assert drawn["layout"]["yaxis"]["title"]["text"] == channel
    unit = f" {declared.unit}" if declared and declared.unit else ""
    assert drawn["layout"]["title"]["text"].endswith(f"(RMS 3{unit})")
    assert errors["layout"]["yaxis"]["title"]["text"] == rms


def test_a_record_without_a_verdict_says_so(
    api_server: LiveServer, monitored: Monitored, viewer: httpx.Client
):
    from harness.api_helpers import simulated, upload_simulated

    with clients(monitored.org) as (_, ingest, _):
        stored = upload_simulated(ingest, monitored.structure["id"], simulated("k2", 0.0, [41, 999], 500))
    page = viewer.get(f"{DASHBOARD}/records/{stored['id']}")
    assert page.status_code == 200 and 'id="no-verdict"' in page.text
    assert 'id="charts"' not in page.text


def test_an_unknown_fault_mode_on_the_record_page_is_refused(viewer: httpx.Client, monitored: Monitored):
    response = viewer.get(f"{DASHBOARD}/records/{monitored.records[0]['id']}", params={"mode": "k9"})
    assert response.status_code == 422 and "no fault mode &#39;k9&#39;; it has k2" in response.text


def test_the_refinement_page_shows_the_effects_found_and_the_errors(api_server: LiveServer):
    from harness.api_helpers import npz_bytes, post_record
    from simulator.simulate import Effects, Scenario, simulate

    org = Org.create(api_server)
    with clients(org) as (admin, ingest, _):
        structure_id = create_structure(admin, "rig to refine")["id"]
        ids = []
        for seed, effects in ((1, []), (2, ["quadratic_stiffness2=3e5"])):
            scenario = Scenario(disturbance_std=200.0, effects=Effects.parse(effects))
            record = simulate(scenario, 12_000, np.random.SeedSequence([43, seed]))
            body = npz_bytes(x=record.x, y=record.y, fs=record.fs)
            ids.append(post_record(ingest, structure_id, body, "application/x-npz").json()["id"])
        baseline = admin.post(
            f"{API}/structures/{structure_id}/models/baseline",
            json={"record_ids": ids[:1], "terms": RIG_TERMS},
        )
        body = {"record_id": ids[1], "base_model_id": baseline.json()["id"]}
        refinement = admin.post(f"{API}/structures/{structure_id}/refinements", json=body).json()
    report = refinement["report"]
    assert report["effects_added"], "the undeclared quadratic stiffness is found"
    with logged_in(api_server, org.keys["viewer"]) as client:
        structure_page = client.get(f"{DASHBOARD}/structures/{structure_id}")
        assert f'href="/dashboard/refinements/{refinement["id"]}"' in structure_page.text
        page = client.get(f"{DASHBOARD}/refinements/{refinement['id']}")
    assert page.status_code == 200
    for effect in report["effects_added"]:
        assert f"<strong>{effect['name']}</strong>" in page.text
    # The record does not repeat: no noise floor (a record that does, tests/test_dashboard_browser.py).
    assert report["noise_floor"] is None and 'id="noise-floor"' not in page.text
    declared, refined = charts(page)["errors"]["data"]
    assert declared["y"] == [report["before"]["one_step_rms"], report["before"]["free_run_rms"]]
    assert refined["y"] == [report["after"]["one_step_rms"], report["after"]["free_run_rms"]]
    assert refined["y"][0] < declared["y"][0]
    # Whether the test part lies within the data fitted: the same record's other part, so it does.
    assert not report["tests"][0]["coverage"]["extrapolates"]
    assert str(escape(report["tests"][0]["coverage"]["description"])) in page.text

    # A report stored before refinements judged several records: one test, as before/after.
    from service.tables import Refinement

    with api_server.app.state.sessions() as session:
        stored = session.get(Refinement, refinement["id"])
        assert stored is not None
        stored.report = {key: value for key, value in stored.report.items() if key != "tests"} | {
            "effects_added": [
                {k: v for k, v in effect.items() if k != "decided_by"} for effect in report["effects_added"]
            ]
        }
        session.commit()
    with logged_in(api_server, org.keys["viewer"]) as client:
        page = client.get(f"{DASHBOARD}/refinements/{refinement['id']}")
    assert page.status_code == 200
    assert f"{report['after']['free_run_rms']:.4g}" in page.text and f"record {ids[1]}" in page.text
    assert "not measured" in page.text  # nor was the coverage of its test part
    assert 'id="withdrawn"' not in page.text

    # A report whose effects the final check took back, then one whose refined model lost to the
    # start on the held-out tails: the page names them, that nothing is kept, and why.
    withdrawn = [effect["name"] for effect in report["effects_added"]]
    for change, why in (
        ({}, "With output-error parameters"),
        ({"held_out": {"refined_returned": False}}, "held-out tails, which no choice of the loop saw"),
    ):
        with api_server.app.state.sessions() as session:
            stored = session.get(Refinement, refinement["id"])
            assert stored is not None
            stored.report = stored.report | {"effects_added": [], "effects_withdrawn": withdrawn} | change
            session.commit()
        with logged_in(api_server, org.keys["viewer"]) as client:
            page = client.get(f"{DASHBOARD}/refinements/{refinement['id']}")
        assert page.status_code == 200
        assert f"Withdrawn: {', '.join(withdrawn)}." in page.text and why in page.text
        assert "No effect was added: the declared model stands." in page.text


def test_a_login_ends_when_it_expires(api_server: LiveServer):
    from service.domain.logins import find_login, open_login

    org = Org.create(api_server)
    with api_server.app.state.sessions() as session:
        lasting = open_login(session, org.keys["viewer"], dt.timedelta(hours=1))
        expired = open_login(session, org.keys["viewer"], dt.timedelta(seconds=-1))
        assert lasting is not None and expired is not None
        found = find_login(session, lasting)
        assert found is not None and found.organisation == org.name
        assert find_login(session, expired) is None
    with http_client(base_url=api_server.url, cookies={COOKIE: expired}) as client:
        assert client.get(DASHBOARD).status_code == 303


# --- alarms (last: acknowledging changes the monitored structure's alarms) -------------------

CSRF = re.compile(r'name="csrf" value="([0-9a-f]{64})"')


def test_alarm_forms_need_an_admin_login_the_page_s_token_and_the_dashboard_s_origin(
    api_server: LiveServer, monitored: Monitored
):
    sid = monitored.structure["id"]
    with monitored.org.client("viewer") as api:
        (alarm,) = api.get(f"{API}/alarms", params={"structure_id": sid, "rule_kind": "persistence"}).json()[
            "items"
        ]
    url = f"{DASHBOARD}/alarms/{alarm['id']}/acknowledge"

    def state() -> dict:
        with monitored.org.client("viewer") as api:
            return api.get(f"{API}/alarms/{alarm['id']}").json()

    with logged_in(api_server, monitored.org.keys["viewer"]) as viewer:
        page = viewer.get(f"{DASHBOARD}/structures/{sid}")
        assert f'data-alarm-id="{alarm["id"]}"' in page.text and "Admins acknowledge" in page.text
        assert "/acknowledge" not in page.text, "no buttons for a viewer"
        # The viewer's own login token, which its pages do not show, does not make it an admin.
        refused = viewer.post(url, data={"csrf": form_token(viewer.cookies[COOKIE]), "note": "mine"})
        assert refused.status_code == 403 and "admin key" in refused.text
    other = Org.create(api_server)
    with logged_in(api_server, other.keys["admin"]) as stranger:
        token = CSRF.search(stranger.get(DASHBOARD).text)
        assert token is None, "a fleet without alarms has no alarm forms"
    with logged_in(api_server, monitored.org.keys["admin"]) as admin:
        page = admin.get(f"{DASHBOARD}/structures/{sid}")
        found = CSRF.search(page.text)
        assert found is not None and "/acknowledge" in page.text
        token = found.group(1)
        assert admin.post(url, data={"note": "no token"}).status_code == 403
        assert admin.post(url, data={"csrf": "0" * 64}).status_code == 403
        forged = admin.post(url, data={"csrf": token}, headers={"Origin": "https://evil.example"})
        assert forged.status_code == 403 and "dashboard itself" in forged.text
        assert state()["state"] == "open", "the refused forms changed nothing"
        here = f"{DASHBOARD}/structures/{sid}"
        done = admin.post(url, data={"csrf": token, "note": "crew on site", "next": here})
        assert done.status_code == 303 and done.headers["location"] == here
        assert (state()["state"], state()["acknowledgement_note"]) == ("acknowledged", "crew on site")
        again = admin.post(url, data={"csrf": token, "next": here})
        assert again.status_code == 409 and "only an open alarm" in again.text
        # The resolve form is the acknowledge form's twin, registered by the same code: it resolves.
        resolve = url.replace("/acknowledge", "/resolve")
        closed = admin.post(resolve, data={"csrf": token, "note": "bolt tightened", "next": here})
        assert closed.status_code == 303 and closed.headers["location"] == here
        assert (state()["resolution"], state()["resolution_note"]) == ("by_hand", "bolt tightened")
