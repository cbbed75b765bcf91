"""Sending notifications: signed webhook POSTs and e-mails, each one bounded attempt.

Webhooks are signed as Stripe signs its events: ``Narxwatch-Signature: t=<unix time>,v1=<hex>``,
the HMAC-SHA256 under the webhook's secret of ``f"{t}.{body}"``; a receiver recomputes it and
refuses a stale ``t`` (replays). ``Idempotency-Key`` is the same on every attempt of a delivery.

Webhook targets are checked against SSRF when a webhook is created and again at each attempt
(DNS may have changed): the host's every address must be public (``admitted``: an IPv6 address
that carries an IPv4 one is judged by what it carries), unless the operator allows others. The
connection then goes to an address so checked (no second lookup an attacker could answer
differently), with TLS still verified against the host's name. That, and one
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
from collections.abc import Callable, Iterable
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
Reading = Callable[[ipaddress.IPv6Address], list[ipaddress.IPv4Address]]  # the IPv4s an address carries


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

_V4, _V6 = ipaddress.IPv4Network, ipaddress.IPv6Network

NOT_PUBLIC: tuple[ipaddress.IPv4Network | ipaddress.IPv6Network, ...] = (
    _V4("0.0.0.0/8"),  # "this network" (RFC 791, RFC 6890)
    _V4("10.0.0.0/8"),  # private (RFC 1918)
    _V4("100.64.0.0/10"),  # shared address space, carrier-grade NAT (RFC 6598)
    _V4("127.0.0.0/8"),  # loopback (RFC 1122)
    _V4("169.254.0.0/16"),  # link-local, where clouds serve instance metadata (RFC 3927)
    _V4("172.16.0.0/12"),  # private (RFC 1918)
    _V4("192.0.0.0/24"),  # IETF protocol assignments (RFC 6890)
    _V4("192.0.2.0/24"),  # documentation (RFC 5737)
    _V4("192.168.0.0/16"),  # private (RFC 1918)
    _V4("198.18.0.0/15"),  # benchmarking (RFC 2544)
    _V4("198.51.100.0/24"),  # documentation (RFC 5737)
    _V4("203.0.113.0/24"),  # documentation (RFC 5737)
    _V4("224.0.0.0/4"),  # multicast (RFC 5771)
    _V4("240.0.0.0/4"),  # reserved, and the limited broadcast address (RFC 1112, RFC 919)
    _V6("::/128"),  # unspecified (RFC 4291)
    _V6("::1/128"),  # loopback (RFC 4291)
    _V6("100::/64"),  # discard-only (RFC 6666)
    _V6("2001:2::/48"),  # benchmarking (RFC 5180)
    _V6("2001:db8::/32"),  # documentation (RFC 3849)
    _V6("3fff::/20"),  # documentation (RFC 9637)
    _V6("fc00::/7"),  # unique-local (RFC 4193)
    _V6("fe80::/10"),  # link-local (RFC 4291)
    _V6("fec0::/10"),  # site-local, deprecated but still routed by some networks (RFC 3879)
    _V6("ff00::/8"),  # multicast (RFC 4291)
)


def _rfc6052(*prefix_lengths: int) -> Reading:
    """The IPv4 addresses an address carries after a translation prefix of each length (RFC 6052
    §2.2: the 32 bits that follow the prefix, stepping over bits 64–71)."""

    def read(address: ipaddress.IPv6Address) -> list[ipaddress.IPv4Address]:
        bits = int(address) >> 64 << 56 | int(address) & (1 << 56) - 1  # bits 64–71 left out
        return [
            ipaddress.IPv4Address(bits >> (88 - (length if length <= 64 else length - 8)) & 0xFFFF_FFFF)
            for length in prefix_lengths
        ]

    return read


CARRIERS: tuple[tuple[ipaddress.IPv6Network, Reading], ...] = (
    (_V6("::/96"), _rfc6052(96)),  # IPv4-compatible, deprecated (RFC 4291 §2.5.5.1)
    (_V6("::ffff:0:0/96"), _rfc6052(96)),  # IPv4-mapped (RFC 4291 §2.5.5.2)
    (_V6("::ffff:0:0:0/96"), _rfc6052(96)),  # IPv4-translated, SIIT (RFC 2765 §2.1)
    (_V6("64:ff9b::/96"), _rfc6052(96)),  # NAT64's well-known prefix (RFC 6052 §2.1)
    # NAT64's local-use prefix (RFC 8215): the translator's prefix may be any RFC 6052 length
    # within it, which the address does not tell, so every reading is judged.
    (_V6("64:ff9b:1::/48"), _rfc6052(48, 56, 64, 96)),
    (_V6("2002::/16"), lambda address: [address.sixtofour]),  # 6to4 (RFC 3056 §2)
    (_V6("2001::/32"), lambda address: list(address.teredo)),  # Teredo: server, client (RFC 4380 §4)
)


def _not_public(address: Address) -> bool:
    return any(address in network for network in NOT_PUBLIC)


def carried_ipv4(address: Address) -> list[ipaddress.IPv4Address]:
    """The IPv4 addresses an IPv6 address embeds or is translated to (``CARRIERS``); none for
    any other address, nor for one ``NOT_PUBLIC`` already names (::1 is loopback, not 0.0.0.1)."""
    if isinstance(address, ipaddress.IPv6Address) and not _not_public(address):
        for network, read in CARRIERS:
            if address in network:
                return read(address)  # type: ignore[return-value]
    return []


def admitted(address: Address, settings: Settings) -> bool:
    """Whether a webhook may dial ``address``: the operator's allowance admits it
    (``webhook_allow_private``, or ``webhook_allowed_networks`` holds it); else it is in no
    ``NOT_PUBLIC`` range, every IPv4 it carries (``carried_ipv4``) is admitted, and one that
    carries none is global in Python's reading of the IANA special-purpose registries as well.

    An address that carries an IPv4 reaches that IPv4 on a network that translates (NAT64, SIIT,
    6to4, Teredo), where Python counts it as global or, as for 6to4 and Teredo, private whatever
    it carries: so it is judged by what it carries, and one carrying public IPv4 addresses only is
    admitted as they would be.
    """
    if settings.webhook_allow_private or any(address in net for net in settings.webhook_allowed_networks):
        return True
    if _not_public(address):
        return False
    if carried := carried_ipv4(address):
        return all(admitted(ipv4, settings) for ipv4 in carried)
    return address.is_global


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
    """The host's addresses, all of them admitted (``admitted``); ``InputError`` naming one
    that is not (and the IPv4 addresses it carries), or saying the host has none."""
    try:
        found = socket.getaddrinfo(host, port, type=socket.SOCK_STREAM)
    except (OSError, UnicodeError, ValueError) as exc:  # gaierror; IDNA; a name no resolver takes
        raise InputError(f"the webhook host {host!r} cannot be resolved: {exc}") from None
    addresses = list(dict.fromkeys(ipaddress.ip_address(str(info[4][0]).split("%")[0]) for info in found))
    refused = [address for address in addresses if not admitted(address, settings)]
    if refused or not addresses:
        named = str(refused[0]) if refused else "nothing"
        if carried := carried_ipv4(refused[0]) if refused else []:
            named += f" (carrying {', '.join(map(str, carried))})"
        raise InputError(
            f"the webhook host {host!r} resolves to {named}, which is not a "
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
