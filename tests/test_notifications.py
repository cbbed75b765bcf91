"""Notifications: webhooks signed and retried until a real receiver takes them, e-mails through a
real SMTP server, the delivery log, the SSRF guard, and tenancy.

The rules of the outbox and of one attempt are checked on a SQLite file through the domain code;
what a user sees (the API, deliveries by the job workers of both backends, a killed worker) over
HTTP against the real app, with a receiver and an SMTP server the test starts. The API's
refusals, its listings and the sealed secret on SQLite: no database decides them; deliveries,
which the job queue carries: the whole way from an upload to its alarm's deliveries on both,
the retries and the e-mail on SQLite (the domain decides them, not the database).
"""

from __future__ import annotations

import datetime as dt
import email
import ipaddress
import itertools
import json
import os
import socket
import subprocess
import sys
import threading
import time
import uuid
from collections.abc import Iterator
from concurrent.futures import ThreadPoolExecutor
from email import policy
from pathlib import Path

import psycopg
import pytest
import trustme
from cryptography.fernet import Fernet
from pydantic import SecretStr, ValidationError
from sqlalchemy import func, select, update
from sqlalchemy.orm import Session, sessionmaker

from harness import migrated
from harness.api_helpers import (
    API,
    Org,
    clients,
    create_structure,
    detail,
    npz_bytes,
    post_record,
    simulated,
    train_fault_mode,
    wait_for,
)
from harness.live import LiveServer, free_port
from harness.receivers import HANG, Mailbox, Receiver, verify
from harness.workers import Worker, workers
from service import senders
from service.config import DEFAULT_DATABASE, Settings
from service.db import make_engine, session_factory, transaction
from service.domain import notifications, renotify
from service.jobs.distributed import conninfo
from service.jobs.embedded import EmbeddedBackend, claim, defer, run
from service.sealing import check_keys, seal, unseal
from service.tables import (
    Alarm,
    Delivery,
    EmailSubscription,
    Job,
    Organisation,
    Structure,
    Webhook,
    utcnow,
)

SECRET = "whsec_" + "k" * 32
PAYLOAD = {"id": 7, "structure_id": 3, "state": "open", "opened_at": "2026-11-23T22:00:00+00:00"}
LOOPBACK = '["127.0.0.0/8"]'
# Short backoff and attempts, loopback receivers admitted: the tests' settings (also given to
# `narxwatch worker` processes, as environment variables).
FAST = {
    "webhook_allowed_networks": LOOPBACK,
    "delivery_first_retry_seconds": "0.2",
    "notification_timeout_seconds": "5",
    "smtp_host": "127.0.0.1",
    "smtp_starttls": "false",
    # An hour: no alarm is due again while a test runs unless the test moves its opening back.
    "renotify_after_seconds": "3600",
    # `narxwatch worker`'s sweep, which defers each delivery due (a retry too), every second.
    "worker_sweep_seconds": "1",
}
FAST_FAILOVER = {"worker_heartbeat_seconds": "0.5", "worker_stalled_seconds": "3"}


def fast_settings(url: str, **more: object) -> Settings:
    values = {"embedded_worker": False, **FAST, "webhook_allowed_networks": json.loads(LOOPBACK), **more}
    return Settings(database_url=url, **values)  # type: ignore[arg-type]


# --- the outbox and one attempt, through the domain code, on a SQLite file ----------------------


class Outbox:
    """A migrated SQLite file with two organisations; the first has a webhook and an e-mail
    subscription."""

    def __init__(self, tmp_path: Path) -> None:
        url = migrated.sqlite(tmp_path / "notify.db")
        self.settings = fast_settings(url, delivery_max_attempts=3)
        self.sessions: sessionmaker[Session] = session_factory(make_engine(url))
        with transaction(self.sessions) as session:
            first, other = Organisation(name="first"), Organisation(name="other")
            session.add_all([first, other])
            session.flush()
            self.organisation_id, self.other_id = first.id, other.id

    def webhook(self, url: str, events: list[str]) -> int:
        with transaction(self.sessions) as session:
            sealed = seal(SECRET, self.settings)
            webhook = Webhook(organisation_id=self.organisation_id, url=url, secret=sealed, events=events)
            session.add(webhook)
            session.flush()
            return webhook.id

    def subscription(self, events: list[str]) -> int:
        with transaction(self.sessions) as session:
            row = EmailSubscription(
                organisation_id=self.organisation_id, addresses=["a@example.com"], events=events
            )
            session.add(row)
            session.flush()
            return row.id

    def deliveries(self) -> list[Delivery]:
        with self.sessions() as session:
            return list(session.scalars(select(Delivery).order_by(Delivery.id)))

    def run_jobs(self, now: dt.datetime | None = None) -> int:
        """Sweep the outbox into jobs and run every job due (embedded backend's functions)."""
        ran = 0
        with self.sessions() as session:
            notifications.sweep(session, defer, now)
            while (job := claim(session, now=now)) is not None:
                run(session, job, self.settings, now=now)
                ran += 1
        return ran


@pytest.fixture
def outbox(tmp_path: Path) -> Outbox:
    return Outbox(tmp_path)


def test_notify_adds_one_delivery_per_target_that_wants_the_event_and_nothing_if_rolled_back(outbox: Outbox):
    opened_only = outbox.webhook("https://93.184.215.14/hook", ["alarm.opened"])
    resolved_only = outbox.webhook("https://93.184.215.14/other", ["alarm.resolved"])
    mail = outbox.subscription(["alarm.opened", "alarm.resolved"])
    with outbox.sessions() as session:
        notifications.notify(session, outbox.organisation_id, "alarm.opened", PAYLOAD)
        session.rollback()  # the change it announced was not made: nothing to tell
    assert outbox.deliveries() == []
    with transaction(outbox.sessions) as session:
        notifications.notify(session, outbox.organisation_id, "alarm.opened", PAYLOAD)
        notifications.notify(session, outbox.other_id, "alarm.opened", PAYLOAD)  # has no targets
    found = outbox.deliveries()
    assert {(d.webhook_id, d.email_subscription_id) for d in found} == {(opened_only, None), (None, mail)}
    assert resolved_only not in {d.webhook_id for d in found}
    assert all(d.payload == PAYLOAD and d.status == "pending" and d.attempts == 0 for d in found)
    assert len({d.key for d in found}) == 2, "each delivery has a key of its own"
    with outbox.sessions() as session, pytest.raises(ValueError, match="unknown event"):
        notifications.notify(session, outbox.organisation_id, "alarm.exploded", PAYLOAD)


