"""The FastAPI application: routers under /api/v1, errors mapped to clear 4xx/5xx answers."""

from __future__ import annotations

from collections.abc import AsyncIterator
from contextlib import asynccontextmanager

from asgi_correlation_id import CorrelationIdMiddleware
from fastapi import FastAPI, Request, status
from fastapi.exception_handlers import http_exception_handler
from fastapi.exceptions import RequestValidationError
from fastapi.responses import JSONResponse, Response
from sqlalchemy.exc import OperationalError
from starlette.exceptions import HTTPException as StarletteHTTPException

from models.errors import InputError
from service import dashboard
from service.api import health, metrics, modelling, records, refinements, schedules, structures
from service.api.expensive import Slots
from service.api.limits import BodyLimitMiddleware
from service.config import Settings, get_settings
from service.db import make_engine, session_factory
from service.domain.errors import ConflictError, NotFoundError
from service.jobs import job_backend
from service.migrate import upgrade_database
from service.observability.logs import REQUEST_ID_HEADER, is_sane_request_id
from service.observability.requests import ObserveRequests
from simulator.recordfile import RecordTooLargeError

API_PREFIX = "/api/v1"


def create_app(settings: Settings | None = None) -> FastAPI:
    settings = settings or get_settings()

    @asynccontextmanager
    async def lifespan(app: FastAPI) -> AsyncIterator[None]:
        if settings.upgrade_on_start:
            upgrade_database(settings.database_url)
        app.state.jobs.start()
        yield
        app.state.jobs.stop()
        app.state.engine.dispose()

    app = FastAPI(
        title="narxwatch",
        version="0.1.0",
        description="Condition monitoring of vibrating structures with NARX and functional NARX models.",
        lifespan=lifespan,
    )
    app.state.settings = settings
    app.state.engine = make_engine(settings.database_url)
    app.state.sessions = session_factory(app.state.engine)
    app.state.jobs = job_backend(settings, app.state.sessions, in_service=True)
    app.state.expensive = Slots(settings.max_concurrent_expensive)
    app.include_router(health.router)
    app.include_router(metrics.router)
    routers = (structures.router, modelling.router, records.router, refinements.router, schedules.router)
    for router in routers:
        app.include_router(router, prefix=API_PREFIX)
    dashboard.install(app)
    _add_error_handlers(app)
    app.add_middleware(BodyLimitMiddleware, limit=settings.max_upload_bytes)
    # The last added runs first: a request gets its id, then is timed and logged whole.
    app.add_middleware(ObserveRequests)
    app.add_middleware(CorrelationIdMiddleware, header_name=REQUEST_ID_HEADER, validator=is_sane_request_id)
    return app


def _add_error_handlers(app: FastAPI) -> None:
    def answer(request: Request, code: int, message: str) -> Response:
        if dashboard.is_dashboard(request):
            return dashboard.error_page(request, code, message)
        return JSONResponse({"detail": message}, status_code=code)

    @app.exception_handler(RecordTooLargeError)
    async def too_large(request: Request, exc: RecordTooLargeError) -> Response:
        return answer(request, status.HTTP_413_CONTENT_TOO_LARGE, str(exc))

    @app.exception_handler(InputError)
    async def input_error(request: Request, exc: InputError) -> Response:
        return answer(request, status.HTTP_422_UNPROCESSABLE_CONTENT, str(exc))

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
            return dashboard.error_page(request, exc.status_code, str(exc.detail))
        return await http_exception_handler(request, exc)

    @app.exception_handler(NotFoundError)
    async def not_found(request: Request, exc: NotFoundError) -> Response:
        return answer(request, status.HTTP_404_NOT_FOUND, str(exc))

    @app.exception_handler(ConflictError)
    async def conflict(request: Request, exc: ConflictError) -> Response:
        return answer(request, status.HTTP_409_CONFLICT, str(exc))

    @app.exception_handler(OperationalError)
    async def database_unavailable(request: Request, exc: OperationalError) -> Response:
        return answer(
            request, status.HTTP_503_SERVICE_UNAVAILABLE, "the database is unavailable; retry shortly"
        )
