"""Each HTTP request timed into the latency histogram and logged as one line, by route template.

Labels and log fields name the route's template (``/api/v1/structures/{structure_id}``), never
the raw path: ids in paths would make a time series of every object, and a client could make
as many as it liked. The method is bounded the same way.
"""

from __future__ import annotations

import logging
import re
import time

from starlette.routing import compile_path
from starlette.types import ASGIApp, Message, Receive, Scope, Send

from service.observability.metrics import REQUEST_SECONDS

OTHER = "other"  # a path no route serves, or a method HTTP does not define
METHODS = frozenset({"GET", "HEAD", "POST", "PUT", "PATCH", "DELETE", "OPTIONS"})

log = logging.getLogger("narxwatch.access")


class ObserveRequests:
    """Pure ASGI middleware (no BaseHTTPMiddleware: it would buffer streamed answers and run the
    app in another task)."""

    def __init__(self, app: ASGIApp) -> None:
        self.app = app
        self._templates: list[tuple[re.Pattern[str], str]] | None = None

    async def __call__(self, scope: Scope, receive: Receive, send: Send) -> None:
        if scope["type"] != "http":
            await self.app(scope, receive, send)
            return
        started = time.perf_counter()
        status = 500  # what the client gets if the app raises before answering
        observed = False

        async def observed_send(message: Message) -> None:
            nonlocal status, observed
            if message["type"] == "http.response.start":
                status = message["status"]
            elif message["type"] == "http.response.body" and not message.get("more_body", False):
                # Before the last part leaves: a client that has its answer finds it counted.
                observed = True
                self._observe(scope, status, time.perf_counter() - started)
            await send(message)

        try:
            await self.app(scope, receive, observed_send)
        finally:
            if not observed:  # the app raised, or the client left, before the answer ended
                self._observe(scope, status, time.perf_counter() - started)

    def _observe(self, scope: Scope, status: int, seconds: float) -> None:
        method = scope["method"] if scope["method"] in METHODS else OTHER
        route = self._route(scope)
        REQUEST_SECONDS.labels(method, route, str(status)).observe(seconds)
        duration_ms = round(1000 * seconds, 3)
        log.info(
            "%s %s %s %.1f ms",
            method,
            route,
            status,
            duration_ms,
            extra={"method": method, "route": route, "status": status, "duration_ms": duration_ms},
        )

    def _route(self, scope: Scope) -> str:
        """The template of the route serving the path: from the app's OpenAPI paths, the one
        public list of full templates (FastAPI's routes keep an included router's prefix apart),
        and its documentation pages."""
        if self._templates is None:
            app = scope["app"]
            pages = (app.openapi_url, app.docs_url, app.redoc_url, app.swagger_ui_oauth2_redirect_url)
            paths = [*app.openapi()["paths"], *filter(None, pages)]
            self._templates = [(compile_path(path)[0], path) for path in paths]
        return next((path for regex, path in self._templates if regex.match(scope["path"])), OTHER)
