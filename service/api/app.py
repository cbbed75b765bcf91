"""The FastAPI application: routers under /api/v1, errors mapped to clear 4xx/5xx answers."""

from __future__ import annotations

import math
from collections.abc import AsyncIterator, Awaitable, Callable, Mapping
from contextlib import asynccontextmanager

from asgi_correlation_id import CorrelationIdMiddleware
from fastapi import FastAPI, Request, status
from fastapi.exception_handlers import http_exception_handler
from fastapi.exceptions import RequestValidationError
from fastapi.openapi.docs import get_swagger_ui_html
from fastapi.responses import HTMLResponse, JSONResponse, RedirectResponse, Response
from fastapi.routing import APIRoute
from fastapi.staticfiles import StaticFiles
from sqlalchemy.exc import OperationalError
from sqlalchemy.exc import TimeoutError as PoolTimeoutError
from starlette.exceptions import HTTPException as StarletteHTTPException
from starlette.routing import compile_path
from swagger_ui_bundle import swagger_ui_path

from models.errors import InputError
from recordfiles.reader import RecordTooLargeError
from service import dashboard, sealing
from service.api import (
    alarms,
    health,
    jobs,
    keys,
    metrics,
    modelling,
    notifications,
    records,
    refinements,
    retention,
    schedules,
    structures,
)
from service.api.expensive import Slots, Uploads
from service.api.limits import BodyLimit, BodyLimitMiddleware
from service.config import Settings, get_settings
from service.db import make_engine, session_factory
from service.domain.errors import ConflictError, NotFoundError
from service.jobs.backends import job_backend
from service.migrate import upgrade_database
from service.observability.logs import REQUEST_ID_HEADER, is_sane_request_id
from service.observability.requests import ObserveRequests

API_PREFIX = "/api/v1"
DOCS = "/docs"


def create_app(settings: Settings | None = None) -> FastAPI:
    settings = settings or get_settings()

    @asynccontextmanager
    async def lifespan(app: FastAPI) -> AsyncIterator[None]:
        if settings.upgrade_on_start:
            upgrade_database(settings.database_url)
        sealing.check_keys(settings)
        app.state.jobs.start()
        yield
        app.state.jobs.stop()
        app.state.engine.dispose()

    app = FastAPI(
        title="narxwatch",
        version="0.1.0",
        description="Condition monitoring of vibrating structures with NARX and functional NARX models.",
        lifespan=lifespan,
        docs_url=None,  # served by _add_docs from the installed package, not from a CDN
        redoc_url=None,  # ReDoc has no packaged build; Swagger UI covers the same ground
    )
    app.state.settings = settings
    app.state.engine = make_engine(settings.database_url, settings.pool_timeout_seconds)
    app.state.sessions = session_factory(app.state.engine)
    app.state.jobs = job_backend(settings, app.state.sessions, in_service=True)
    app.state.expensive = Slots(settings.max_concurrent_expensive)
    app.state.uploads = Uploads(settings.max_concurrent_uploads, settings.upload_wait_seconds)
    app.include_router(health.router)
    app.include_router(metrics.router)
    routers = (
        structures.router,
        modelling.router,
        records.router,
        refinements.router,
        schedules.router,
        jobs.router,
        keys.router,
        alarms.router,
        notifications.router,
        retention.router,
    )
    for router in routers:
        app.include_router(router, prefix=API_PREFIX)
    dashboard.install(app)
    _add_docs(app)
    _add_error_handlers(app, settings)
    # The routes' own patterns, under the prefix they are served at.
    record_routes = [route for route in records.router.routes if isinstance(route, APIRoute)]
    uploads = [
        compile_path(API_PREFIX + route.path)[0]
        for route in record_routes
        if route.endpoint in (records.upload_record, records.upload_record_set)
    ]
    app.add_middleware(
        BodyLimitMiddleware,
        limit=BodyLimit(settings.max_request_bytes, "NARXWATCH_MAX_REQUEST_BYTES"),
        upload_limit=BodyLimit(settings.max_upload_bytes, "NARXWATCH_MAX_UPLOAD_BYTES"),
        uploads=uploads,
        timeout=settings.body_timeout_seconds,
    )
    # The last added runs first: a request gets its id, then is timed and logged whole.
    app.add_middleware(ObserveRequests)
    app.add_middleware(CorrelationIdMiddleware, header_name=REQUEST_ID_HEADER, validator=is_sane_request_id)
    return app


