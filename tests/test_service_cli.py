"""``narxwatch db upgrade``, ``keys``, ``demo-seed`` and ``serve``: seeding, serving and what
depends on the default database's place (fixed when the service is imported: a missing one is
refused and not created) run as a user runs them (the console script); the keys commands on the
seeded database, and the refusals of a database named by its URL (unmigrated, unreachable) or of
invalid settings, through its entry point in this process."""

from __future__ import annotations

import datetime as dt
import hashlib
import json
import os
import shutil
import signal
import subprocess
import sys
import uuid
from collections.abc import Callable
from functools import partial
from pathlib import Path

import httpx
import pytest
from cryptography.fernet import Fernet
from sqlalchemy import insert, select, update

from harness import migrated
from harness.cli import invoke
from harness.live import free_port, wait_until_serving
from service.db import make_engine
from service.migrate import upgrade_database
from service.tables import Organisation, Structure, Webhook, utcnow

BIN = Path(sys.executable).parent
NARXWATCH = shutil.which("narxwatch", path=str(BIN))
ROLES = ("admin", "ingest", "viewer")
HEADER = ["id", "organisation", "prefix", "role", "created", "expires", "last", "used", "revoked"]


def run(
    *args: str, env: dict[str, str], check: bool = True, cwd: Path | None = None
) -> subprocess.CompletedProcess[str]:
    result = subprocess.run([NARXWATCH, *args], env=env, cwd=cwd, capture_output=True, text=True, timeout=300)
    if check:
        assert result.returncode == 0, result.stderr
    return result


@pytest.fixture(scope="module")
def seeded(tmp_path_factory) -> dict[str, str]:
    """An environment whose SQLite database holds the demo, seeded twice, renamed in between (as
    ``PATCH /structures/{id}`` renames it): seeded first as a user seeds it, then again in this
    process (``db upgrade`` runs as a process where the default database is made)."""
    folder = tmp_path_factory.mktemp("svc")
    env = {**os.environ, "NARXWATCH_DATABASE_URL": f"sqlite:///{folder / 'n.db'}"}
    upgrade_database(env["NARXWATCH_DATABASE_URL"])
    first = run("demo-seed", env=env)
    engine = make_engine(env["NARXWATCH_DATABASE_URL"])
    with engine.begin() as connection:
        connection.execute(update(Structure).values(name="bay 3 rig"))
    engine.dispose()
    second = invoke("demo-seed", cwd=folder, environ=env)
    env["FIRST_SEED"], env["SECOND_SEED"] = first.stdout, second.stdout
    return env


@pytest.fixture
def in_process(monkeypatch, tmp_path) -> Callable[..., subprocess.CompletedProcess[str]]:
    """``invoke`` with the given NARXWATCH_ settings added to this process's environment (kept for
    the test's later commands)."""

    def command(*args: str, check: bool = True, **settings: str) -> subprocess.CompletedProcess[str]:
        for name, value in settings.items():
            monkeypatch.setenv(f"NARXWATCH_{name.upper()}", value)
        return invoke(*args, cwd=tmp_path, check=check)

    return command


@pytest.fixture
def on_seeded(seeded, in_process) -> Callable[..., subprocess.CompletedProcess[str]]:
    """A command run in this process on the seeded database (the keys commands: the database is
    what they are about, not the process, and a new process spends two seconds on imports)."""
    return partial(in_process, database_url=seeded["NARXWATCH_DATABASE_URL"])


def test_demo_seed_is_idempotent(seeded):
    assert "k2 experiments" in seeded["FIRST_SEED"]
    # The second run finds the demo, renamed, and trains nothing.
    assert "experiments" not in seeded["SECOND_SEED"]
    assert "is structure 1" in seeded["SECOND_SEED"]


def test_the_demo_structure_declares_the_simulated_rigs_force_and_displacement(seeded):
    """The demo's records are the simulator's (force on mass 1 [N], displacement of mass 2 [m]),
    and its structure says so, as any structure of one's own would."""
    engine = make_engine(seeded["NARXWATCH_DATABASE_URL"])
    with engine.connect() as connection:
        declared = connection.execute(
            select(Structure.excitation_quantity, Structure.excitation_unit,
                   Structure.response_quantity, Structure.response_unit)
        ).one()  # fmt: skip
    engine.dispose()
    assert tuple(declared) == ("force", "N", "displacement", "m")


