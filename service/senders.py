"""Sending notifications: signed webhook POSTs and e-mails, each one bounded attempt.

Webhooks are signed as Stripe signs its events: ``Narxwatch-Signature: t=<unix time>,v1=<hex>``,
the HMAC-SHA256 under the webhook's secret of ``f"{t}.{body}"``; a receiver recomputes it and
refuses a stale ``t`` (replays). ``Idempotency-Key`` is the same on every attempt of a delivery.

Webhook targets are checked against SSRF when a webhook is created and again at each attempt
(DNS may have changed): the host's every address must be global, unless the operator allows
private ranges. The connection then goes to an address so checked (no second lookup an attacker
could answer differently), with TLS still verified against the host's name. That, and one
deadline for the whole attempt (a per-read timeout alone lets a trickling peer hold a worker for
hours), is why this module speaks to httpcore, httpx's transport, below httpx's API, which offers
neither. Redirects are not followed (a redirect is a failed attempt) and at most
``ANSWER_BYTES`` of an answer are read.
"""

from __future__ import annotations

import datetime as dt
import hashlib
import hmac
import ipaddress
import json
import smtplib
import socket
import ssl
import time
from collections.abc import Iterable
from dataclasses import dataclass
from email.message import EmailMessage
from functools import cache
from pathlib import Path
from typing import Any
from urllib.parse import urlsplit

import httpcore

from models.errors import InputError
from service.config import Settings

SIGNATURE_HEADER = "Narxwatch-Signature"
ANSWER_BYTES = 1024  # of an answer's body, kept in the log of a failed attempt (up to 200 characters)
USER_AGENT = "narxwatch-webhooks/1"

Address = ipaddress.IPv4Address | ipaddress.IPv6Address


@dataclass(frozen=True)
class Message:
    """An event as it is sent: ``key`` identifies it to the receiver across attempts."""

    key: str
    event: str
    created_at: dt.datetime
    payload: dict[str, Any]

    def body(self) -> bytes:
        document = {
            "id": self.key,
            "event": self.event,
            "created_at": self.created_at.isoformat(),
            "data": self.payload,
        }
        return json.dumps(document, separators=(",", ":"), ensure_ascii=False).encode()


@dataclass(frozen=True)
class Outcome:
    delivered: bool
    status_code: int | None  # the HTTP status, or the SMTP reply code, when there was one
    error: str | None


def signature(secret: str, timestamp: int, body: bytes) -> str:
    """The header value: ``t=<timestamp>,v1=<hex HMAC-SHA256 of "t.body" under the secret>``."""
    digest = hmac.new(secret.encode(), f"{timestamp}.".encode() + body, hashlib.sha256).hexdigest()
    return f"t={timestamp},v1={digest}"


# --- SSRF --------------------------------------------------------------------------------------


def _admitted(address: Address, settings: Settings) -> bool:
    if settings.webhook_allow_private:
        return True
    if isinstance(address, ipaddress.IPv6Address) and address.ipv4_mapped is not None:
        address = address.ipv4_mapped  # ::ffff:127.0.0.1 is loopback
    if any(address in network for network in settings.webhook_allowed_networks):
        return True
    return address.is_global and not address.is_multicast


def checked_url(url: str) -> tuple[str, str, int]:
    """(scheme, host, port) of a webhook URL that is http(s), names a host and carries no
    credentials; ``InputError`` saying what is wrong otherwise."""
    try:
        parts = urlsplit(url)
        port = parts.port
    except ValueError as exc:
        raise InputError(f"the webhook URL cannot be read: {exc}") from None
    if parts.scheme not in ("http", "https"):
        raise InputError(
            f"a webhook URL must start with https:// or http://, not {parts.scheme or '(none)'}:"
        )
    if not parts.hostname:
        raise InputError("the webhook URL names no host")
    if parts.username is not None or parts.password is not None:
        raise InputError("a webhook URL carries no user name or password: the signature authenticates")
    return parts.scheme, parts.hostname, port or (443 if parts.scheme == "https" else 80)