def test_a_due_delivery_is_claimed_once_however_often_it_is_swept_and_a_stale_claim_does_nothing(
    outbox: Outbox,
):
    outbox.webhook("https://93.184.215.14/hook", ["alarm.opened"])
    with transaction(outbox.sessions) as session:
        notifications.notify(session, outbox.organisation_id, "alarm.opened", PAYLOAD)
    now = utcnow()
    with outbox.sessions() as session:
        assert notifications.sweep(session, defer, now) == 1
        assert notifications.sweep(session, defer, now) == 0, "a claimed delivery was deferred twice"
        assert notifications.sweep(session, defer, now + dt.timedelta(minutes=1)) == 0
        (job,) = session.scalars(select(Job))
        # A job whose claim no longer holds (the delivery claimed again after the lease) does nothing.
        later = now + notifications.CLAIM_LEASE + dt.timedelta(seconds=1)
        assert notifications.sweep(session, defer, later) == 1
        notifications.deliver(session, outbox.settings, **job.args)
    (delivery,) = outbox.deliveries()
    assert (delivery.status, delivery.attempts) == ("pending", 0)


def test_a_delivery_that_keeps_failing_is_retried_with_backoff_then_marked_failed(outbox: Outbox):
    """Nothing listens on the port: each attempt fails at once, is logged, and the next is due
    ``delivery_first_retry_seconds`` · 2^(attempt − 1) later, up to ``delivery_max_attempts``."""
    outbox.webhook(f"http://127.0.0.1:{free_port()}/gone", ["alarm.opened"])
    with transaction(outbox.sessions) as session:
        notifications.notify(session, outbox.organisation_id, "alarm.opened", PAYLOAD)
    first_retry = outbox.settings.delivery_first_retry_seconds
    for attempt in range(1, outbox.settings.delivery_max_attempts + 1):
        started = utcnow()
        assert outbox.run_jobs(now=started + dt.timedelta(hours=attempt)) == 1
        finished = utcnow()
        (delivery,) = outbox.deliveries()
        assert delivery.attempts == attempt and delivery.last_status_code is None
        assert "ConnectError" in (delivery.last_error or ""), delivery.last_error
        if attempt < outbox.settings.delivery_max_attempts:
            # Due the backoff after the attempt failed, which was between these two readings of
            # the clock (however long a loaded machine took over it).
            backoff = dt.timedelta(seconds=first_retry * 2 ** (attempt - 1))
            assert started + backoff <= delivery.next_attempt_at <= finished + backoff, (started, finished)
            assert delivery.status == "pending"
    assert delivery.status == "failed" and delivery.delivered_at is None
    assert outbox.run_jobs(now=utcnow() + dt.timedelta(days=30)) == 0


def test_the_target_is_checked_again_at_each_attempt(outbox: Outbox):
    """A webhook accepted while its host was public, whose name now resolves to loopback (or an
    operator who withdrew the allowance): the attempt is refused before anything is sent."""
    with Receiver(SECRET) as receiver:
        outbox.webhook(receiver.url.replace("127.0.0.1", "localhost"), ["alarm.opened"])
        with transaction(outbox.sessions) as session:
            notifications.notify(session, outbox.organisation_id, "alarm.opened", PAYLOAD)
        outbox.settings = outbox.settings.model_copy(update={"webhook_allowed_networks": []})
        assert outbox.run_jobs() == 1
        assert receiver.requests == []
    (delivery,) = outbox.deliveries()
    assert delivery.status == "pending" and delivery.attempts == 1
    assert "not a public address" in (delivery.last_error or ""), delivery.last_error


def test_an_address_that_carries_a_loopback_ipv4_is_checked_again_at_each_attempt(outbox: Outbox):
    """Webhooks whose hosts carry 127.0.0.1 in each IPv6 form that embeds or translates an IPv4,
    stored while the operator admitted them: once the allowance is withdrawn the attempt is
    refused before anything is dialled, each log naming its address."""
    urls = {form: f"http://[{embed(LOOPBACK_IPV4)}]:9100/hook" for form, embed in EMBEDDINGS.items()}
    for url in urls.values():
        outbox.webhook(url, ["alarm.opened"])
    with transaction(outbox.sessions) as session:
        notifications.notify(session, outbox.organisation_id, "alarm.opened", PAYLOAD)
    outbox.settings = outbox.settings.model_copy(update={"webhook_allowed_networks": []})
    assert outbox.run_jobs() == len(urls)
    deliveries = outbox.deliveries()
    assert [(d.status, d.attempts) for d in deliveries] == [("pending", 1)] * len(urls)
    for url, delivery in zip(urls.values(), deliveries, strict=True):
        host = url.split("[")[1].split("]")[0]
        assert "not a public address" in (delivery.last_error or ""), (url, delivery.last_error)
        assert str(ipaddress.ip_address(host)) in (delivery.last_error or ""), (url, delivery.last_error)


def test_the_test_process_dials_nothing_but_loopback(outbox: Outbox):
    """The guard of tests/conftest.py: a delivery the operator let go anywhere
    (``webhook_allow_private``) to a routable address is refused at the socket, at once (the
    documentation address 192.0.2.1 would otherwise take the whole timeout), while loopback still
    answers."""
    with pytest.raises(PermissionError, match=r"loopback only, not 192\.0\.2\.1"):
        socket.create_connection(("192.0.2.1", 80), timeout=5)
    with (
        socket.socket(socket.AF_INET6, socket.SOCK_DGRAM) as udp,
        pytest.raises(PermissionError, match="loopback only, not 2001:db8::1"),
    ):
        udp.sendto(b"x", ("2001:db8::1", 53))
    anywhere = outbox.settings.model_copy(update={"webhook_allow_private": True})
    message = senders.Message("k", "alarm.opened", utcnow(), PAYLOAD)
    started = time.monotonic()
    outcome = senders.post_webhook("http://192.0.2.1/hook", SECRET, 1, message, anywhere)
    assert not outcome.delivered and "loopback only, not 192.0.2.1" in (outcome.error or ""), outcome
    assert time.monotonic() - started < anywhere.notification_timeout_seconds
    with Receiver(SECRET) as receiver:
        assert senders.post_webhook(receiver.url, SECRET, 1, message, outbox.settings).delivered


