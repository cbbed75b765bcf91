"""Service commands: ``serve``, ``worker``, ``db upgrade/prune/vacuum``, ``keys create/list/revoke``,
``demo-seed``."""

from __future__ import annotations

import contextlib
import datetime as dt
import logging
import os
import re
import resource
import shutil
import tempfile
import time
from pathlib import Path
from typing import Annotated

import typer
from rich.table import Table
from rich.text import Text
from sqlalchemy.orm import Session, sessionmaker

from service.cli.console import fail, stderr, stdout
from service.config import get_settings
from service.db import make_engine, session_factory, transaction, vacuum
from service.domain import keys
from service.domain.errors import NotFoundError
from service.errors import DatabaseUnreachableError
from service.migrate import database_name, require_current_schema, upgrade_database
from service.observability.logs import configure_logging, logging_config
from service.security import KeyRefusedError, Role, authenticate, create_key
from service.tables import utcnow

db_app = typer.Typer(help="Database schema.", no_args_is_help=True)
keys_app = typer.Typer(help="API keys.", no_args_is_help=True)
log = logging.getLogger("narxwatch")


WORKER_HEALTHCHECK_SECONDS = 60


def serve(
    host: Annotated[str, typer.Option(help="Interface to listen on.")] = "127.0.0.1",
    port: Annotated[int, typer.Option(help="TCP port.", min=1, max=65535)] = 8000,
    workers: Annotated[int, typer.Option(help="Worker processes.", min=1)] = 1,
) -> None:
    """Serve the REST API (upgrading the database schema first, unless told not to).

    Logs go to stderr in NARXWATCH_LOG_FORMAT (json or text), one line per request. With several
    workers, the request-latency metrics are shared through files in PROMETHEUS_MULTIPROC_DIR: a
    fresh temporary folder, removed at exit, unless the variable names one.
    """
    # Imported here: the other commands of this module do not need it.
    import uvicorn

    from service import sealing
    from service.observability import MULTIPROCESS_DIR

    settings = get_settings()
    if not settings.upgrade_on_start:
        require_current_schema(settings.database_url)
    json_logs = settings.log_format == "json"
    configure_logging("INFO", json=json_logs)
    if settings.upgrade_on_start:
        upgrade_database(settings.database_url)
    sealing.check_keys(settings)  # here, where a key file it cannot read ends in one line
    # Upgraded once here: the workers must not race each other to do it again.
    os.environ["NARXWATCH_UPGRADE_ON_START"] = "false"
    metrics_dir = None
    if workers > 1 and not os.environ.get(MULTIPROCESS_DIR):
        # Set before uvicorn starts the workers: prometheus-client picks its mode at import.
        metrics_dir = os.environ[MULTIPROCESS_DIR] = tempfile.mkdtemp(prefix="narxwatch-metrics-")
    _open_files_to_the_hard_limit()  # before the workers start: they inherit it
    log.info("narxwatch API on http://%s:%s (docs: http://%s:%s/docs)", host, port, host, port)
    try:
        uvicorn.run(
            "service.api.app:create_app",
            factory=True,
            host=host,
            port=port,
            workers=workers,
            # NARXWATCH_HEADER_TIMEOUT_SECONDS bounds each request's head. Named, as the app is:
            # imported where it serves, not in a supervisor of several workers, which needs neither.
            http="service.api.protocol:HeaderTimeoutProtocol",
            # uvicorn kills a worker that does not answer its supervisor's ping within this time
            # (5 s by default): importing the app on a loaded machine, or a long numerical step
            # holding the GIL, can take longer than that without anything being wrong.
            timeout_worker_healthcheck=WORKER_HEALTHCHECK_SECONDS,
            log_level="info",
            log_config=logging_config("INFO", json=json_logs),  # applied again in each worker
            access_log=False,  # narxwatch.access logs each request, with its route and duration
        )
    finally:
        if metrics_dir is not None:
            shutil.rmtree(metrics_dir, ignore_errors=True)


