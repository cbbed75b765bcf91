"""The FastAPI application: routers under /api/v1, errors mapped to clear 4xx/5xx answers."""

from __future__ import annotations

from collections.abc import AsyncIterator
from contextlib import asynccontextmanager

from asgi_correlation_id import CorrelationIdMiddleware
from fastapi import FastAPI, Request, status
from fastapi.exceptions import RequestValidationError
from fastapi.responses import JSONResponse
from sqlalchemy.exc import OperationalError

from models.errors import InputError
from service.api import health, metrics, modelling, records, refinements, schedules, structures
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
    app.include_router(health.router)
    app.include_router(metrics.router)
    routers = (structures.router, modelling.router, records.router, refinements.router, schedules.router)
    for router in routers:
        app.include_router(router, prefix=API_PREFIX)
    _add_error_handlers(app)
    app.add_middleware(BodyLimitMiddleware, limit=settings.max_upload_bytes)
    # The last added runs first: a request gets its id, then is timed and logged whole.
    app.add_middleware(ObserveRequests)
    app.add_middleware(CorrelationIdMiddleware, header_name=REQUEST_ID_HEADER, validator=is_sane_request_id)
    return app


def _add_error_handlers(app: FastAPI) -> None:
    def answer(code: int, message: str) -> JSONResponse:
        return JSONResponse({"detail": message}, status_code=code)

    @app.exception_handler(RecordTooLargeError)
    async def too_large(_: Request, exc: RecordTooLargeError) -> JSONResponse:
        return answer(status.HTTP_413_CONTENT_TOO_LARGE, str(exc))

    @app.exception_handler(InputError)
    async def input_error(_: Request, exc: InputError) -> JSONResponse:
        return answer(status.HTTP_422_UNPROCESSABLE_CONTENT, str(exc))

    @app.exception_handler(RequestValidationError)
    async def invalid_request(_: Request, exc: RequestValidationError) -> JSONResponse:
        # Where and why, but never the input itself: it may not even be encodable (a lone
        # surrogate) and echoing it back serves no one.
        errors = [{"loc": list(e["loc"]), "msg": e["msg"], "type": e["type"]} for e in exc.errors()]
        return JSONResponse({"detail": errors}, status_code=status.HTTP_422_UNPROCESSABLE_CONTENT)

    @app.exception_handler(NotFoundError)
    async def not_found(_: Request, exc: NotFoundError) -> JSONResponse:
        return answer(status.HTTP_404_NOT_FOUND, str(exc))

    @app.exception_handler(ConflictError)
    async def conflict(_: Request, exc: ConflictError) -> JSONResponse:
        return answer(status.HTTP_409_CONFLICT, str(exc))

    @app.exception_handler(OperationalError)
    async def database_unavailable(_: Request, exc: OperationalError) -> JSONResponse:
        return answer(status.HTTP_503_SERVICE_UNAVAILABLE, "the database is unavailable; retry shortly")