def test_redirects_are_not_followed(outbox: Outbox):
    """A receiver that redirects (here to another loopback port, as one would to an internal
    address): the attempt fails with the 3xx, and the redirect's target hears nothing."""
    with Receiver(SECRET) as elsewhere:
        target = socket.socket()
        target.bind(("127.0.0.1", 0))
        target.listen()
        port = target.getsockname()[1]

        def answer_with_a_redirect() -> None:
            connection, _ = target.accept()
            with connection:
                connection.recv(65536)
                head = f"HTTP/1.1 307 Temporary Redirect\r\nLocation: {elsewhere.url}\r\n"
                connection.sendall(f"{head}Content-Length: 0\r\n\r\n".encode())

        server = threading.Thread(target=answer_with_a_redirect, daemon=True)
        server.start()
        outbox.webhook(f"http://127.0.0.1:{port}/hook", ["alarm.opened"])
        with transaction(outbox.sessions) as session:
            notifications.notify(session, outbox.organisation_id, "alarm.opened", PAYLOAD)
        assert outbox.run_jobs() == 1
        server.join(10)
        target.close()
        assert elsewhere.requests == []
    (delivery,) = outbox.deliveries()
    assert (delivery.status, delivery.last_status_code) == ("pending", 307)
    assert "redirects are not followed" in (delivery.last_error or "")


@pytest.fixture(scope="module")
def authority() -> trustme.CA:
    """A private certificate authority, as an organisation's internal receivers are signed by."""
    return trustme.CA()


@pytest.fixture
def authority_file(authority: trustme.CA, tmp_path: Path) -> Path:
    path = tmp_path / "private-ca.pem"
    authority.cert_pem.write_to_path(str(path))
    return path


def test_a_webhook_over_https_is_delivered_once_its_certificate_authority_is_trusted(
    outbox: Outbox, authority: trustme.CA, authority_file: Path
):
    """A receiver whose certificate a private CA signed: refused while only certifi's and the
    system's authorities are trusted (nothing sent), delivered signed once the operator names
    the CA (NARXWATCH_NOTIFICATION_CA_FILE)."""
    with Receiver(SECRET, authority=authority) as receiver:
        assert receiver.url.startswith("https://")
        outbox.webhook(receiver.url, ["alarm.opened"])
        with transaction(outbox.sessions) as session:
            notifications.notify(session, outbox.organisation_id, "alarm.opened", PAYLOAD)
        assert outbox.run_jobs() == 1
        assert receiver.requests == []
        (delivery,) = outbox.deliveries()
        assert (delivery.status, delivery.attempts) == ("pending", 1)
        assert "CERTIFICATE_VERIFY_FAILED" in (delivery.last_error or ""), delivery.last_error
        outbox.settings = outbox.settings.model_copy(update={"notification_ca_file": authority_file})
        assert outbox.run_jobs(now=utcnow() + dt.timedelta(minutes=1)) == 1
        (request,) = receiver.requests
        assert request.signed and request.document()["data"] == PAYLOAD
    (delivery,) = outbox.deliveries()
    assert (delivery.status, delivery.attempts, delivery.last_status_code) == ("delivered", 2, 200)


def test_an_email_goes_through_starttls_once_the_relays_certificate_authority_is_trusted(
    outbox: Outbox, authority: trustme.CA, authority_file: Path
):
    """A relay that takes mail only after STARTTLS, its certificate signed by a private CA."""
    with Mailbox(authority=authority) as box:
        outbox.settings = outbox.settings.model_copy(update={"smtp_port": box.port, "smtp_starttls": True})
        outbox.subscription(["alarm.opened"])
        with transaction(outbox.sessions) as session:
            notifications.notify(session, outbox.organisation_id, "alarm.opened", PAYLOAD)
        assert outbox.run_jobs() == 1
        assert box.messages == []
        (delivery,) = outbox.deliveries()
        assert "CERTIFICATE_VERIFY_FAILED" in (delivery.last_error or ""), delivery.last_error
        outbox.settings = outbox.settings.model_copy(update={"notification_ca_file": authority_file})
        assert outbox.run_jobs(now=utcnow() + dt.timedelta(minutes=1)) == 1
        (message,) = box.messages
        assert message.rcpt_tos == ["a@example.com"]
    (delivery,) = outbox.deliveries()
    assert (delivery.status, delivery.attempts) == ("delivered", 2)


def test_a_certificate_authority_file_that_holds_no_certificate_is_refused_at_start(tmp_path: Path):
    missing, empty = tmp_path / "missing.pem", tmp_path / "empty.pem"
    empty.write_text("not a certificate\n")
    with pytest.raises(ValidationError, match="notification_ca_file"):
        Settings(notification_ca_file=missing)  # type: ignore[arg-type]
    with pytest.raises(ValidationError, match=r"empty\.pem holds no PEM certificate"):
        Settings(notification_ca_file=empty)  # type: ignore[arg-type]


def test_a_secret_sealed_under_a_key_the_server_lost_is_not_sent_and_a_rotation_keeps_every_secret(
    outbox: Outbox,
):
    """A webhook sealed under key A: a server given only key B makes no attempt it could not sign
    (the log says which setting to mend); given B then A, it delivers; resealed under B, B alone
    opens it. Each delivery signed with the secret as given."""
    keys = {name: SecretStr(Fernet.generate_key().decode()) for name in "AB"}

    def holding(*names: str) -> Settings:
        return outbox.settings.model_copy(update={"secret_keys": [keys[name] for name in names]})

    def announce_and_deliver(now: dt.datetime | None = None) -> None:
        with transaction(outbox.sessions) as session:
            notifications.notify(session, outbox.organisation_id, "alarm.opened", PAYLOAD)
        assert outbox.run_jobs(now) >= 1

    with Receiver(SECRET) as receiver:
        outbox.settings = holding("A")
        outbox.webhook(receiver.url, ["alarm.opened"])
        outbox.settings = holding("B")
        announce_and_deliver()
        assert receiver.requests == []
        (delivery,) = outbox.deliveries()
        assert delivery.status == "pending" and "NARXWATCH_SECRET_KEYS" in (delivery.last_error or "")
        outbox.settings = holding("B", "A")
        assert outbox.run_jobs(now=utcnow() + dt.timedelta(minutes=1)) == 1
        with transaction(outbox.sessions) as session:
            assert notifications.reseal_secrets(session, outbox.settings) == 1
        outbox.settings = holding("B")
        announce_and_deliver()
        assert len(receiver.requests) == 2 and all(request.signed for request in receiver.requests)
    assert [d.status for d in outbox.deliveries()] == ["delivered", "delivered"]