def _open_files_to_the_hard_limit() -> None:
    """Raise this process's soft limit on open files to its hard limit.

    Every connection holds a file descriptor until it is closed, and the soft limit a service
    is often given (1024 under systemd) is soon reached by many slow or idle clients: then the
    server can accept no one else until some go. Python's event loops wait with epoll, so many
    descriptors cost nothing more; the hard limit stays the administrator's bound.
    """
    soft, hard = resource.getrlimit(resource.RLIMIT_NOFILE)
    # An unlimited hard limit is refused (above what the kernel allows): the soft one then stays.
    with contextlib.suppress(ValueError, OSError):
        if soft != hard:
            resource.setrlimit(resource.RLIMIT_NOFILE, (hard, hard))


def worker(
    once: Annotated[bool, typer.Option(help="Run the jobs due now, then exit.")] = False,
    concurrency: Annotated[
        int, typer.Option(help="Jobs run at once by this worker (distributed backend).", min=1, max=64)
    ] = 1,
) -> None:
    """Run queued inspections and scheduled runs, until stopped (Ctrl-C, SIGTERM).

    Any number may run, on any machine that reaches the database; each job runs at least once,
    and its verdict is stored once. On PostgreSQL this is a Procrastinate worker; on SQLite it
    serves a service started with NARXWATCH_EMBEDDED_WORKER=false.
    """
    from service.jobs.backends import backend_name, job_backend

    settings = get_settings()
    if backend_name(settings) == "embedded" and concurrency > 1:
        fail("--concurrency applies to the distributed backend (PostgreSQL); run more workers instead")
    try:
        _wait_for_current_schema(settings.database_url)
    except KeyboardInterrupt:
        return
    from service import sealing

    sealing.check_keys(settings)
    configure_logging("INFO", json=settings.log_format == "json")
    backend = job_backend(settings, session_factory(make_engine(settings.database_url)), in_service=False)
    if not once:
        stdout.print(f"narxwatch worker ({backend.name} backend): running jobs (Ctrl-C stops)")
    try:
        ran = backend.work(once=once, concurrency=concurrency)
    except KeyboardInterrupt:
        backend.stop()
        return
    if once:
        stdout.print(f"ran {ran} job(s)" if ran is not None else "ran every job due")


def _wait_for_current_schema(database_url: str) -> None:
    """Check the schema as every command does, but wait for a database that does not answer: a
    worker started while its server starts or restarts (or is away) must come up by itself, as a
    running worker that loses the database does. A missing or old schema is refused at once."""
    from service.jobs.types import RESTART_FIRST, RESTART_MAX

    delay = RESTART_FIRST
    while True:
        try:
            require_current_schema(database_url)
            return
        except DatabaseUnreachableError as exc:
            stderr.print(
                f"waiting: {exc}; trying again in {delay:.0f} s",
                markup=False,
                highlight=False,
                soft_wrap=True,
            )
            time.sleep(delay)
            delay = min(2 * delay, RESTART_MAX)


@db_app.command("upgrade")
def db_upgrade(revision: Annotated[str, typer.Argument(help="Target revision.")] = "head") -> None:
    """Bring the database schema (NARXWATCH_DATABASE_URL) up to date."""
    settings = get_settings()
    upgrade_database(settings.database_url, revision)
    stdout.print(f"database at {database_name(settings.database_url)} is at revision {revision}")


PASSES = {
    "signals": "records' signals dropped",
    "verdicts": "verdicts deleted",
    "records": "records deleted",
    "deliveries": "deliveries deleted",
}