def _add_docs(app: FastAPI) -> None:
    """``/docs``: Swagger UI with its assets from the ``swagger-ui-bundle-v2`` package, so the docs
    work on a machine without internet; ``/`` leads people to the dashboard."""
    app.mount(f"{DOCS}/static", StaticFiles(directory=str(swagger_ui_path)), name="docs-static")

    @app.get(DOCS, include_in_schema=False)
    def docs() -> HTMLResponse:
        return get_swagger_ui_html(
            openapi_url=app.openapi_url or "/openapi.json",
            title=f"{app.title} API",
            swagger_js_url=f"{DOCS}/static/swagger-ui-bundle.js",
            swagger_css_url=f"{DOCS}/static/swagger-ui.css",
            swagger_favicon_url=f"{DOCS}/static/favicon-32x32.png",
        )

    @app.get("/", include_in_schema=False)
    def root() -> RedirectResponse:
        return RedirectResponse(dashboard.HOME, status.HTTP_303_SEE_OTHER)


def _add_error_handlers(app: FastAPI, settings: Settings) -> None:
    def answer(
        request: Request, code: int, message: str, headers: Mapping[str, str] | None = None
    ) -> Response:
        if dashboard.is_dashboard(request):
            response = dashboard.error_page(request, code, message)
            response.headers.update(headers or {})
            return response
        return JSONResponse({"detail": message}, status_code=code, headers=headers)

    def refusal(code: int) -> Callable[[Request, Exception], Awaitable[Response]]:
        async def refused(request: Request, exc: Exception) -> Response:
            return answer(request, code, str(exc))

        return refused

    # What the service refuses, each kind with its status code; the message is the error's own.
    for error, code in (
        (RecordTooLargeError, status.HTTP_413_CONTENT_TOO_LARGE),
        (InputError, status.HTTP_422_UNPROCESSABLE_CONTENT),
        (NotFoundError, status.HTTP_404_NOT_FOUND),
        (ConflictError, status.HTTP_409_CONFLICT),
    ):
        app.add_exception_handler(error, refusal(code))

    @app.exception_handler(RequestValidationError)
    async def invalid_request(request: Request, exc: RequestValidationError) -> Response:
        # Where and why, but never the input itself: it may not even be encodable (a lone
        # surrogate) and echoing it back serves no one.
        errors = [{"loc": list(e["loc"]), "msg": e["msg"], "type": e["type"]} for e in exc.errors()]
        if dashboard.is_dashboard(request):
            message = "; ".join(f"{e['loc'][-1]}: {e['msg']}" for e in errors)
            return dashboard.error_page(request, status.HTTP_422_UNPROCESSABLE_CONTENT, message)
        return JSONResponse({"detail": errors}, status_code=status.HTTP_422_UNPROCESSABLE_CONTENT)

    @app.exception_handler(StarletteHTTPException)
    async def http_error(request: Request, exc: StarletteHTTPException) -> Response:
        if dashboard.is_dashboard(request):
            return answer(request, exc.status_code, str(exc.detail), exc.headers)
        return await http_exception_handler(request, exc)

    # Retry after as long as a request may wait for the pool: the connections in use turn over.
    retry_after = {"Retry-After": str(math.ceil(settings.pool_timeout_seconds))}

    @app.exception_handler(OperationalError)
    async def database_unavailable(request: Request, exc: OperationalError) -> Response:
        message = "the database is unavailable; retry shortly"
        return answer(request, status.HTTP_503_SERVICE_UNAVAILABLE, message, retry_after)

    @app.exception_handler(PoolTimeoutError)
    async def database_busy(request: Request, exc: PoolTimeoutError) -> Response:
        # Every pooled connection stayed in use for NARXWATCH_POOL_TIMEOUT_SECONDS: overload, not a fault.
        message = "the service is busy (no database connection came free in time); retry shortly"
        return answer(request, status.HTTP_503_SERVICE_UNAVAILABLE, message, retry_after)

    @app.exception_handler(Exception)
    async def internal_error(request: Request, exc: Exception) -> Response:
        # uvicorn closes the connection after an unhandled error (logged with its traceback):
        # saying so keeps a keep-alive client from sending its next request into a closed socket.
        message = "internal error (logged on the server); the request's changes were rolled back"
        return answer(request, status.HTTP_500_INTERNAL_SERVER_ERROR, message, {"Connection": "close"})
