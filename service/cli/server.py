"""Service commands: ``serve``, ``worker``, ``db upgrade``, ``keys create``, ``demo-seed``."""

from __future__ import annotations

import logging
import os
import shutil
import tempfile
from pathlib import Path
from typing import Annotated

import typer
import uvicorn
from sqlalchemy.orm import Session, sessionmaker

from service.cli.console import fail, stdout
from service.config import get_settings
from service.db import make_engine, session_factory, transaction
from service.migrate import database_name, require_current_schema, upgrade_database
from service.observability.logs import configure_logging, logging_config
from service.observability.metrics import MULTIPROCESS_DIR
from service.security import Role, authenticate, create_key

db_app = typer.Typer(help="Database schema.", no_args_is_help=True)
keys_app = typer.Typer(help="API keys.", no_args_is_help=True)
log = logging.getLogger("narxwatch")


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
    settings = get_settings()
    if not settings.upgrade_on_start:
        require_current_schema(settings.database_url)
    json_logs = settings.log_format == "json"
    configure_logging("INFO", json=json_logs)
    if settings.upgrade_on_start:
        upgrade_database(settings.database_url)
    # Upgraded once here: the workers must not race each other to do it again.
    os.environ["NARXWATCH_UPGRADE_ON_START"] = "false"
    metrics_dir = None
    if workers > 1 and not os.environ.get(MULTIPROCESS_DIR):
        # Set before uvicorn starts the workers: prometheus-client picks its mode at import.
        metrics_dir = os.environ[MULTIPROCESS_DIR] = tempfile.mkdtemp(prefix="narxwatch-metrics-")
    log.info("narxwatch API on http://%s:%s (docs: http://%s:%s/docs)", host, port, host, port)
    try:
        uvicorn.run(
            "service.api.app:create_app",
            factory=True,
            host=host,
            port=port,
            workers=workers,
            log_level="info",
            log_config=logging_config("INFO", json=json_logs),  # applied again in each worker
            access_log=False,  # narxwatch.access logs each request, with its route and duration
        )
    finally:
        if metrics_dir is not None:
            shutil.rmtree(metrics_dir, ignore_errors=True)


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
    from service.jobs import backend_name, job_backend

    settings = get_settings()
    if backend_name(settings) == "embedded" and concurrency > 1:
        fail("--concurrency applies to the distributed backend (PostgreSQL); run more workers instead")
    require_current_schema(settings.database_url)
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


@db_app.command("upgrade")
def db_upgrade(revision: Annotated[str, typer.Argument(help="Target revision.")] = "head") -> None:
    """Bring the database schema (NARXWATCH_DATABASE_URL) up to date."""
    settings = get_settings()
    upgrade_database(settings.database_url, revision)
    stdout.print(f"database at {database_name(settings.database_url)} is at revision {revision}")


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
) -> None:
    """Create an API key and print it once: only its hash is stored."""
    if role not in Role.__members__:
        fail(f"unknown role {role!r}: choose admin, ingest or viewer")
    sessions = ready_sessions()
    with transaction(sessions) as session:
        key = create_key(session, org, Role[role])
    print(key)


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
        key = None if key_file is None else _new_key_unless_kept(session, key_file, ORGANISATION)
    if key_file is not None and key is not None:
        key_file.touch(mode=0o600)
        key_file.chmod(0o600)  # the owner's only, before the key is in it
        key_file.write_text(key + "\n")
        stdout.print(f"demo ingest key (also in {key_file}; shown once): {key}")
    stdout.print(f"demo structure {STRUCTURE!r} is structure {structure.id}")


def _new_key_unless_kept(session: Session, key_file: Path, organisation: str) -> str | None:
    """A new ingest key of ``organisation``, unless ``key_file`` holds one that still opens the API
    (a restart keeps its key; a key revoked or lost with its database is replaced)."""
    kept = key_file.read_text().strip() if key_file.is_file() else ""
    if kept and authenticate(session, kept) is not None:
        return None
    return create_key(session, organisation, Role.ingest)