@db_app.command("prune")
def db_prune(
    org: Annotated[str | None, typer.Option(help="Only this organisation (default: every one).")] = None,
    batch: Annotated[
        int | None,
        typer.Option(
            help="Rows per transaction, an upload waiting at most one (default: as the job workers prune).",
            min=1,
            max=10_000,
        ),
    ] = None,
) -> None:
    """Prune now under each organisation's retention policy (as the job workers do periodically),
    printing each batch as it is committed."""
    # Imported here: retention brings the schemas and the science they name, seconds that
    # `narxwatch keys` and `db upgrade` should not pay.
    from service.domain import retention

    sessions = ready_sessions()
    with sessions() as session:
        chosen = retention.organisations(session, org)
    if not chosen:
        fail(f"no organisation named {org!r}" if org is not None else "no organisations yet")
    for organisation_id, name in chosen:
        with sessions() as session:

            def shown(done: retention.Batch, name: str = name) -> None:
                stdout.print(
                    f"{name}: {done.rows} {PASSES[done.what]}", markup=False, highlight=False, soft_wrap=True
                )

            pruned = retention.prune(session, organisation_id, batch=batch or retention.BATCH, progress=shown)
        counts = ", ".join(f"{getattr(pruned, what)} {done}" for what, done in PASSES.items())
        stdout.print(
            f"{name}: {counts}, in {pruned.batches} batch(es)",
            markup=False,
            highlight=False,
            soft_wrap=True,
        )


@db_app.command("reseal")
def db_reseal() -> None:
    """Seal every webhook's signing secret again under the first of the server's keys
    (NARXWATCH_SECRET_KEYS, or the key file): the last step of a key's rotation, after which the
    keys behind the first may go. All or none: a secret no key opens leaves every one as it was."""
    from service.domain import notifications
    from service.domain.errors import ConflictError

    settings = get_settings()
    try:
        with transaction(ready_sessions()) as session:
            resealed = notifications.reseal_secrets(session, settings)
    except ConflictError as exc:
        fail(str(exc))
    stdout.print(f"{resealed} webhook secret(s) sealed under the first key", markup=False, soft_wrap=True)


@db_app.command("vacuum")
def db_vacuum() -> None:
    """Give the space of pruned signals and rows back: on SQLite the file shrinks (uploads wait
    while it is rewritten); on PostgreSQL the space is reused and the statistics refreshed."""
    database_url = get_settings().database_url
    require_current_schema(database_url)
    engine = make_engine(database_url)
    try:
        vacuum(engine)
    finally:
        engine.dispose()
    stdout.print(f"database at {database_name(database_url)} vacuumed", markup=False, soft_wrap=True)


def ready_sessions() -> sessionmaker[Session]:
    """Sessions on the configured database, once it is known to exist at the newest schema: a
    command that only reads or adds rows must not create an empty database by opening it."""
    database_url = get_settings().database_url
    require_current_schema(database_url)
    return session_factory(make_engine(database_url))


@keys_app.command("create")
def keys_create(
    org: Annotated[str, typer.Option(help="Organisation name (created if new).")],
    role: Annotated[str, typer.Option(help="admin, ingest or viewer.")],
    expires: Annotated[
        str | None,
        typer.Option(
            help="When the key stops working: a duration from now (90m, 12h, 30d, 2w) or an ISO date "
            "(midnight UTC) or time with a zone. Default: never (until revoked)."
        ),
    ] = None,
) -> None:
    """Create an API key and print it once: only its hash is stored."""
    if role not in Role.__members__:
        fail(f"unknown role {role!r}: choose admin, ingest or viewer")
    expires_at = None if expires is None else _expiry(expires, utcnow())
    with transaction(ready_sessions()) as session:
        key = create_key(session, org, Role[role], expires_at)
    print(key)


@keys_app.command("list")
def keys_list(
    org: Annotated[str | None, typer.Option(help="Only this organisation's keys.")] = None,
) -> None:
    """List the keys (never the keys themselves nor their hashes), times in UTC."""
    with transaction(ready_sessions()) as session:
        rows = [key for key in keys.list_keys(session) if org is None or key.organisation.name == org]
        table = Table(
            "id", "organisation", "prefix", "role", "created", "expires", "last used", "revoked", box=None
        )
        for key in rows:
            table.add_row(
                str(key.id),
                Text(key.organisation.name),  # a name is not rich markup
                key.prefix,
                key.role,
                *(_when(t) for t in (key.created_at, key.expires_at, key.last_used_at, key.revoked_at)),
            )
    if not rows and org is not None:
        fail(f"organisation {org!r} has no keys")
    stdout.print(table if rows else "no keys yet: create one with `narxwatch keys create`")