def vetted_addresses(host: str, port: int, settings: Settings) -> list[Address]:
    """The host's addresses, all of them admitted (``_admitted``); ``InputError`` naming one
    that is not, or saying the host has none."""
    try:
        found = socket.getaddrinfo(host, port, type=socket.SOCK_STREAM)
    except (OSError, UnicodeError, ValueError) as exc:  # gaierror; IDNA; a name no resolver takes
        raise InputError(f"the webhook host {host!r} cannot be resolved: {exc}") from None
    addresses = list(dict.fromkeys(ipaddress.ip_address(str(info[4][0]).split("%")[0]) for info in found))
    refused = [address for address in addresses if not _admitted(address, settings)]
    if refused or not addresses:
        raise InputError(
            f"the webhook host {host!r} resolves to {refused[0] if refused else 'nothing'}, which is not a "
            "public address: private, loopback and link-local targets are refused unless the operator "
            "allows them (NARXWATCH_WEBHOOK_ALLOW_PRIVATE, NARXWATCH_WEBHOOK_ALLOWED_NETWORKS)"
        )
    return addresses


def check_webhook_url(url: str, settings: Settings) -> None:
    """Refuse (``InputError``) a URL a webhook may not target."""
    _, host, port = checked_url(url)
    vetted_addresses(host, port, settings)


class _Deadline(httpcore.SyncBackend):
    """Connects only to ``addresses`` (checked beforehand), and ends every read, write and
    connection by one deadline for the whole attempt."""

    def __init__(self, addresses: Iterable[Address], deadline: float) -> None:
        self._addresses = list(addresses)
        self._deadline = deadline

    def _remaining(self, timeout: float | None) -> float:
        left = self._deadline - time.monotonic()
        if left <= 0:
            raise httpcore.TimeoutException("the attempt ran out of time")
        return left if timeout is None else min(timeout, left)

    def connect_tcp(  # type: ignore[override]
        self, host: str, port: int, timeout: float | None = None, **options: Any
    ) -> httpcore.NetworkStream:
        error: Exception | None = None
        for address in self._addresses:
            try:
                stream = super().connect_tcp(str(address), port, self._remaining(timeout), **options)
                return _BoundedStream(stream, self)
            except httpcore.ConnectError as exc:
                error = exc
        raise error or httpcore.ConnectError("no address to connect to")


class _BoundedStream(httpcore.NetworkStream):
    def __init__(self, stream: httpcore.NetworkStream, backend: _Deadline) -> None:
        self._stream = stream
        self._backend = backend

    def read(self, max_bytes: int, timeout: float | None = None) -> bytes:
        return self._stream.read(max_bytes, self._backend._remaining(timeout))

    def write(self, buffer: bytes, timeout: float | None = None) -> None:
        self._stream.write(buffer, self._backend._remaining(timeout))

    def close(self) -> None:
        self._stream.close()

    def start_tls(
        self, ssl_context: ssl.SSLContext, server_hostname: str | None = None, timeout: float | None = None
    ) -> httpcore.NetworkStream:
        upgraded = self._stream.start_tls(ssl_context, server_hostname, self._backend._remaining(timeout))
        return _BoundedStream(upgraded, self._backend)

    def get_extra_info(self, info: str) -> Any:
        return self._stream.get_extra_info(info)


@cache
def tls_context(ca_file: Path | None) -> ssl.SSLContext:
    """What every delivery's TLS is verified against: certifi's and the system's certificate
    authorities, and ``ca_file``'s (``NARXWATCH_NOTIFICATION_CA_FILE``).

    Built once per file, not per attempt: reading the CA bundle takes about 70 ms of CPU, which
    httpcore spent on every delivery when it built its default context for each pool. A context
    is safe to share between threads once configured.
    """
    context = httpcore.default_ssl_context()
    if ca_file is not None:
        context.load_verify_locations(ca_file)
    return context


