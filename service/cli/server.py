"""Service commands: ``serve``, ``worker``, ``db upgrade``, ``keys create``, ``demo-seed``."""

from __future__ import annotations

import os
from typing import Annotated

import typer
import uvicorn

from service.cli.console import fail, stdout
from service.config import get_settings
from service.db import make_engine, session_factory, transaction
from service.migrate import upgrade_database
from service.security import Role, create_key

db_app = typer.Typer(help="Database schema.", no_args_is_help=True)
keys_app = typer.Typer(help="API keys.", no_args_is_help=True)


def serve(
    host: Annotated[str, typer.Option(help="Interface to listen on.")] = "127.0.0.1",
    port: Annotated[int, typer.Option(help="TCP port.", min=1, max=65535)] = 8000,
    workers: Annotated[int, typer.Option(help="Worker processes.", min=1)] = 1,
) -> None:
    """Serve the REST API (upgrading the database schema first, unless told not to)."""
    settings = get_settings()
    if settings.upgrade_on_start:
        upgrade_database(settings.database_url)
    # Upgraded once here: the workers must not race each other to do it again.
    os.environ["NARXWATCH_UPGRADE_ON_START"] = "false"
    stdout.print(f"narxwatch API on http://{host}:{port}  (docs: http://{host}:{port}/docs)")
    uvicorn.run(
        "service.api.app:create_app", factory=True, host=host, port=port, workers=workers, log_level="info"
    )


def worker(
    once: Annotated[bool, typer.Option(help="Run the jobs due now, then exit.")] = False,
) -> None:
    """Run queued inspections (inspect=queue) from the database's job queue, until stopped.

    Any number may run, on any machine that reaches the database; each job runs at least once,
    and its verdict is stored once. Run it when the service itself runs with NARXWATCH_JOBS=off.
    """
    from service.jobs import EmbeddedWorker

    settings = get_settings()
    runner = EmbeddedWorker(session_factory(make_engine(settings.database_url)), settings)
    if once:
        stdout.print(f"ran {runner.run_due()} job(s)")
        return
    stdout.print("narxwatch worker: running queued jobs (Ctrl-C stops)")
    runner.start()
    try:
        while runner.alive():
            runner.join(1.0)
    except KeyboardInterrupt:
        runner.stop()


@db_app.command("upgrade")
def db_upgrade(revision: Annotated[str, typer.Argument(help="Target revision.")] = "head") -> None:
    """Bring the database schema (NARXWATCH_DATABASE_URL) up to date."""
    settings = get_settings()
    upgrade_database(settings.database_url, revision)
    stdout.print(f"database at {settings.database_url.split('@')[-1]} is at revision {revision}")


@keys_app.command("create")
def keys_create(
    org: Annotated[str, typer.Option(help="Organisation name (created if new).")],
    role: Annotated[str, typer.Option(help="admin, ingest or viewer.")],
) -> None:
    """Create an API key and print it once: only its hash is stored."""
    if role not in Role.__members__:
        fail(f"unknown role {role!r}: choose admin, ingest or viewer")
    sessions = session_factory(make_engine(get_settings().database_url))
    with transaction(sessions) as session:
        key = create_key(session, org, Role[role])
    print(key)


def demo_seed() -> None:
    """Create the demo organisation, structure and models (once; repeating changes nothing)."""
    from service.demo import STRUCTURE, seed_demo

    settings = get_settings()
    upgrade_database(settings.database_url)
    sessions = session_factory(make_engine(settings.database_url))
    with transaction(sessions) as session:
        structure = seed_demo(session, lambda step: stdout.print(f"demo: {step}"))
    stdout.print(f"demo structure {STRUCTURE!r} is structure {structure.id}")
