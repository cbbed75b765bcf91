"""Operating conditions on records (issue 16): stated in a JSON body, CSV comment lines or NPZ
scalars, stored, and shown with every record and verdict the API answers with.

Through HTTP against the real app on SQLite (and one round trip on PostgreSQL); a refused upload
leaves nothing behind (``api_helpers.nothing_written``).
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np
import pytest

from harness.api_helpers import (
    API,
    FS,
    Org,
    clients,
    create_structure,
    csv_text,
    detail,
    json_body,
    noise,
    nothing_written,
    npz_bytes,
    post_record,
    simulated,
    train_fault_mode,
    verdicts,
    wait_for,
)
from harness.live import LiveServer
from recordfiles.conditions import MAX_CONDITIONS

NPZ = "application/x-npz"
CSV = "text/csv"
TEMPERATURE = {"name": "temperature", "value": 12.5, "unit": "°C"}


@dataclass
class Site:
    server: LiveServer
    org: Org
    rig: int  # an active k2 fault-mode model
    bare: int  # no models


@pytest.fixture(scope="module")
def site(sqlite_api_server: LiveServer) -> Site:
    org = Org.create(sqlite_api_server)
    with clients(org) as (admin, ingest, _):
        rig = create_structure(admin, "rig")["id"]
        train_fault_mode(admin, ingest, rig, "k2", seed=41)
        bare = create_structure(admin, "bare")["id"]
    return Site(sqlite_api_server, org, rig, bare)


@pytest.fixture
def ingest(site: Site):
    with site.org.client("ingest") as client:
        yield client


@pytest.fixture
def viewer(site: Site):
    with site.org.client("viewer") as client:
        yield client


def stored(response) -> dict:
    assert response.status_code in (200, 201, 202), response.text
    return response.json()


def healthy_body(seed: int, **extra) -> dict:
    record = simulated("none", 0.0, seed)
    return {"x": record.x.tolist(), "y": record.y.tolist(), "fs": record.fs, **extra}


# --- stated in every format ---------------------------------------------------------------------


def test_json_conditions_are_stored_sorted_by_name_with_their_units(site: Site, ingest):
    conditions = [{"name": "speed", "value": 3, "unit": "m/s"}, TEMPERATURE, {"name": "level", "value": -2.5}]
    record = stored(post_record(ingest, site.bare, json_body(300, conditions=conditions)))
    assert record["conditions"] == [
        {"name": "level", "value": -2.5, "unit": None},
        {"name": "speed", "value": 3.0, "unit": "m/s"},
        TEMPERATURE,
    ]


def test_a_record_without_conditions_answers_as_before_with_an_empty_list(site: Site, ingest):
    record = stored(post_record(ingest, site.bare, json_body(300)))
    assert record["conditions"] == []
    assert set(record) == {
        "id", "structure_id", "fs", "n_samples", "acquired_at", "created_at", "sha256", "conditions",
        "created", "verdict", "signals_pruned_at",
    }  # fmt: skip
    assert record["signals_pruned_at"] is None


def test_csv_comment_lines_state_conditions_with_or_without_a_unit(site: Site, ingest):
    """The simulator's ``# temperature=12.5`` has no unit; ``# NAME=VALUE UNIT`` gives one; a comment
    that is no assignment is prose, as before."""
    x, y = noise(300)
    text = "# recorded on the north span\n# temperature=12.5 °C\n# speed = 80 km/h\n# level=3\n"
    record = stored(post_record(ingest, site.bare, text + csv_text(x, y), CSV))
    assert record["conditions"] == [
        {"name": "level", "value": 3.0, "unit": None},
        {"name": "speed", "value": 80.0, "unit": "km/h"},
        {"name": "temperature", "value": 12.5, "unit": "°C"},
    ]


def test_npz_scalar_members_are_conditions_without_units(site: Site, ingest):
    x, y = noise(300)
    body = npz_bytes(x=x, y=y, fs=FS, temperature=np.float64(-7.25), speed=np.array([3], dtype=np.int32))
    record = stored(post_record(ingest, site.bare, body, NPZ))
    assert record["conditions"] == [
        {"name": "speed", "value": 3.0, "unit": None},
        {"name": "temperature", "value": -7.25, "unit": None},
    ]


def test_a_reupload_returns_the_stored_conditions_and_cannot_change_them(site: Site, ingest):
    body = json_body(300, conditions=[TEMPERATURE])
    first = stored(post_record(ingest, site.bare, body))
    again = post_record(ingest, site.bare, {**body, "conditions": []})
    assert again.status_code == 200 and again.json()["conditions"] == [TEMPERATURE]
    assert again.json()["id"] == first["id"]
    same = post_record(ingest, site.bare, body)
    assert same.status_code == 200 and same.json()["id"] == first["id"]
    other = post_record(ingest, site.bare, {**body, "conditions": [{**TEMPERATURE, "value": 13.0}]})
    assert other.status_code == 409, other.text
    assert detail(other) == (
        f"record {first['id']} holds the same data and was stored with the conditions temperature=12.5 °C; "
        "this upload states temperature=13 °C. A record keeps the conditions of its first upload"
    )
    kept = post_record(ingest, site.bare, {**body, "conditions": []})
    assert kept.json()["conditions"] == [TEMPERATURE]


# --- shown with every verdict ---------------------------------------------------------------


def test_verdicts_history_and_summary_carry_the_records_conditions(site: Site, ingest, viewer):
    bare = stored(post_record(ingest, site.rig, healthy_body(51), inspect="true"))
    warm = stored(post_record(ingest, site.rig, healthy_body(52, conditions=[TEMPERATURE]), inspect="true"))
    assert warm["verdict"]["conditions"] == [TEMPERATURE]
    assert bare["verdict"]["conditions"] == []
    listed = {v["id"]: v for v in verdicts(viewer, site.rig)}
    assert listed[warm["verdict"]["id"]]["conditions"] == [TEMPERATURE]
    assert listed[bare["verdict"]["id"]]["conditions"] == []
    one = viewer.get(f"{API}/verdicts/{warm['verdict']['id']}").json()
    assert one == warm["verdict"]
    summary = viewer.get(f"{API}/structures/{site.rig}/summary").json()
    assert summary["latest"] == warm["verdict"]
    trend = {point["verdict_id"]: point for point in summary["trend"]}
    assert trend[warm["verdict"]["id"]]["conditions"] == [TEMPERATURE]
    assert trend[bare["verdict"]["id"]]["conditions"] == []


def test_a_queued_inspection_s_verdict_carries_the_conditions(site: Site, ingest, viewer):
    speed = {"name": "speed", "value": 80.0, "unit": "km/h"}
    record = stored(post_record(ingest, site.rig, healthy_body(53, conditions=[speed]), inspect="queue"))
    assert record["conditions"] == [speed]

    def verdict() -> dict | None:
        return next((v for v in verdicts(viewer, site.rig) if v["record_id"] == record["id"]), None)

    assert wait_for(verdict, 60, "the queued verdict")["conditions"] == [speed]  # type: ignore[index]


# --- bad input: a clear 422, nothing stored ---------------------------------------------------


def condition_csv(*lines: str) -> str:
    x, y = noise(300)
    return "".join(f"{line}\n" for line in lines) + csv_text(x, y)


def npz_record(**members) -> bytes:
    x, y = noise(300)
    return npz_bytes(x=x, y=y, **members)


def many(count: int) -> list[dict]:
    return [{"name": f"v{index}", "value": float(index)} for index in range(count)]


@pytest.mark.parametrize(
    ("body", "media", "fragment"),
    [
        (json_body(300, conditions=[{"name": "temperature", "value": float("nan")}]), None,
         "the condition 'temperature' is nan; a condition's value must be a finite number"),
        (condition_csv("# temperature=inf °C"), CSV,
         "the condition 'temperature' is inf; a condition's value must be a finite number"),
        (json_body(300, conditions=[{"name": "Temperature", "value": 1.0}]), None,
         "the condition name 'Temperature' is not allowed: a condition's name is a lowercase letter"),
        (condition_csv("# wind-speed=3"), CSV, "the condition name 'wind-speed' is not allowed"),
        (json_body(300, conditions=[{"name": "fs", "value": 1.0}]), None,
         "'fs' cannot name a condition: x, y and fs are the record's signals and sampling rate"),
        (json_body(300, conditions=[{"name": "t", "value": 1.0, "unit": "deg C"}]), None,
         "the unit 'deg C' of condition 't' is not allowed"),
        (json_body(300, conditions=[{"name": "t", "value": 1.0, "unit": "\u200b°C"}]), None,
         "the unit '\\u200b°C' of condition 't' is not allowed: a unit is 1 to 16 printable characters"),
        (json_body(300, conditions=many(MAX_CONDITIONS + 1)), None,
         f"a record may carry at most {MAX_CONDITIONS} conditions"),
        (condition_csv(*(f"# v{index}={index}" for index in range(MAX_CONDITIONS + 1))), CSV,
         f"a record may carry at most {MAX_CONDITIONS} conditions"),
        (json_body(300, conditions=[TEMPERATURE, {"name": "temperature", "value": 3.0}]), None,
         "the condition 'temperature' is given twice; give each condition once"),
        (condition_csv("# temperature=12.5", "# temperature=13"), CSV,
         "the condition 'temperature' is given twice"),
        (condition_csv("# temperature=12,5 °C"), CSV,
         "CSV line 1: the condition 'temperature' has the value '12,5', which is not a number"),
        (condition_csv("# fs=1500 Hz"), CSV,
         "CSV line 1: the '# fs=' comment holds the sampling rate in Hz, one number without a unit"),
        (npz_record(fs=FS, temperature=np.array([12.5, 13.0])), NPZ,
         "NPZ member 'temperature' holds 2 values (shape (2,)); a condition is one number"),
        (npz_record(fs=FS, temperature=np.zeros(100)), NPZ,
         "NPZ member 'temperature' must be one number, but its header declares shape (100,) of float64"),
        (npz_record(fs=FS, temperature=np.array("warm")), NPZ,
         "NPZ member 'temperature' holds a condition, which must be a number; got dtype <U4"),
        (npz_record(Speed=1.0), NPZ,
         "NPZ member 'Speed': the condition name 'Speed' is not allowed"),
        (npz_record(temperature=np.float64("nan")), NPZ,
         "the condition 'temperature' is nan"),
        (npz_record(**{f"v{i}": float(i) for i in range(MAX_CONDITIONS + 2)}), NPZ,
         f"the NPZ holds {MAX_CONDITIONS + 4} members; a record holds the arrays x, y and fs"),
    ],
    ids=[
        "json-nan", "csv-inf", "json-uppercase-name", "csv-name-with-dash", "json-reserved-name",
        "json-unit-with-space", "json-unit-with-a-hidden-character", "json-too-many", "csv-too-many",
        "json-twice", "csv-twice",
        "csv-value-not-a-number", "csv-fs-with-unit", "npz-two-values", "npz-array", "npz-text",
        "npz-uppercase-name", "npz-nan", "npz-too-many",
    ],
)  # fmt: skip
def test_bad_conditions_are_refused_and_nothing_is_stored(site: Site, ingest, body, media, fragment):
    with nothing_written(site.org, site.rig):
        response = post_record(ingest, site.rig, body, media, inspect="true")
        assert response.status_code == 422, response.text
        assert fragment in detail(response), detail(response)


def test_a_name_as_long_as_a_body_is_quoted_short(site: Site, ingest):
    name = "t" * 100_000
    response = post_record(ingest, site.bare, json_body(300, conditions=[{"name": name, "value": 1.0}]))
    assert response.status_code == 422 and len(detail(response)) < 400, detail(response)[:400]


# --- PostgreSQL -------------------------------------------------------------------------------


def test_conditions_round_trip_on_postgresql(postgresql_api_server: LiveServer):
    org = Org.create(postgresql_api_server)
    with clients(org) as (admin, ingest, _):
        structure = create_structure(admin)["id"]
        body = json_body(300, conditions=[TEMPERATURE, {"name": "speed", "value": 1e-300}])
        first = stored(post_record(ingest, structure, body))
        again = post_record(ingest, structure, {**body, "conditions": []})
    assert again.status_code == 200
    expected = [{"name": "speed", "value": 1e-300, "unit": None}, TEMPERATURE]
    assert again.json()["conditions"] == first["conditions"] == expected
