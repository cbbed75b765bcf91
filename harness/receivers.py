"""What notifications are delivered to in the tests: a real HTTP receiver and a real SMTP server.

The receiver checks every request's signature the way a webhook's owner would (recomputing the
HMAC-SHA256 of ``t.body`` with the shared secret, refusing a stale ``t``), answers with the
statuses it is told to, in order, and "applies" each event once, by its ``Idempotency-Key``, as an
application that keeps the keys it has seen does.
"""

from __future__ import annotations

import hashlib
import hmac
import json
import ssl
import threading
import time
from collections.abc import Iterable
from dataclasses import dataclass, field
from http.server import BaseHTTPRequestHandler, ThreadingHTTPServer
from typing import Any

import trustme
from aiosmtpd.controller import Controller
from aiosmtpd.smtp import SMTP, Envelope, Session

from harness.live import free_port

HOST = "127.0.0.1"

TOLERANCE = 300  # seconds a signature's timestamp may be old (Stripe's default)
HANG = 0  # an "answer" that holds the request until ``release`` is set, then answers 200


def verify(secret: str, header: str, body: bytes, now: float | None = None) -> bool:
    """A receiver's check of ``Narxwatch-Signature: t=…,v1=…``: written here from the scheme,
    not with the service's code."""
    fields = dict(part.split("=", 1) for part in header.split(",") if "=" in part)
    if "t" not in fields or "v1" not in fields or not fields["t"].isdigit():
        return False
    if abs((now or time.time()) - int(fields["t"])) > TOLERANCE:
        return False
    expected = hmac.new(secret.encode(), fields["t"].encode() + b"." + body, hashlib.sha256).hexdigest()
    return hmac.compare_digest(expected, fields["v1"])


@dataclass
class Request:
    headers: dict[str, str]  # names in lower case
    body: bytes
    signed: bool
    at: float = field(default_factory=time.monotonic)

    def document(self) -> dict[str, Any]:
        return json.loads(self.body)


@dataclass
class Receiver:
    """``with Receiver(secret, [500, 500, 200]) as receiver:`` serves on ``receiver.url`` until
    the block ends; once the answers are used up it answers 200. With ``answers_for``, the
    scripted answers go to that event's requests alone (others get 200), so that an event sent
    while another is being retried cannot take one of its answers. With ``authority``, over HTTPS,
    its certificate for 127.0.0.1 signed by that certificate authority."""

    secret: str
    answers: Iterable[int] = ()
    answers_for: str | None = None
    authority: trustme.CA | None = None
    requests: list[Request] = field(default_factory=list)
    applied: dict[str, dict[str, Any]] = field(default_factory=dict)  # events acted on, by key
    release: threading.Event = field(default_factory=threading.Event)
    arrived: threading.Event = field(default_factory=threading.Event)

    def __post_init__(self) -> None:
        self._answers = iter(self.answers)
        self._lock = threading.Lock()
        receiver = self

        class Handler(BaseHTTPRequestHandler):
            def do_POST(self) -> None:
                body = self.rfile.read(int(self.headers.get("Content-Length", "0")))
                signed = verify(receiver.secret, self.headers.get("Narxwatch-Signature", ""), body)
                headers = {name.lower(): value for name, value in self.headers.items()}
                status = receiver._record(Request(headers, body, signed))
                self.send_response(status)
                self.send_header("Content-Length", "2")
                self.end_headers()
                self.wfile.write(b"{}")

            def log_message(self, *args: Any) -> None:
                pass

        self._server = ThreadingHTTPServer((HOST, free_port()), Handler)
        if self.authority is not None:
            serving = _serving_tls(self.authority)
            self._server.socket = serving.wrap_socket(self._server.socket, server_side=True)
        self._server.daemon_threads = True
        self._thread = threading.Thread(target=self._server.serve_forever, daemon=True)

    def _record(self, request: Request) -> int:
        with self._lock:
            self.requests.append(request)
            scripted = self.answers_for is None or request.document().get("event") == self.answers_for
            status = next(self._answers, 200) if scripted else 200
        self.arrived.set()
        if not request.signed:
            return 400
        if status in (200, HANG):  # the application acts on an event it has not seen yet
            key = request.headers["idempotency-key"]
            with self._lock:
                self.applied.setdefault(key, request.document())
        if status == HANG:
            self.release.wait(60)
            return 200
        return status

    @property
    def url(self) -> str:
        scheme = "http" if self.authority is None else "https"
        return f"{scheme}://{HOST}:{self._server.server_address[1]}/hooks/narxwatch"

    def __enter__(self) -> Receiver:
        self._thread.start()
        return self

    def __exit__(self, *_: object) -> None:
        self.release.set()
        self._server.shutdown()
        self._server.server_close()


class Mailbox:
    """A real SMTP server (aiosmtpd) on loopback keeping the messages it accepts; after
    ``refuse_next(n)`` it answers ``451`` (try again later) to the next ``n``. With ``authority``
    it takes mail only after STARTTLS, its certificate signed by that certificate authority."""

    def __init__(self, authority: trustme.CA | None = None) -> None:
        self.messages: list[Envelope] = []
        self.refused = 0
        self._refuse = 0
        self.port = free_port()
        tls = {} if authority is None else {"tls_context": _serving_tls(authority), "require_starttls": True}
        self._controller = Controller(self, hostname=HOST, port=self.port, **tls)

    async def handle_DATA(self, server: SMTP, session: Session, envelope: Envelope) -> str:  # noqa: N802
        if self.refused < self._refuse:
            self.refused += 1
            return "451 4.3.0 try again later"
        self.messages.append(envelope)
        return "250 OK"

    def refuse_next(self, count: int) -> None:
        self.refused, self._refuse = 0, count

    def __enter__(self) -> Mailbox:
        self._controller.start()
        return self

    def __exit__(self, *_: object) -> None:
        self._controller.stop()


def _serving_tls(authority: trustme.CA) -> ssl.SSLContext:
    """A server's TLS context, its certificate for ``HOST`` signed by ``authority``."""
    context = ssl.create_default_context(ssl.Purpose.CLIENT_AUTH)
    authority.issue_cert(HOST).configure_cert(context)
    return context