def test_keys_create_prints_a_working_key_once(on_seeded):
    key = on_seeded("keys", "create", "--org", "demo", "--role", "viewer").stdout.strip()
    assert key.startswith("nw_") and len(key) > 40
    other = on_seeded("keys", "create", "--org", "demo", "--role", "viewer").stdout.strip()
    assert other != key


def test_keys_create_refuses_an_unknown_role(tmp_path):
    # Refused before the database is opened: in this process (the console script's entry point).
    result = invoke("keys", "create", "--org", "demo", "--role", "root", cwd=tmp_path, check=False)
    assert result.returncode == 2 and "unknown role 'root'" in result.stderr


def listing(command: Callable[..., subprocess.CompletedProcess[str]], *args: str) -> dict[str, list[str]]:
    """``narxwatch keys list``'s rows, by prefix: id, organisation, prefix, role, then the times."""
    return rows_of(command("keys", "list", *args).stdout)


def rows_of(text: str) -> dict[str, list[str]]:
    header, *lines = text.splitlines()
    assert header.split() == HEADER
    return {row[2]: row for row in (line.split() for line in lines)}


def prefix(key: str) -> str:
    return key.split("_")[1]


def test_keys_list_shows_every_key_but_never_the_key_or_its_hash(on_seeded):
    org = f"list-{uuid.uuid4().hex[:8]}"
    on_seeded("keys", "create", "--org", f"other-{org}", "--role", "viewer")  # listed, not ours
    made = {role: on_seeded("keys", "create", "--org", org, "--role", role).stdout.strip() for role in ROLES}
    text = on_seeded("keys", "list").stdout
    everyone, ours = rows_of(text), listing(on_seeded, "--org", org)
    assert set(ours) == {prefix(key) for key in made.values()} and set(ours) < set(everyone)
    for role, key in made.items():
        row = ours[prefix(key)]
        # id, organisation, prefix, role, created (date and minute), expires, last used and revoked: none.
        assert row[1:4] == [org, prefix(key), role] and row[6:] == ["-", "-", "-"], row
        assert dt.datetime.fromisoformat(f"{row[4]}T{row[5]}+00:00") <= dt.datetime.now(dt.UTC)
    for key in made.values():
        assert key not in text and hashlib.sha256(key.encode()).hexdigest() not in text
    unknown = on_seeded("keys", "list", "--org", "no-such-org", check=False)
    assert unknown.returncode == 2 and "organisation 'no-such-org' has no keys" in unknown.stderr


def test_keys_create_expires_after_a_duration_or_at_a_time(on_seeded):
    org = f"expiring-{uuid.uuid4().hex[:8]}"
    expiries = {
        "90m": dt.timedelta(minutes=90),
        "30d": dt.timedelta(days=30),
        "2099-01-31": dt.datetime(2099, 1, 31, tzinfo=dt.UTC),  # a date: its midnight UTC
        "2099-01-31T10:30:00+02:00": dt.datetime(2099, 1, 31, 8, 30, tzinfo=dt.UTC),
    }
    made = {}
    for expires in expiries:
        before = dt.datetime.now(dt.UTC).replace(second=0, microsecond=0)
        created = on_seeded("keys", "create", "--org", org, "--role", "viewer", "--expires", expires)
        made[expires] = (prefix(created.stdout.strip()), before, dt.datetime.now(dt.UTC))
    rows = listing(on_seeded, "--org", org)
    for expires, expected in expiries.items():
        key, before, after = made[expires]
        listed = dt.datetime.fromisoformat(f"{rows[key][6]}T{rows[key][7]}+00:00")  # to the minute
        if isinstance(expected, dt.timedelta):
            assert before + expected <= listed <= after + expected, expires
        else:
            assert listed == expected, expires


