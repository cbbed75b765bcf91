"""Service settings, read from the environment with the ``NARXWATCH_`` prefix."""

from __future__ import annotations

import base64
import binascii
import os
import ssl
from functools import lru_cache
from pathlib import Path
from typing import Literal

from pydantic import Field, FilePath, IPvAnyNetwork, SecretStr, ValidationError, field_validator
from pydantic_settings import BaseSettings, SettingsConfigDict

from service.errors import SettingsError


def _data_home() -> Path:
    """The user's data directory per the XDG base-directory spec: where the default database lives,
    whatever folder a command is run from (a path relative to it would start a new, empty one).
    A relative ``XDG_DATA_HOME`` is ignored, as the spec says."""
    configured = Path(os.environ.get("XDG_DATA_HOME", ""))
    return configured if configured.is_absolute() else Path.home() / ".local" / "share"


DEFAULT_DATABASE = _data_home() / "narxwatch" / "narxwatch.db"

KEY_FORM = "32 bytes in URL-safe base64 (a Fernet key)"


def is_key(key: str) -> bool:
    """Whether ``key`` can seal secrets (``service.sealing``): 32 bytes in URL-safe base64."""
    try:
        return len(base64.urlsafe_b64decode(key.encode("ascii"))) == 32
    except (binascii.Error, UnicodeEncodeError):
        return False