def test_the_key_file_is_made_once_for_its_owner_alone_whoever_starts_first(tmp_path: Path):
    """Eight processes' worth of threads reading a key file no one has made yet: one key, kept
    where the default database is by default, readable by its owner alone."""
    settings = Settings(secret_key_file=tmp_path / "narxwatch" / "secret.key")
    with ThreadPoolExecutor(8) as pool:
        list(pool.map(lambda _: check_keys(settings), range(8)))
    (key,) = settings.secret_key_file.read_text().split()
    assert settings.secret_key_file.stat().st_mode & 0o777 == 0o600
    assert (
        unseal(seal(SECRET, settings), settings.model_copy(update={"secret_keys": [SecretStr(key)]}))
        == SECRET
    )
    assert list(settings.secret_key_file.parent.iterdir()) == [settings.secret_key_file]  # no drafts left
    assert Settings.model_fields["secret_key_file"].default == DEFAULT_DATABASE.parent / "secret.key"


@pytest.fixture(scope="module")
def api_server(sqlite_api_server: LiveServer) -> LiveServer:
    return sqlite_api_server


def test_a_webhooks_secret_is_stored_sealed_and_never_shown_again(api_server: LiveServer):
    """What a copy of the database holds is no secret: only the server's key opens it."""
    with clients(Org.create(api_server)) as (admin, _, _):
        created = admin.post(f"{API}/webhooks", json=GOOD)
        assert created.status_code == 201, created.text
        listed = admin.get(f"{API}/webhooks")
    with api_server.app.state.sessions() as session:
        stored = session.get_one(Webhook, created.json()["id"]).secret
    assert SECRET not in stored and SECRET not in created.text + listed.text
    assert unseal(stored, api_server.settings) == SECRET


def test_an_attempt_ends_by_its_deadline_however_slowly_the_receiver_answers(outbox: Outbox):
    """A receiver that trickles its answer a byte at a time, each well within a per-read timeout:
    the attempt still ends at ``notification_timeout_seconds``."""
    outbox.settings = outbox.settings.model_copy(update={"notification_timeout_seconds": 1.0})
    listener = socket.socket()
    listener.bind(("127.0.0.1", 0))
    listener.listen()
    stop = threading.Event()

    def trickle() -> None:
        connection, _ = listener.accept()
        with connection:
            connection.recv(65536)
            for byte in b"HTTP/1.1 200 OK\r\nX-Slow: " + b"a" * 10_000:
                if stop.wait(0.2):
                    return
                try:
                    connection.sendall(bytes([byte]))
                except OSError:
                    return

    thread = threading.Thread(target=trickle, daemon=True)
    thread.start()
    outbox.webhook(f"http://127.0.0.1:{listener.getsockname()[1]}/slow", ["alarm.opened"])
    with transaction(outbox.sessions) as session:
        notifications.notify(session, outbox.organisation_id, "alarm.opened", PAYLOAD)
    started = time.monotonic()
    assert outbox.run_jobs() == 1
    elapsed = time.monotonic() - started
    stop.set()
    listener.close()
    (delivery,) = outbox.deliveries()
    assert delivery.status == "pending" and "timed out" in (delivery.last_error or ""), delivery.last_error
    assert elapsed < 3.0, f"the attempt took {elapsed:.1f} s for a 1 s deadline"


# --- over HTTP, delivered by each backend's workers --------------------------------------------


@pytest.fixture(scope="module")
def mailbox() -> Iterator[Mailbox]:
    with Mailbox() as box:
        yield box


@pytest.fixture(scope="module", params=["sqlite", "postgresql"])
def notifying(request, tmp_path_factory, mailbox: Mailbox) -> Iterator[LiveServer]:
    """The app with the tests' notification settings; on PostgreSQL with one `narxwatch worker`."""
    folder = tmp_path_factory.mktemp("notify")
    smtp = {"smtp_port": str(mailbox.port)}
    if request.param == "sqlite":
        settings = fast_settings(f"sqlite:///{folder / 'narxwatch.db'}", embedded_worker=True, **smtp)
        with LiveServer(settings) as server:
            yield server
        return
    url = migrated.postgresql(request.getfixturevalue("postgres_url"), f"notify_{uuid.uuid4().hex[:12]}")
    # The worker first: its start-up goes on while the server starts.
    with workers(url, 1, folder, **FAST, **smtp), LiveServer(fast_settings(url, **smtp)) as server:
        yield server


def announce(server: LiveServer, org: Org, event: str, payload: dict) -> None:
    """What the alarms code does at a transition: ``notify`` in the transaction of the change."""
    with transaction(server.app.state.sessions) as session:
        organisation_id = session.scalar(select(Organisation.id).where(Organisation.name == org.name))
        notifications.notify(session, organisation_id, event, payload)


def delivered(admin, path: str, count: int = 1) -> list[dict]:
    """The target's deliveries once ``count`` of them are no longer pending (within 60 s)."""

    def done() -> list[dict] | None:
        items = admin.get(f"{API}{path}/deliveries").json()["items"]
        return items if sum(item["status"] != "pending" for item in items) >= count else None

    return wait_for(done, 60, f"deliveries of {path}")  # type: ignore[return-value]


def delivered_event(admin, path: str, event: str) -> dict:
    """The target's delivery of ``event`` once it is no longer pending (within 60 s)."""

    def done() -> dict | None:
        items = admin.get(f"{API}{path}/deliveries").json()["items"]
        return next((i for i in items if i["event"] == event and i["status"] != "pending"), None)

    return wait_for(done, 60, f"{event} delivered to {path}")  # type: ignore[return-value]