def test_keys_create_refuses_an_expiry_it_cannot_keep(on_seeded):
    org = f"refused-{uuid.uuid4().hex[:8]}"
    refusals = {
        "2020-01-01": "has passed; give a time in the future",
        "tomorrow": "give a duration (90m, 12h, 30d, 2w) or an ISO date or time",
        "2099-01-31T10:30:00": "give the time a zone",
        "99999999999d": "lies beyond the year 9999",
    }
    for expires, message in refusals.items():
        args = ("keys", "create", "--org", org, "--role", "viewer", "--expires", expires)
        # In this process, on the seeded database: a key that was not refused would be stored there.
        result = on_seeded(*args, check=False)
        assert result.returncode == 2 and message in result.stderr, (expires, result.stderr)
        assert "Traceback" not in result.stderr and result.stdout == ""
    assert on_seeded("keys", "list", "--org", org, check=False).returncode == 2, "a refused key was stored"


def test_keys_revoke_by_prefix_or_id(on_seeded):
    org = f"revoke-{uuid.uuid4().hex[:8]}"
    first, second, kept = (
        on_seeded("keys", "create", "--org", org, "--role", "ingest").stdout.strip() for _ in range(3)
    )
    rows = listing(on_seeded, "--org", org)
    by_prefix = on_seeded("keys", "revoke", prefix(first)).stdout
    assert f"key {rows[prefix(first)][0]} ({prefix(first)}, ingest of '{org}') revoked at" in by_prefix
    by_id = on_seeded("keys", "revoke", rows[prefix(second)][0]).stdout
    assert f"({prefix(second)}, ingest of '{org}') revoked at" in by_id
    after = listing(on_seeded, "--org", org)
    for key in (first, second):
        revoked = dt.datetime.fromisoformat(f"{after[prefix(key)][-2]}T{after[prefix(key)][-1]}+00:00")
        assert revoked <= dt.datetime.now(dt.UTC)
    assert after[prefix(kept)][-1] == "-"
    for unknown in ("999999", "0123456789ab"):
        result = on_seeded("keys", "revoke", unknown, check=False)
        assert result.returncode == 2 and f"API key {unknown} not found" in result.stderr, result.stderr


def test_serve_answers_with_the_seeded_demo(seeded, on_seeded):
    port = free_port()
    admin = on_seeded("keys", "create", "--org", "demo", "--role", "admin").stdout.strip()
    server = subprocess.Popen(
        [NARXWATCH, "serve", "--port", str(port)],
        env=seeded,
        stdout=subprocess.PIPE,
        stderr=subprocess.STDOUT,
    )
    try:
        base = f"http://127.0.0.1:{port}"
        wait_until_serving(base, server, 60, lambda: "narxwatch serve did not start")
        assert httpx.get(f"{base}/readyz").json() == {"status": "ready"}
        headers = {"Authorization": f"Bearer {admin}"}
        structures = httpx.get(f"{base}/api/v1/structures", headers=headers).json()
        assert [s["name"] for s in structures] == ["bay 3 rig"]  # the demo, as the fixture renamed it
        models = httpx.get(f"{base}/api/v1/structures/{structures[0]['id']}/models", headers=headers).json()
        assert sorted((m["name"], m["active"]) for m in models) == [
            ("baseline", True),
            ("k1", True),
            ("k2", True),
        ]
        # A key revoked on the command line is refused by the running service at once.
        key = on_seeded("keys", "create", "--org", "demo", "--role", "viewer").stdout.strip()
        viewer = {"Authorization": f"Bearer {key}"}
        assert httpx.get(f"{base}/api/v1/structures", headers=viewer).status_code == 200
        on_seeded("keys", "revoke", prefix(key))
        assert httpx.get(f"{base}/api/v1/structures", headers=viewer).status_code == 401
    finally:
        server.send_signal(signal.SIGINT)
        server.wait(timeout=30)


# --- Where the database lives, and commands run before it exists ---------------------------------


@pytest.fixture
def newcomer(tmp_path) -> tuple[dict[str, str], Path, Path]:
    """A user's environment with no NARXWATCH_DATABASE_URL, a working directory outside the
    repository, and the XDG data directory the default database belongs in."""
    env = {k: v for k, v in os.environ.items() if not k.startswith("NARXWATCH_")}
    env["XDG_DATA_HOME"] = str(tmp_path / "data")
    workdir = tmp_path / "somewhere"
    workdir.mkdir()
    return env, workdir, tmp_path / "data" / "narxwatch" / "narxwatch.db"