@keys_app.command("revoke")
def keys_revoke(
    key: Annotated[str, typer.Argument(help="The key's id or prefix, as `narxwatch keys list` shows them.")],
) -> None:
    """Revoke a key at once; the dashboard logins opened with it end too."""
    with transaction(ready_sessions()) as session:
        try:
            revoked = keys.revoke_key(session, keys.find_key(session, key.strip()))
        except NotFoundError as exc:
            fail(str(exc))
        stdout.print(
            f"key {revoked.id} ({revoked.prefix}, {revoked.role} of {revoked.organisation.name!r}) "
            f"revoked at {_when(revoked.revoked_at)} UTC; its dashboard logins ended",
            markup=False,
        )


_DURATION = re.compile(r"(\d+)\s*([smhdw])")
_UNITS = {"s": "seconds", "m": "minutes", "h": "hours", "d": "days", "w": "weeks"}


def _expiry(text: str, now: dt.datetime) -> dt.datetime:
    """The time ``--expires`` names: a duration from ``now``, a date (its midnight UTC), or a time
    with a zone."""
    text = text.strip()
    try:
        if duration := _DURATION.fullmatch(text):
            return now + dt.timedelta(**{_UNITS[duration[2]]: int(duration[1])})
        try:
            return dt.datetime.combine(dt.date.fromisoformat(text), dt.time(), dt.UTC)
        except ValueError:
            when = dt.datetime.fromisoformat(text)
    except ValueError:
        fail(
            f"--expires {text!r}: give a duration (90m, 12h, 30d, 2w) or an ISO date or time, e.g. 2027-01-31"
        )
    except OverflowError:
        fail(f"--expires {text!r} lies beyond the year 9999")
    if when.tzinfo is None:
        fail(f"--expires {text!r}: give the time a zone, e.g. {text}Z, or give a date alone")
    return when


def _when(moment: dt.datetime | None) -> str:
    return "-" if moment is None else f"{moment:%Y-%m-%d %H:%M}"


def demo_seed(
    key_file: Annotated[
        Path | None,
        typer.Option(
            help="Also keep an ingest key of the demo organisation in this file (readable by its owner "
            "only), made and printed once: the simulator's in docker-compose.yml.",
            dir_okay=False,
        ),
    ] = None,
) -> None:
    """Create the demo organisation, structure and models (once; repeating changes nothing)."""
    from service.demo import ORGANISATION, STRUCTURE, seed_demo

    settings = get_settings()
    upgrade_database(settings.database_url)
    sessions = session_factory(make_engine(settings.database_url))
    with transaction(sessions) as session:
        structure = seed_demo(session, settings, lambda step: stdout.print(f"demo: {step}"))
    key = None
    if key_file is not None and not _opens_the_api(sessions, key_file):
        with transaction(sessions) as session:
            key = create_key(session, ORGANISATION, Role.ingest)
    if key is not None:
        key_file.touch(mode=0o600)
        key_file.chmod(0o600)  # the owner's only, before the key is in it
        key_file.write_text(key + "\n")
        stdout.print(f"demo ingest key (also in {key_file}; shown once): {key}")
        # An ingest key uploads and inspects; creating structures and training need an admin's.
        stdout.print(
            "to create structures and train models, make an admin key where narxwatch runs: "
            f"narxwatch keys create --org {ORGANISATION} --role admin",
            markup=False,
        )
    stdout.print(f"demo structure {STRUCTURE!r} is structure {structure.id}")


def _opens_the_api(sessions: sessionmaker[Session], key_file: Path) -> bool:
    """Whether ``key_file`` holds a key that still opens the API: a restart keeps its key, and a
    key revoked or lost with its database is replaced."""
    kept = key_file.read_text().strip() if key_file.is_file() else ""
    if not kept:
        return False
    with transaction(sessions) as session:
        try:
            authenticate(session, kept)
        except KeyRefusedError:
            return False
    return True