# The retry policy and the senders are the domain's, whichever database holds the outbox: on
# SQLite's embedded worker here; on PostgreSQL the whole way's webhook (below) is answered 500 twice
# too, and retried by `narxwatch worker`'s sweep.
@pytest.mark.parametrize("notifying", ["sqlite"], indirect=True)
def test_an_event_answered_500_twice_is_applied_once_with_every_attempt_signed_and_logged(notifying):
    org = Org.create(notifying)
    with Receiver(SECRET, answers=[500, 500]) as receiver, clients(org) as (admin, _, _):
        created = admin.post(
            f"{API}/webhooks",
            json={"url": receiver.url, "secret": SECRET, "events": ["alarm.opened", "alarm.resolved"]},
        )
        assert created.status_code == 201, created.text
        webhook = created.json()
        assert "secret" not in json.dumps(webhook) and SECRET not in json.dumps(
            admin.get(f"{API}/webhooks").json()
        )
        announce(notifying, org, "alarm.acknowledged", PAYLOAD)  # not wanted by this webhook
        announce(notifying, org, "alarm.opened", PAYLOAD)
        (delivery,) = delivered(admin, f"/webhooks/{webhook['id']}")
    assert (delivery["status"], delivery["attempts"], delivery["last_status_code"]) == ("delivered", 3, 200)
    assert delivery["delivered_at"] is not None and delivery["next_attempt_at"] is None
    assert len(receiver.requests) == 3
    assert all(request.signed for request in receiver.requests), "a signature did not verify"
    assert {r.headers["idempotency-key"] for r in receiver.requests} == {delivery["key"]}
    assert {r.headers["narxwatch-event"] for r in receiver.requests} == {"alarm.opened"}
    (applied,) = receiver.applied.values()
    assert (
        applied["event"] == "alarm.opened" and applied["data"] == PAYLOAD and applied["id"] == delivery["key"]
    )
    gaps = [later.at - earlier.at for earlier, later in itertools.pairwise(receiver.requests)]
    assert gaps[0] >= 0.2 and gaps[1] >= 0.4, f"retried before the backoff: {gaps}"
    # A signature made with another secret, or over another body, does not verify.
    first = receiver.requests[0]
    assert not verify("whsec_" + "x" * 32, first.headers["narxwatch-signature"], first.body)
    assert not verify(SECRET, first.headers["narxwatch-signature"], first.body + b" ")


@pytest.mark.parametrize("notifying", ["sqlite"], indirect=True)
def test_an_event_is_mailed_through_a_real_smtp_server_after_a_refusal(notifying, mailbox: Mailbox):
    org = Org.create(notifying)
    addresses = [f"ops-{uuid.uuid4().hex[:6]}@example.com", "lead@example.org"]
    mailbox.refuse_next(1)
    with clients(org) as (admin, _, _):
        created = admin.post(
            f"{API}/email-subscriptions", json={"addresses": addresses, "events": ["alarm.opened"]}
        )
        assert created.status_code == 201, created.text
        subscription = created.json()
        announce(notifying, org, "alarm.opened", PAYLOAD)
        (delivery,) = delivered(admin, f"/email-subscriptions/{subscription['id']}")
    assert (delivery["status"], delivery["attempts"], delivery["last_status_code"]) == ("delivered", 2, 250)
    (envelope,) = [m for m in mailbox.messages if m.rcpt_tos == addresses]
    message = email.message_from_bytes(envelope.content, policy=policy.default)
    assert "alarm.opened" in message["Subject"] and message["Message-ID"] == f"<{delivery['key']}@narxwatch>"
    document = json.loads(message.get_content())
    assert (document["id"], document["event"], document["data"]) == (delivery["key"], "alarm.opened", PAYLOAD)


ONE_FAULT_OPENS = {"kind": "persistence", "k": 1, "m": 1, "clear_after": 5}


def test_an_alarm_raised_by_an_upload_is_delivered_once_though_the_receiver_answers_500_twice(notifying):
    """The whole way: a faulty record uploaded and inspected opens an alarm in the upload's
    transaction; its webhook gets "alarm.opened" (applied once, after two 500s), then, as nobody
    acknowledges it, "alarm.renotified"; acknowledged, "alarm.acknowledged"."""
    org = Org.create(notifying)
    events = ["alarm.opened", "alarm.acknowledged", "alarm.renotified"]
    receiving = Receiver(SECRET, answers=[500, 500], answers_for="alarm.opened")
    with receiving as receiver, clients(org) as (admin, ingest, viewer):
        structure_id = create_structure(admin)["id"]
        train_fault_mode(admin, ingest, structure_id, "k2", seed=81)
        rules = admin.put(f"{API}/structures/{structure_id}/alarm-rules", json={"rules": [ONE_FAULT_OPENS]})
        assert rules.status_code == 200, rules.text
        webhook = admin.post(
            f"{API}/webhooks", json={"url": receiver.url, "secret": SECRET, "events": events}
        )
        assert webhook.status_code == 201, webhook.text
        path = f"/webhooks/{webhook.json()['id']}"
        record = simulated("k2", 25.0, [82])
        body = npz_bytes(x=record.x, y=record.y, fs=record.fs)
        uploaded = post_record(ingest, structure_id, body, "application/x-npz", inspect="true")
        assert uploaded.status_code == 201 and uploaded.json()["verdict"]["status"] == "faulty", uploaded.text
        (alarm,) = viewer.get(f"{API}/alarms", params={"structure_id": structure_id}).json()["items"]
        opened = delivered_event(admin, path, "alarm.opened")
        assert (opened["status"], opened["attempts"], opened["last_status_code"]) == ("delivered", 3, 200)
        attempts = [r for r in receiver.requests if r.headers["idempotency-key"] == opened["key"]]
        assert [r.document()["data"] for r in attempts] == [alarm] * 3
        assert receiver.applied[opened["key"]]["data"] == alarm
        # Opened two periods ago, which waiting them out would give: the next notification
        # sweep announces it again, once (the one after is a period away).
        with transaction(notifying.app.state.sessions) as session:
            back = dt.timedelta(seconds=2 * float(FAST["renotify_after_seconds"]))
            earlier = dt.datetime.fromisoformat(alarm["opened_at"]) - back
            session.execute(update(Alarm).where(Alarm.id == alarm["id"]).values(opened_at=earlier))
        reminder = delivered_event(admin, path, "alarm.renotified")
        assert receiver.applied[reminder["key"]]["data"]["state"] == "open"
        acknowledged = admin.post(f"{API}/alarms/{alarm['id']}/acknowledge", json={"note": "on it"})
        assert acknowledged.status_code == 200, acknowledged.text
        last = delivered_event(admin, path, "alarm.acknowledged")
        assert receiver.applied[last["key"]]["data"] == acknowledged.json()
        logged = admin.get(f"{API}{path}/deliveries").json()["items"]
        assert sorted(d["event"] for d in logged) == sorted(events), "an event was announced twice"
        assert all(d["status"] == "delivered" for d in logged)
    assert len(receiver.applied) == 3, "an event was applied more than once"
    assert all(request.signed for request in receiver.requests)