def test_the_default_database_is_in_the_users_data_directory(newcomer, tmp_path):
    env, workdir, database = newcomer
    run("db", "upgrade", env=env, cwd=workdir)
    assert database.is_file()
    assert list(workdir.iterdir()) == []
    # Another working directory reaches the same database.
    elsewhere = tmp_path / "elsewhere"
    elsewhere.mkdir()
    key = run("keys", "create", "--org", "o", "--role", "viewer", env=env, cwd=elsewhere).stdout
    assert key.startswith("nw_")
    assert list(elsewhere.iterdir()) == []


def test_without_xdg_data_home_the_database_is_under_local_share(newcomer, tmp_path):
    env, workdir, _ = newcomer
    del env["XDG_DATA_HOME"]
    env["HOME"] = str(tmp_path / "home")
    run("db", "upgrade", env=env, cwd=workdir)
    assert (tmp_path / "home" / ".local" / "share" / "narxwatch" / "narxwatch.db").is_file()


def one_line_refusal(result: subprocess.CompletedProcess[str], database: Path) -> str:
    assert result.returncode == 2, result.stderr
    lines = result.stderr.strip().splitlines()
    assert len(lines) == 1, result.stderr
    assert str(database) in lines[0] and "narxwatch db upgrade" in lines[0]
    return lines[0]


NEED_A_DATABASE = [
    ["keys", "create", "--org", "o", "--role", "viewer"],
    ["worker", "--once"],
]


@pytest.mark.parametrize("command", NEED_A_DATABASE, ids=lambda c: " ".join(c[:2]))
def test_a_missing_database_is_a_one_line_error_and_is_not_created(newcomer, command, tmp_path):
    env, workdir, database = newcomer
    line = one_line_refusal(run(*command, env=env, cwd=workdir, check=False), database)
    assert "no database" in line
    assert not (tmp_path / "data").exists()
    assert list(workdir.iterdir()) == []


def test_serve_without_upgrading_refuses_a_missing_database(newcomer, tmp_path):
    env, workdir, database = newcomer
    env["NARXWATCH_UPGRADE_ON_START"] = "false"
    one_line_refusal(run("serve", "--port", str(free_port()), env=env, cwd=workdir, check=False), database)
    assert not (tmp_path / "data").exists()


@pytest.mark.parametrize("command", NEED_A_DATABASE, ids=lambda c: " ".join(c[:2]))
def test_an_unmigrated_database_is_a_one_line_error_and_is_left_alone(newcomer, command):
    env, workdir, database = newcomer
    env["NARXWATCH_DATABASE_URL"] = f"sqlite:///{database}"
    database.parent.mkdir(parents=True)
    upgrade_database(env["NARXWATCH_DATABASE_URL"], "0001")
    before = database.read_bytes()
    line = one_line_refusal(invoke(*command, cwd=workdir, check=False, environ=env), database)
    assert "0001" in line
    assert database.read_bytes() == before


def test_an_unreachable_database_server_is_a_one_line_error_without_the_password(newcomer):
    env, workdir, _ = newcomer
    env["NARXWATCH_DATABASE_URL"] = "postgresql+psycopg://narxwatch:s3cret@127.0.0.1:1/narxwatch"
    result = invoke("keys", "create", "--org", "o", "--role", "viewer", cwd=workdir, check=False, environ=env)
    assert result.returncode == 2
    (line,) = result.stderr.strip().splitlines()
    assert "cannot open the database at postgresql+psycopg://narxwatch:***@127.0.0.1:1/narxwatch" in line
    assert "s3cret" not in result.stderr


# --- The keys webhooks' secrets are sealed under ---------------------------------------------------