class Settings(BaseSettings):
    """Everything the service reads from its environment.

    ``database_url`` defaults to a SQLite file in the user's data directory
    (``$XDG_DATA_HOME/narxwatch/narxwatch.db``, ``~/.local/share/…`` without it); the same code runs on
    ``postgresql+psycopg://user:password@host/db``.
    """

    # Errors name the setting, never its value: it may be a password or a key.
    model_config = SettingsConfigDict(
        env_prefix="NARXWATCH_", env_file=".env", extra="ignore", hide_input_in_errors=True
    )

    database_url: str = f"sqlite:///{DEFAULT_DATABASE}"
    # The largest body of a record upload (a record or a record set): 413 beyond it, refused on its
    # declared length before it is read.
    max_upload_bytes: int = Field(16 * 1024 * 1024, gt=0)
    # The largest body of every other request: JSON documents of a few kilobytes (a training's
    # thousand experiments take about 40 kB), parsed before the route runs, at some 25 times
    # their size for nested arrays (service.api.limits).
    max_request_bytes: int = Field(1024 * 1024, gt=0)
    # The whole body of a request must arrive within this many seconds of its headers, or the
    # request is answered 408: a total, not a per-read bound, since a client trickling 2 bytes
    # every few seconds never trips a per-read one. 30 s carries a typical record (≤ 2 MB) over
    # a 1 Mbit/s link and the largest allowed body over 5 Mbit/s.
    body_timeout_seconds: float = Field(30.0, gt=0)
    # A request's head (request line and headers) must be complete within this many seconds of
    # the connection's opening, or of the previous response's end, or the connection is closed
    # (service.api.protocol). A head is a few hundred bytes to a few kB: one round trip, or a
    # few retransmissions on a lossy link. Longer than uvicorn's idle keep-alive wait (5 s), which
    # so still ends idle connections as before; a client trickling heads to hold connections
    # must open each anew this often.
    header_timeout_seconds: float = Field(10.0, gt=0)
    # The longest a request waits for a database connection when all are in use; then it is
    # answered 503 with Retry-After. Well under a client's patience (typically 10–30 s).
    pool_timeout_seconds: float = Field(5.0, gt=0)
    # How far an upload's acquired_at may lie ahead of the server's clock: the clocks of the systems
    # that acquire records drift, a little. A later time is refused (422): a record from the future
    # would stand for its structure's latest, and hide every fault acquired before its date.
    max_clock_skew_seconds: float = Field(300.0, ge=0)
    alpha: float = Field(0.05, gt=0, lt=0.5)
    lags: int = Field(40, ge=2)
    upgrade_on_start: bool = True
    history_page_size: int = Field(50, ge=1, le=1000)
    # "json": one JSON object a line (timestamp, level, logger, message, request_id, …).
    log_format: Literal["json", "text"] = "json"
    # When set, GET /metrics needs "Authorization: Bearer <token>"; unset, it is open (serve it
    # on an internal network only).
    metrics_token: SecretStr | None = Field(None, min_length=1)
    # Where queued inspections and schedules run (see service.jobs): "auto" is "embedded" on
    # SQLite and "distributed" (Procrastinate, `narxwatch worker` processes) on PostgreSQL.
    job_backend: Literal["auto", "embedded", "distributed"] = "auto"
    # Embedded backend: run jobs on a thread of each service process; off, they wait for
    # `narxwatch worker` processes.
    embedded_worker: bool = True
    # Distributed backend: a worker silent this long (killed, cut off) has its jobs run again.
    worker_heartbeat_seconds: float = Field(2.0, gt=0)
    worker_stalled_seconds: float = Field(10.0, gt=0)
    # Distributed backend: every this many seconds (a divisor of 60: whole seconds of a minute)
    # the workers sweep the schedules and notifications due and the jobs of stalled workers, which
    # wait up to this long more for it. Each sweep is a job, which idle workers run too.
    worker_sweep_seconds: int = Field(2, ge=1, le=60)
    # Dashboard logins: how long one lasts, and whether its cookie is sent over HTTPS only.
    # Browsers treat http://localhost and 127.0.0.1 as secure, so the default suits local use;
    # turn it off only behind a plain-HTTP proxy on a trusted network.
    dashboard_session_hours: float = Field(12.0, gt=0, le=24 * 30)
    session_cookie_secure: bool = True
    # Bounded cost of the expensive routes (docs: reference/limits.md). A cell is one sample times
    # one coefficient (a term, times the basis functions of a fault mode, plus a refinement's
    # candidate regressors): a fit peaks at about 40 bytes a cell (12 M cells: 0.5 GB, 14 s),
    # and its time grows with them. Above ``queue_training_cells`` it runs as a job (202).
    max_training_cells: int = Field(12_000_000, gt=0)
    queue_training_cells: int = Field(2_000_000, gt=0)
    # Coefficients of one model (terms × basis functions): its document holds their covariance,
    # so it grows with their square, and every page that draws the model reads it.
    max_model_coefficients: int = Field(200, gt=0)
    max_model_document_bytes: int = Field(2 * 1024 * 1024, gt=0)
    # Trainings, refinements and inspections of stored records running at once for one
    # organisation in one process; more are answered 429, so that no organisation can hold
    # every thread and pooled connection. One: each holds a core while it runs, and on a
    # machine of few cores two per worker process left another organisation's reads a p95 just
    # over a second under bench/abuse.py's attack.
    max_concurrent_expensive: int = Field(1, ge=1)
    # Record uploads worked on at once in one process (their bodies parsed, checked, inspected
    # and stored), whoever sends them; more wait for one to end, at most
    # ``upload_wait_seconds``, then are answered 503 with Retry-After. A parse holds a few times
    # its body in memory, and parsing and inspecting are mostly Python, which holds the
    # interpreter lock: a second upload in the same process runs no faster, it doubles the
    # memory, costs the threads' switching, and halves what the process's other requests get of
    # the CPU. One per process: with a worker process a core, as many uploads as cores. The
    # wait carries a queue of the largest bodies (a second or so each) and stays well under a
    # client's patience.
    max_concurrent_uploads: int = Field(1, ge=1)
    upload_wait_seconds: float = Field(10.0, gt=0)
    # Notifications (service.domain.notifications). Webhook targets must resolve to global
    # addresses (no loopback, private, link-local … ranges: SSRF), checked when a webhook is
    # created and again at each delivery; ``webhook_allow_private`` lifts that, and
    # ``webhook_allowed_networks`` (JSON list, e.g. '["10.1.0.0/16"]') admits chosen ranges.
    webhook_allow_private: bool = False
    webhook_allowed_networks: list[IPvAnyNetwork] = []
    # A PEM file of further certificate authorities that webhook receivers' and the SMTP relay's
    # certificates may be signed by (an organisation's private CA for admitted internal ranges),
    # trusted beside certifi's and the system's.
    notification_ca_file: FilePath | None = None
    # The keys sealing the secrets the service reads back (webhooks' signing secrets;
    # service.sealing): JSON list, the first sealing, every one unsealing. Unset: those of
    # ``secret_key_file`` (one a line), created with a new key where it does not exist.
    secret_keys: list[SecretStr] = []
    secret_key_file: Path = DEFAULT_DATABASE.parent / "secret.key"
    # One attempt (connect, send, answer; or an SMTP conversation) ends after this many seconds.
    notification_timeout_seconds: float = Field(10.0, gt=0, le=120)
    # A failed delivery is tried again after 30 s, 1, 2, 4 … min, up to this many attempts in all
    # (10: the last about 4 h after the first), then marked failed.
    delivery_max_attempts: int = Field(10, ge=1, le=50)
    delivery_first_retry_seconds: float = Field(30.0, gt=0)
    # An open alarm nobody acknowledged is announced again ("alarm.renotified") this long after it
    # was last announced; 0: never.
    renotify_after_seconds: float = Field(4 * 3600.0, ge=0)
    # Each organisation is pruned under its retention policy (service.domain.retention) this long
    # after it was created, then again after as long; 0: only by `narxwatch db prune`.
    retention_every_seconds: float = Field(24 * 3600.0, ge=0)
    # E-mail notifications go through this relay; without a host, e-mail subscriptions are refused.
    smtp_host: str | None = None
    smtp_port: int = Field(587, ge=1, le=65535)
    smtp_user: str | None = None
    smtp_password: SecretStr | None = None
    smtp_from: str = "narxwatch@localhost"
    smtp_starttls: bool = True

    @field_validator("worker_sweep_seconds")
    @classmethod
    def _divides_a_minute(cls, seconds: int) -> int:
        """The sweeps are Procrastinate's periodic tasks, on a cron of seconds: ``*/7`` would
        sweep 7 s apart, then 4 s across each minute's end."""
        if 60 % seconds:
            raise ValueError(f"{seconds} does not divide 60 (1, 2, 3, 4, 5, 6, 10, 12, 15, 20, 30 or 60)")
        return seconds

    @field_validator("notification_ca_file")
    @classmethod
    def _holds_certificates(cls, path: Path | None) -> Path | None:
        """Refused at start, not at each delivery: a file no TLS context can load."""
        if path is not None:
            try:
                ssl.SSLContext(ssl.PROTOCOL_TLS_CLIENT).load_verify_locations(path)
            except ssl.SSLError as exc:
                raise ValueError(f"{path} holds no PEM certificate ({exc.reason or exc})") from exc
        return path

    @field_validator("secret_keys")
    @classmethod
    def _are_keys(cls, keys: list[SecretStr]) -> list[SecretStr]:
        for position, key in enumerate(keys, 1):
            if not is_key(key.get_secret_value()):
                raise ValueError(f"key {position} of {len(keys)} is not {KEY_FORM}")
        return keys


@lru_cache
def get_settings() -> Settings:
    """The settings of this process; :class:`SettingsError` names every invalid one."""
    try:
        return Settings()
    except ValidationError as exc:
        problems = "; ".join(
            f"NARXWATCH_{str(error['loc'][0]).upper()}: {error['msg']}" for error in exc.errors()
        )
        raise SettingsError(f"invalid settings: {problems}") from None