def post_webhook(url: str, secret: str, delivery_id: int, message: Message, settings: Settings) -> Outcome:
    """One signed POST of ``message`` to ``url``: delivered on a 2xx answer."""
    deadline = time.monotonic() + settings.notification_timeout_seconds
    try:
        _, host, port = checked_url(url)
        addresses = vetted_addresses(host, port, settings)
    except InputError as refused:
        return Outcome(False, None, str(refused))
    body = message.body()
    headers = {
        "Content-Type": "application/json",
        "User-Agent": USER_AGENT,
        "Idempotency-Key": message.key,
        "Narxwatch-Event": message.event,
        "Narxwatch-Delivery": str(delivery_id),
        SIGNATURE_HEADER: signature(secret, int(time.time()), body),
    }
    timeout = settings.notification_timeout_seconds
    extensions = {"timeout": {"connect": timeout, "read": timeout, "write": timeout, "pool": timeout}}
    try:
        with (
            httpcore.ConnectionPool(
                ssl_context=tls_context(settings.notification_ca_file),
                network_backend=_Deadline(addresses, deadline),
                max_connections=1,
            ) as pool,
            pool.stream("POST", url, headers=headers, content=body, extensions=extensions) as answer,
        ):
            status = answer.status
            start = _read_at_most(answer.iter_stream(), ANSWER_BYTES)
    except httpcore.TimeoutException as exc:
        return Outcome(False, None, f"timed out after {timeout:g} s: {exc or 'no answer'}")
    except (httpcore.NetworkError, httpcore.ProtocolError, ssl.SSLError, OSError) as exc:
        return Outcome(False, None, f"{type(exc).__name__}: {exc}")
    if 200 <= status < 300:
        return Outcome(True, status, None)
    said = start.decode(errors="replace").strip()[:200]
    why = "redirects are not followed" if 300 <= status < 400 else said
    return Outcome(False, status, f"HTTP {status}" + (f": {why}" if why else ""))


def _read_at_most(chunks: Iterable[bytes], limit: int) -> bytes:
    read = b""
    for chunk in chunks:
        read += chunk
        if len(read) >= limit:
            break
    return read[:limit]


# --- e-mail ------------------------------------------------------------------------------------


def email_message(addresses: list[str], message: Message, sender: str) -> EmailMessage:
    """The e-mail of an event: its subject names the event and the alarm's structure when the
    payload has them; the body is the event's JSON, as a webhook receives it."""
    email = EmailMessage()
    about = message.payload.get("structure_name") or message.payload.get("structure_id")
    email["Subject"] = f"[narxwatch] {message.event}" + (f": {about}" if about is not None else "")
    email["From"] = sender
    email["To"] = ", ".join(addresses)
    email["Message-ID"] = f"<{message.key}@narxwatch>"  # the same on every attempt: mail clients dedupe
    email.set_content(json.dumps(json.loads(message.body()), indent=2, ensure_ascii=False))
    return email


def send_email(addresses: list[str], message: Message, settings: Settings) -> Outcome:
    """One SMTP conversation through the configured relay: delivered when it accepts the mail
    for every address."""
    if settings.smtp_host is None:
        return Outcome(False, None, "no SMTP relay is configured (NARXWATCH_SMTP_HOST)")
    email = email_message(addresses, message, settings.smtp_from)
    try:
        with smtplib.SMTP(
            settings.smtp_host, settings.smtp_port, timeout=settings.notification_timeout_seconds
        ) as smtp:
            if settings.smtp_starttls:
                smtp.starttls(context=tls_context(settings.notification_ca_file))
            if settings.smtp_user is not None:
                password = settings.smtp_password.get_secret_value() if settings.smtp_password else ""
                smtp.login(settings.smtp_user, password)
            refused = smtp.send_message(email)
    except smtplib.SMTPResponseException as exc:
        return Outcome(
            False, exc.smtp_code, f"SMTP {exc.smtp_code}: {exc.smtp_error.decode(errors='replace')}"
        )
    except smtplib.SMTPRecipientsRefused as exc:
        return Outcome(False, None, f"every address was refused: {', '.join(exc.recipients)}")
    except (smtplib.SMTPException, OSError) as exc:
        return Outcome(False, None, f"{type(exc).__name__}: {exc}")
    if refused:
        return Outcome(False, None, f"refused addresses: {', '.join(refused)}")
    return Outcome(True, 250, None)