def test_db_reseal_seals_every_secret_under_the_first_key_or_changes_nothing(in_process, tmp_path):
    url = migrated.sqlite(tmp_path / "sealed.db")
    old, new = (Fernet.generate_key().decode() for _ in range(2))
    secrets = ["whsec_" + letter * 32 for letter in "xy"]
    engine = make_engine(url)
    with engine.begin() as connection:
        connection.execute(insert(Organisation).values(id=1, name="o", created_at=utcnow()))
        for secret in secrets:
            sealed = Fernet(old).encrypt(secret.encode()).decode()
            values = {"url": "https://93.184.215.14/hook", "events": ["alarm.opened"], "created_at": utcnow()}
            connection.execute(insert(Webhook).values(organisation_id=1, secret=sealed, **values))

    def stored() -> list[str]:
        with engine.connect() as connection:
            return list(connection.scalars(select(Webhook.secret).order_by(Webhook.id)))

    before = stored()
    refused = in_process("db", "reseal", check=False, database_url=url, secret_keys=json.dumps([new]))
    assert refused.returncode == 2, refused.stderr
    assert "webhook 1: " in refused.stderr and "NARXWATCH_SECRET_KEYS" in refused.stderr
    assert stored() == before
    done = in_process("db", "reseal", secret_keys=json.dumps([new, old]))
    assert "2 webhook secret(s) sealed under the first key" in done.stdout
    assert [Fernet(new).decrypt(token.encode()).decode() for token in stored()] == secrets
    engine.dispose()


@pytest.mark.parametrize("command", [["worker", "--once"], ["serve", "--port", "8000"]], ids=lambda c: c[0])
def test_a_process_given_a_key_file_that_holds_no_key_stops_at_its_start_naming_the_file(
    newcomer, tmp_path, command
):
    env, workdir, database = newcomer
    migrated.sqlite(database)
    wrong = tmp_path / "secret.key"
    wrong.write_text("hunter2\n")
    env |= {"NARXWATCH_SECRET_KEY_FILE": str(wrong), "NARXWATCH_LOG_FORMAT": "text"}
    result = run(*command, env=env, cwd=workdir, check=False)
    assert result.returncode == 2, result.stderr
    last = result.stderr.strip().splitlines()[-1]  # serve logs its upgrade before it
    assert last.startswith("error: NARXWATCH_SECRET_KEY_FILE: ") and str(wrong) in last, result.stderr
    assert "one key a line" in last and "hunter2" not in result.stderr


def test_invalid_settings_are_one_line_naming_each_variable_and_never_its_value(newcomer):
    env, workdir, database = newcomer
    env["NARXWATCH_DATABASE_URL"] = f"sqlite:///{database}"
    env |= {"NARXWATCH_SECRET_KEYS": '["hunter2"]', "NARXWATCH_SMTP_PORT": "seventy"}
    env |= {"NARXWATCH_MAX_CLOCK_SKEW_SECONDS": "-1"}
    result = invoke("keys", "list", cwd=workdir, check=False, environ=env)
    assert result.returncode == 2, result.stderr
    (line,) = result.stderr.strip().splitlines()
    assert "NARXWATCH_SECRET_KEYS: " in line and "NARXWATCH_SMTP_PORT: " in line
    assert "NARXWATCH_MAX_CLOCK_SKEW_SECONDS: Input should be greater than or equal to 0" in line
    assert "hunter2" not in result.stderr and "seventy" not in result.stderr


# Garbage in a cycle, left when the command ends; automatic collections off, so that only the
# interpreter's last ones, as the process exits, could come to it.
LEFT_AT_THE_END = """
import gc, os, sys
from service.cli import main

class Cycle:
    def __del__(self):
        os.write(1, b"walked at exit")

gc.disable()
cycle = Cycle()
cycle.me = cycle
del cycle
sys.argv = ["narxwatch", "keys", "--help"]
main()
"""


def test_a_command_exits_without_walking_every_object_it_loaded():
    """The interpreter's last collections walk every object still tracked: a stopped worker or
    server spent seconds on them (numpy's, scipy's, numba's, SQLAlchemy's) before it exited.
    A command leaves them alone, garbage and all: the process hands its memory back whole."""
    ended = subprocess.run(
        [sys.executable, "-c", LEFT_AT_THE_END], capture_output=True, text=True, timeout=120, check=False
    )
    assert ended.returncode == 0, ended.stderr
    assert "revoke" in ended.stdout, "the command did not run"
    assert "walked at exit" not in ended.stdout