def test_a_worker_killed_during_a_delivery_does_not_lose_it(postgres_url: str, tmp_path: Path):
    """The receiver has acted on the event but not yet answered when the worker dies: the job
    runs again on another worker, the delivery is made again with the same key, and the
    receiver's application, which keeps the keys it has seen, acts once."""
    url = migrated.postgresql(postgres_url, f"notify_kill_{uuid.uuid4().hex[:12]}")
    # Started first: its start-up goes on while the server starts.
    victim = Worker(url, tmp_path / "victim.log", **FAST, **FAST_FAILOVER)
    with LiveServer(fast_settings(url)) as server, Receiver(SECRET, answers=[HANG]) as receiver:
        org = Org.create(server)
        with clients(org) as (admin, _, _):
            webhook = admin.post(
                f"{API}/webhooks", json={"url": receiver.url, "secret": SECRET, "events": ["alarm.opened"]}
            ).json()
            announce(server, org, "alarm.opened", PAYLOAD)
            assert receiver.arrived.wait(60), "the worker never attempted the delivery"
            # The other worker starts while the victim holds the job: its start-up goes on while
            # the victim's missed heartbeats add up to a stall, not after.
            with workers(url, 1, tmp_path, **FAST, **FAST_FAILOVER):
                victim.kill()
                receiver.release.set()
                (delivery,) = delivered(admin, f"/webhooks/{webhook['id']}")
    assert (delivery["status"], delivery["attempts"]) == ("delivered", 2)
    assert len(receiver.requests) == 2 and len(receiver.applied) == 1
    assert {r.headers["idempotency-key"] for r in receiver.requests} == {delivery["key"]}
    with psycopg.connect(conninfo(url)) as connection:
        starts = connection.execute(
            "SELECT count(*) FROM procrastinate_events e JOIN procrastinate_jobs j ON j.id = e.job_id "
            "WHERE j.task_name = 'deliver' AND e.type = 'started'"
        ).fetchone()
    assert starts == (2,), "the killed delivery job should have started twice"


# A `narxwatch worker` of the embedded backend with a short lease (the command's is a minute), so
# that the test need not wait a minute for the killed worker's job to be claimed again.
EMBEDDED_WORKER = """
import datetime as dt, sys
from service.config import Settings
from service.db import make_engine, session_factory
from service.jobs.embedded import EmbeddedBackend
settings = Settings()
sessions = session_factory(make_engine(settings.database_url))
lease = dt.timedelta(seconds=float(sys.argv[1]))
EmbeddedBackend(sessions, settings, run_in_process=False, lease=lease).work(once=False)
"""


def test_an_embedded_worker_killed_during_a_delivery_does_not_lose_it(tmp_path: Path):
    """The same on SQLite: the killed worker's lease runs out, another worker claims the job
    again, and the receiver's application acts once on the two attempts."""
    url = migrated.sqlite(tmp_path / "narxwatch.db")
    lease = 1.0
    env = {**os.environ, "NARXWATCH_DATABASE_URL": url}
    env |= {f"NARXWATCH_{name.upper()}": value for name, value in FAST.items()}
    with LiveServer(fast_settings(url)) as server, Receiver(SECRET, answers=[HANG]) as receiver:
        org = Org.create(server)
        with clients(org) as (admin, _, _):
            webhook = admin.post(
                f"{API}/webhooks", json={"url": receiver.url, "secret": SECRET, "events": ["alarm.opened"]}
            ).json()
            announce(server, org, "alarm.opened", PAYLOAD)
            with (tmp_path / "victim.log").open("wb") as log:
                victim = subprocess.Popen(
                    [sys.executable, "-c", EMBEDDED_WORKER, str(lease)], env=env, stdout=log, stderr=log
                )
            try:
                assert receiver.arrived.wait(60), "the worker never attempted the delivery"
            finally:
                victim.kill()
                victim.wait(30)
            receiver.release.set()
            with server.app.state.sessions() as session:
                (job,) = session.scalars(select(Job).where(Job.task == notifications.DELIVER))
                assert (job.status, job.attempts) == ("running", 1), "the killed worker's job is not leased"
            rescuer = EmbeddedBackend(
                server.app.state.sessions,
                server.settings,
                run_in_process=False,
                lease=dt.timedelta(seconds=lease),
            )
            # Claimed again as soon as the lease the victim last renewed has run out.
            assert wait_for(rescuer.run_due, 30, "the killed worker's job was not claimed again") == 1
            (delivery,) = admin.get(f"{API}/webhooks/{webhook['id']}/deliveries").json()["items"]
    assert (delivery["status"], delivery["attempts"]) == ("delivered", 2)
    assert len(receiver.requests) == 2 and len(receiver.applied) == 1
    assert {r.headers["idempotency-key"] for r in receiver.requests} == {delivery["key"]}


# --- the API's refusals and tenancy (default settings: private targets refused, no SMTP) --------


def _ipv6(value: int) -> str:
    return str(ipaddress.IPv6Address(value))


def _teredo(server: str, client: str) -> str:
    """A Teredo address (RFC 4380 §4): prefix, server, flags, port and client, the last two
    obfuscated (every bit flipped)."""
    server_bits, client_bits = int(ipaddress.IPv4Address(server)), int(ipaddress.IPv4Address(client))
    return _ipv6(0x2001_0000 << 96 | server_bits << 64 | (3544 ^ 0xFFFF) << 32 | client_bits ^ 0xFFFF_FFFF)


LOOPBACK_IPV4 = "127.0.0.1"
PUBLIC_IPV4 = "8.8.8.8"
# Each IPv6 form that embeds or translates an IPv4 address, written from the RFCs (not with the
# service's code): the IPv4 it carries → the address.
EMBEDDINGS = {
    "IPv4-compatible ::/96": lambda v4: _ipv6(int(ipaddress.IPv4Address(v4))),
    "IPv4-mapped ::ffff:0:0/96": lambda v4: _ipv6(0xFFFF << 32 | int(ipaddress.IPv4Address(v4))),
    "IPv4-translated ::ffff:0:0:0/96": lambda v4: _ipv6(0xFFFF << 48 | int(ipaddress.IPv4Address(v4))),
    "NAT64 64:ff9b::/96": lambda v4: _ipv6(0x64_FF9B << 96 | int(ipaddress.IPv4Address(v4))),
    "NAT64 local-use 64:ff9b:1::/48": lambda v4: _ipv6(0x64_FF9B_0001 << 80 | int(ipaddress.IPv4Address(v4))),
    "6to4 2002::/16": lambda v4: _ipv6(0x2002 << 112 | int(ipaddress.IPv4Address(v4)) << 80 | 1),
    "Teredo server": lambda v4: _teredo(v4, PUBLIC_IPV4),
    "Teredo client": lambda v4: _teredo(PUBLIC_IPV4, v4),
}
INTERNAL_IPV4 = [LOOPBACK_IPV4, "10.0.0.1", "169.254.169.254", "192.168.1.1"]


