"""``PATCH /structures/{id}``: a structure's name, description and signal declarations changed
after its creation, over HTTP against the real app.

What is sent changes and nothing else. A declaration says what the stored records' numbers are
(and so the units of the models' coefficients): before the structure has records it may change
freely; after, it may only be completed, and a change is refused with the reason. Every refusal
leaves the structure as it was (``api_helpers.nothing_written``). The name clash rests on the
database's unique constraint, so it is checked on SQLite and PostgreSQL; the rest on SQLite.
"""

from __future__ import annotations

import httpx
import pytest

from harness.api_helpers import (
    API,
    FS,
    Org,
    create_structure,
    detail,
    json_body,
    nothing_written,
    post_record,
)
from harness.live import LiveServer

FORCE_N = {"quantity": "force", "unit": "N"}
ACCELERATION = {"quantity": "acceleration", "unit": None}
ACCELERATION_MS2 = {"quantity": "acceleration", "unit": "m/s\u00b2"}
# The module's tests run on SQLite; those whose behaviour differs by database take ``api_server``.


@pytest.fixture(scope="module")
def org(sqlite_api_server: LiveServer) -> Org:
    return Org.create(sqlite_api_server)


@pytest.fixture
def admin(org: Org):
    with org.client("admin") as client:
        yield client


def patch(admin: httpx.Client, structure_id: int, body: dict) -> httpx.Response:
    return admin.patch(f"{API}/structures/{structure_id}", json=body)


def refused(response: httpx.Response, status: int, *fragments: str) -> None:
    assert response.status_code == status, response.text
    for fragment in fragments:
        assert fragment in detail(response), f"{fragment!r} not in {detail(response)!r}"


def test_only_the_fields_sent_change(admin: httpx.Client):
    made = admin.post(
        f"{API}/structures",
        json={
            "name": "pump",
            "fs": FS,
            "description": "old",
            "excitation": FORCE_N,
            "response": ACCELERATION,
        },
    ).json()
    renamed = patch(admin, made["id"], {"name": " Pump 3 "})
    assert renamed.status_code == 200, renamed.text
    assert renamed.json() == made | {"name": "Pump 3"}  # stored as names are: trimmed
    described = patch(admin, made["id"], {"description": "the north pump"})
    assert described.json() == made | {"name": "Pump 3", "description": "the north pump"}
    read = admin.get(f"{API}/structures/{made['id']}").json()
    listed = {s["id"]: s for s in admin.get(f"{API}/structures").json()}[made["id"]]
    assert read == described.json()
    assert {key: listed[key] for key in read} == read
    assert patch(admin, made["id"], {}).json() == read


def test_declarations_change_freely_before_the_structure_has_records(admin: httpx.Client):
    made = create_structure(admin)
    declared = patch(admin, made["id"], {"excitation": FORCE_N, "response": ACCELERATION_MS2})
    assert declared.status_code == 200, declared.text
    assert (declared.json()["excitation"], declared.json()["response"]) == (FORCE_N, ACCELERATION_MS2)
    velocity = {"quantity": "velocity", "unit": " m/s "}
    changed = patch(admin, made["id"], {"excitation": None, "response": velocity})
    assert changed.status_code == 200, changed.text
    read = admin.get(f"{API}/structures/{made['id']}").json()
    assert (read["excitation"], read["response"]) == (None, {"quantity": "velocity", "unit": "m/s"})


def test_once_records_exist_a_declaration_is_completed_never_changed(api_server: LiveServer):
    """Stating what was not stated keeps the records' meaning; changing or withdrawing it would
    relabel numbers measured in the first units, so it is refused, the whole request with it. On
    both databases: the look at the records is made under the structure state's row lock, which
    only PostgreSQL takes (SQLite holds its single writer's lock by then)."""
    org = Org.create(api_server)
    with org.client("admin") as admin:
        declared_after_records(org, admin)


def declared_after_records(org: Org, admin: httpx.Client) -> None:
    made = admin.post(f"{API}/structures", json={"name": "bridge", "fs": FS, "response": ACCELERATION}).json()
    with org.client("ingest") as ingest:
        assert post_record(ingest, made["id"], json_body(300)).status_code == 201
    completed = patch(admin, made["id"], {"excitation": FORCE_N, "response": ACCELERATION_MS2})
    assert completed.status_code == 200, completed.text
    assert (completed.json()["excitation"], completed.json()["response"]) == (FORCE_N, ACCELERATION_MS2)
    assert patch(admin, made["id"], {"response": ACCELERATION_MS2}).status_code == 200  # as it is
    changes = [
        {"response": {"quantity": "acceleration", "unit": "g"}, "name": "renamed"},  # another unit
        {"excitation": {"quantity": "voltage", "unit": "N"}},  # another quantity
        {"excitation": {"quantity": "force"}, "description": "changed"},  # its unit withdrawn
        {"response": None},  # withdrawn
    ]
    with nothing_written(org, made["id"]):
        answers = [patch(admin, made["id"], body) for body in changes]
    for answer in answers:
        refused(answer, 409, "structure 'bridge' has records", "can only be completed")
    assert "its response is declared as acceleration y [m/s\u00b2] and cannot become nothing" in detail(
        answers[-1]
    )
    assert admin.get(f"{API}/structures/{made['id']}").json() == completed.json()


def test_a_name_another_structure_has_is_a_conflict(api_server: LiveServer):
    """On the unique constraint of each database; the request changes nothing."""
    org = Org.create(api_server)
    with org.client("admin") as admin:
        taken = create_structure(admin, "taken")
        made = create_structure(admin, "free")
        with nothing_written(org, made["id"]):
            for name in ("taken", " taken "):
                refused(
                    patch(admin, made["id"], {"name": name, "description": "x"}),
                    409,
                    "a structure named 'taken' already exists in your organisation",
                )
        assert patch(admin, taken["id"], {"name": "taken"}).status_code == 200  # its own name
        assert patch(admin, made["id"], {"name": "Taken"}).json()["name"] == "Taken"


BAD_UPDATES = {
    "fs": ({"fs": 1000.0}, "fs cannot change: its records were stored at it"),
    "null name": ({"name": None}, "name cannot be null: leave it out to keep it"),
    "null description": ({"description": None}, "description cannot be null"),
    "empty name": ({"name": " "}, "a name cannot be empty or only whitespace"),
    "unknown field": ({"owner": "me"}, "Extra inputs are not permitted"),
    "unknown quantity": ({"response": {"quantity": "mass", "unit": "kg"}}, "'pressure' or 'other'"),
    "unit with a space": (
        {"excitation": {"quantity": "force", "unit": "k N"}},
        "the unit 'k N' is not allowed: a unit is 1 to 16 printable characters without spaces",
    ),
    "name not a string": ({"name": 3}, "valid string"),
}


@pytest.mark.parametrize(("body", "fragment"), BAD_UPDATES.values(), ids=BAD_UPDATES.keys())
def test_bad_updates_are_refused_saying_why(org: Org, admin: httpx.Client, body, fragment):
    structure_id = create_structure(admin)["id"]
    with nothing_written(org, structure_id):
        refused(patch(admin, structure_id, {"description": "changed"} | body), 422, fragment)


def test_only_an_admin_changes_a_structure(org: Org, admin: httpx.Client):
    structure_id = create_structure(admin)["id"]
    for role in ("viewer", "ingest"):
        with org.client(role) as client:
            refused(
                patch(client, structure_id, {"name": "mine"}),
                403,
                f"this needs a key of role 'admin' or higher; yours is '{role}'",
            )
