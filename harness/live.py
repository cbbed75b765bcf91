"""The real narxwatch app served by uvicorn on a free loopback port, for tests over HTTP."""

from __future__ import annotations

import socket
import ssl
import subprocess
import threading
import time
import uuid
from collections.abc import Callable
from dataclasses import dataclass
from typing import Any

import httpx
import uvicorn

from service.api.app import create_app
from service.api.protocol import header_timeout_protocol
from service.config import Settings
from service.db import transaction
from service.security import Role, create_key

# httpx builds a TLS context for every client, reading the CA bundle (about 70 ms on a slow
# machine), though the test clients speak plain HTTP on loopback: they share this one.
TLS = ssl.create_default_context()


def http_client(**options: Any) -> httpx.Client:
    """An httpx client for the test servers, sharing one TLS context (``TLS``)."""
    return httpx.Client(verify=TLS, **options)


def wait_until_serving(base: str, process: subprocess.Popen, timeout: float, why: Callable[[], str]) -> None:
    """Poll ``base``/healthz until a separately started ``narxwatch serve`` answers; fail with
    ``why()`` if it exits or ``timeout`` seconds pass first."""
    deadline = time.monotonic() + timeout
    with http_client(base_url=base) as http:
        while True:
            try:
                if http.get("/healthz").status_code == 200:
                    return
            except httpx.TransportError:
                pass
            assert time.monotonic() < deadline and process.poll() is None, why()
            time.sleep(0.1)


def free_port() -> int:
    with socket.socket() as probe:
        probe.bind(("127.0.0.1", 0))
        return probe.getsockname()[1]


class LiveServer:
    """``with LiveServer(settings) as server:`` serves the app until the block ends."""

    def __init__(self, settings: Settings) -> None:
        self.settings = settings
        self.app = create_app(settings)
        self.port = free_port()
        config = uvicorn.Config(
            self.app,
            host="127.0.0.1",
            port=self.port,
            log_level="warning",
            http=header_timeout_protocol(settings.header_timeout_seconds),  # as `narxwatch serve`
        )
        self._server = uvicorn.Server(config)
        self._thread = threading.Thread(target=self._server.run, name="narxwatch-live", daemon=True)

    @property
    def url(self) -> str:
        return f"http://127.0.0.1:{self.port}"

    def __enter__(self) -> LiveServer:
        self._thread.start()
        deadline = time.monotonic() + 60
        while not self._server.started:
            if not self._thread.is_alive() or time.monotonic() > deadline:
                raise RuntimeError("the narxwatch test server did not start")
            time.sleep(0.02)
        return self

    def __exit__(self, *_: object) -> None:
        self._server.should_exit = True
        self._thread.join(timeout=30)

    def key(self, role: Role | str, organisation: str | None = None) -> str:
        """A new API key (for a new organisation unless one is named)."""
        with transaction(self.app.state.sessions) as session:
            return create_key(
                session,
                organisation or f"org-{uuid.uuid4().hex[:12]}",
                Role[str(role)] if isinstance(role, str) else role,
            )

    def client(self, key: str | None = None) -> httpx.Client:
        headers = {"Authorization": f"Bearer {key}"} if key else {}
        return http_client(base_url=self.url, headers=headers, timeout=60)


@dataclass
class Tenant:
    """An organisation with a key of each role."""

    name: str
    admin: httpx.Client
    ingest: httpx.Client
    viewer: httpx.Client

    @classmethod
    def create(cls, server: LiveServer) -> Tenant:
        name = f"org-{uuid.uuid4().hex[:12]}"
        return cls(
            name,
            server.client(server.key(Role.admin, name)),
            server.client(server.key(Role.ingest, name)),
            server.client(server.key(Role.viewer, name)),
        )


# --- what the database decides, on each ------------------------------------------------------
# Most API tests run on SQLite (their modules' ``api_server``); the few of what the database takes
# part in (the values it can hold, transactions, constraints, what it stores for a page) take a
# fixture parametrised over ``DATABASES``, made with ``on_each_database``.
DATABASES = ("sqlite", "postgresql")


def on_each_database(request: Any, on_sqlite: str, build: Callable[[LiveServer], Any]) -> Any:
    """For a fixture parametrised over ``DATABASES``: on SQLite, the module's fixture named
    ``on_sqlite`` (built once for both kinds of test); on PostgreSQL, ``build`` on its server."""
    if request.param == "sqlite":
        return request.getfixturevalue(on_sqlite)
    return build(request.getfixturevalue("postgresql_api_server"))