@pytest.mark.parametrize("form", EMBEDDINGS)
def test_a_webhook_whose_address_carries_an_internal_ipv4_is_refused_naming_it(tenant, form):
    """Every form, carrying loopback, a private address, the cloud metadata address: a 422 naming
    the address and the IPv4 it carries. Carrying a public IPv4 it is admitted as that IPv4 would
    be, except in the local-use NAT64 prefix, whose other readings (RFC 6052 §2.2, by the
    operator's prefix length) carry 0.0.0.0 here."""
    for v4 in INTERNAL_IPV4:
        address = EMBEDDINGS[form](v4)
        response = tenant.admin.post(f"{API}/webhooks", json={**GOOD, "url": f"http://[{address}]:9100/"})
        assert response.status_code == 422, (address, response.text)
        assert address in detail(response) and v4 in detail(response), detail(response)
    assert tenant.admin.get(f"{API}/webhooks").json() == []
    public = EMBEDDINGS[form](PUBLIC_IPV4)
    response = tenant.admin.post(f"{API}/webhooks", json={**GOOD, "url": f"http://[{public}]/hooks"})
    if form.startswith("NAT64 local-use"):
        assert response.status_code == 422 and "0.0.0.0" in detail(response), response.text
    else:
        assert response.status_code == 201, (public, response.text)
        assert tenant.admin.delete(f"{API}/webhooks/{response.json()['id']}").status_code == 204


@pytest.mark.parametrize(
    "address",
    [
        "fec0::1",  # site-local
        "fd12:3456::1",  # unique-local
        "fe80::1",  # link-local
        "2001:db8::1",  # documentation
        "3fff::1",  # documentation
        "2001:2::1",  # benchmarking
        "ff02::1",  # multicast
        "192.0.2.1",  # documentation
        "198.51.100.7",  # documentation
        "203.0.113.9",  # documentation
        "198.18.0.1",  # benchmarking
        "100.64.0.1",  # shared (carrier-grade NAT)
        "0.1.2.3",  # "this network"
        "224.0.0.1",  # multicast
        "240.0.0.1",  # reserved
        "255.255.255.255",  # broadcast
    ],
)
def test_special_purpose_ranges_are_refused_at_creation(tenant, address):
    host = f"[{address}]" if ":" in address else address
    response = tenant.admin.post(f"{API}/webhooks", json={**GOOD, "url": f"https://{host}/hooks"})
    assert response.status_code == 422, response.text
    assert f"resolves to {address}," in detail(response) and "not a public address" in detail(response)


NO_ALLOWANCE = Settings(webhook_allowed_networks=[])


@pytest.mark.parametrize(
    ("address", "admitted"),
    [
        *((EMBEDDINGS[form](v4), False) for form in EMBEDDINGS for v4 in INTERNAL_IPV4),
        *((EMBEDDINGS[form](PUBLIC_IPV4), True) for form in EMBEDDINGS if "local-use" not in form),
        ("64:ff9b:1::808:808", False),  # read with a /48 prefix it carries 0.0.0.0
        ("64:ff9b:1:808:8:808:808:808", True),  # 8.8.8.8 whatever the local prefix's length
        ("64:ff9b:1:7f00:0:100:808:808", False),  # 8.8.8.8 at /96, 127.0.0.1 at /48
        (_teredo("10.0.0.1", "192.168.1.1"), False),
        ("::", False),
        ("::1", False),
        ("::ffff:0:0", False),  # carries 0.0.0.0
        ("2001:4860:4860::8888", True),
        ("2606:4700:4700::1111", True),
        ("8.8.8.8", True),
        ("93.184.215.14", True),
        ("fec0::1", False),
        ("fc00::1", False),
        ("fe80::1", False),
        ("2001:db8::1", False),
        ("3fff:fff::1", False),
        ("2001:2::1", False),
        ("ff0e::1", False),
        ("100.64.0.1", False),
        ("198.19.255.255", False),
        ("192.0.0.8", False),
        ("233.252.0.1", False),
        ("250.1.2.3", False),
    ],
)
def test_the_ssrf_rule_judges_an_address_by_its_range_and_every_ipv4_it_carries(address, admitted):
    assert senders.admitted(ipaddress.ip_address(address), NO_ALLOWANCE) is admitted


@pytest.mark.parametrize(
    ("address", "allowed", "admitted"),
    [
        (EMBEDDINGS["NAT64 64:ff9b::/96"](LOOPBACK_IPV4), ["127.0.0.0/8"], True),  # by the IPv4 it carries
        (_teredo("10.0.0.1", "192.168.1.1"), ["10.0.0.0/8"], False),  # one of two carried admitted
        (_teredo("10.0.0.1", "192.168.1.1"), ["10.0.0.0/8", "192.168.0.0/16"], True),
        ("fec0::1", ["fec0::/10"], True),
        ("64:ff9b:1::a00:1", ["64:ff9b:1::/48"], True),  # an operator's own local-use translator
        ("198.18.0.1", ["10.0.0.0/8"], False),
    ],
)
def test_the_operators_allowance_admits_what_it_names(address, allowed, admitted):
    settings = Settings(webhook_allowed_networks=allowed)  # type: ignore[arg-type]
    assert senders.admitted(ipaddress.ip_address(address), settings) is admitted
    assert senders.admitted(
        ipaddress.ip_address(address), settings.model_copy(update={"webhook_allow_private": True})
    )


GOOD = {"url": "https://93.184.215.14/hooks", "secret": SECRET, "events": ["alarm.opened"]}


@pytest.mark.parametrize(
    ("change", "message"),
    [
        ({"url": "ftp://93.184.215.14/hooks"}, "https:// or http://"),
        ({"url": "file:///etc/passwd"}, "https:// or http://"),
        ({"url": "hooks.example.com/x"}, "https:// or http://"),
        ({"url": "http://127.0.0.1:8000/hooks"}, "not a public address"),
        ({"url": "http://localhost/hooks"}, "not a public address"),
        ({"url": "http://10.1.2.3/hooks"}, "not a public address"),
        ({"url": "http://192.168.0.10/hooks"}, "not a public address"),
        ({"url": "http://169.254.169.254/latest/meta-data"}, "not a public address"),
        ({"url": "http://[::1]/hooks"}, "not a public address"),
        ({"url": "http://[::ffff:127.0.0.1]/hooks"}, "not a public address"),
        ({"url": "http://[fd00::1]/hooks"}, "not a public address"),
        ({"url": "http://0.0.0.0/hooks"}, "not a public address"),
        # IPv6 forms that carry a private IPv4 (loopback, metadata), and ranges Python counts as global.
        ({"url": "http://[::7f00:1]:9100/"}, "::7f00:1"),
        ({"url": "http://[::ffff:0:7f00:1]:9100/"}, "::ffff:0:7f00:1"),
        ({"url": "http://[64:ff9b::7f00:1]:9100/"}, "64:ff9b::7f00:1"),
        ({"url": "http://[64:ff9b::a9fe:a9fe]/latest/meta-data"}, "64:ff9b::a9fe:a9fe"),
        ({"url": "http://[2002:7f00:1::1]:9100/"}, "2002:7f00:1::1"),
        ({"url": "http://[fec0::1]/hooks"}, "fec0::1"),
        # Other spellings of 127.0.0.1: the addresses a name resolves to are checked, not its text.
        ({"url": "http://2130706433/hooks"}, "not a public address"),
        ({"url": "http://0x7f.1/hooks"}, "not a public address"),
        ({"url": "https://user:pw@93.184.215.14/hooks"}, "no user name or password"),
        ({"url": "https://93.184.215.14/a hook"}, "no spaces or control characters"),
        ({"secret": "too-short"}, "at least 32 characters"),
        ({"events": ["alarm.exploded"]}, "alarm.opened"),
        ({"events": []}, "at least 1 item"),
    ],
)
def test_a_bad_webhook_is_refused_with_a_clear_422_and_nothing_is_stored(tenant, change, message):
    response = tenant.admin.post(f"{API}/webhooks", json={**GOOD, **change})
    assert response.status_code == 422, response.text
    assert message in detail(response)
    assert tenant.admin.get(f"{API}/webhooks").json() == []


def test_an_admin_creates_lists_reads_the_log_of_and_deletes_a_webhook(api_server: LiveServer):
    owner = Org.create(api_server)
    with owner.client("admin") as admin:
        created = admin.post(f"{API}/webhooks", json=GOOD)
        assert created.status_code == 201, created.text
        webhook_id = created.json()["id"]
        assert [w["id"] for w in admin.get(f"{API}/webhooks").json()] == [webhook_id]
        assert admin.get(f"{API}/webhooks/{webhook_id}/deliveries").json() == {
            "items": [],
            "next_cursor": None,
        }
        assert admin.delete(f"{API}/webhooks/{webhook_id}").status_code == 204
        assert admin.get(f"{API}/webhooks").json() == []


def test_email_subscriptions_need_an_smtp_relay_and_valid_addresses(tenant):
    body = {"addresses": ["ops@example.com"], "events": ["alarm.opened"]}
    response = tenant.admin.post(f"{API}/email-subscriptions", json=body)
    assert response.status_code == 409 and "NARXWATCH_SMTP_HOST" in detail(response)
    bad = tenant.admin.post(
        f"{API}/email-subscriptions", json={**body, "addresses": ["ops@example.com, evil@x.org"]}
    )
    assert bad.status_code == 422, bad.text
    assert tenant.admin.get(f"{API}/email-subscriptions").json() == []


def test_the_delivery_log_counts_rows_only_of_its_target(outbox: Outbox):
    """A guard against a listing that leaks: deliveries are read by their own target's id."""
    mine = outbox.webhook("https://93.184.215.14/a", ["alarm.opened"])
    theirs = outbox.webhook("https://93.184.215.14/b", ["alarm.resolved"])
    with transaction(outbox.sessions) as session:
        notifications.notify(session, outbox.organisation_id, "alarm.opened", PAYLOAD)
        notifications.notify(session, outbox.organisation_id, "alarm.resolved", PAYLOAD)
    with outbox.sessions() as session:
        logged = notifications.deliveries(session, session.get(Webhook, mine), 10, None)
        assert [d.event for d in logged] == ["alarm.opened"]
        total = session.scalar(
            select(func.count()).select_from(Delivery).where(Delivery.webhook_id == theirs)
        )
        assert total == 1


def test_an_open_alarm_is_renotified_once_per_period_until_acknowledged(outbox: Outbox):
    outbox.webhook("https://93.184.215.14/hook", ["alarm.renotified"])
    opened = utcnow() - dt.timedelta(hours=2)
    with transaction(outbox.sessions) as session:
        structure = Structure(organisation_id=outbox.organisation_id, name="rig", fs=1500.0)
        session.add(structure)
        session.flush()
        alarms = [
            Alarm(
                structure_id=structure.id,
                organisation_id=outbox.organisation_id,
                rule_kind=kind,
                rule={"kind": kind},
                fault_mode="k2",
                state=state,
                opened_at=opened,
                triggered_at=opened,
                evaluated_through=opened,
            )
            for kind, state in (("persistence", "open"), ("severity", "acknowledged"))
        ]
        session.add_all(alarms)
        session.flush()
        open_id = alarms[0].id
    hour = dt.timedelta(hours=1)
    now = utcnow()
    with outbox.sessions() as session:
        assert renotify.sweep(session, dt.timedelta(hours=3), now) == 0, "renotified before its time"
        assert renotify.sweep(session, hour, now) == 1
        assert renotify.sweep(session, hour, now) == 0, "renotified twice in one period"
        assert renotify.sweep(session, hour, now + hour - dt.timedelta(seconds=1)) == 0
        assert renotify.sweep(session, hour, now + hour) == 1
        assert renotify.sweep(session, dt.timedelta(0), now + 5 * hour) == 0, "0 means never"
    found = outbox.deliveries()
    assert [d.event for d in found] == ["alarm.renotified"] * 2
    assert {(d.payload["id"], d.payload["state"]) for d in found} == {(open_id, "open")}
