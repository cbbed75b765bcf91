"""The production app plus a no-op upload endpoint, for the API load benchmark only.

``bench/load_api.py`` serves this with ``uvicorn bench.noop_app:create_app_with_noop --factory``
(from the project root) so that the same server process answers both the real upload and
``POST /bench/noop``. The no-op takes the same payload the same way the real upload does — the
app-wide body limit (``BodyLimitMiddleware``), the same ``Ingest`` key check (one database
session and an API-key lookup), ``request.body()`` and the same ``parse_upload`` with its
validation — and then stores, inspects and returns nothing. The difference between the two is
therefore the cost of the real work: storing the record, running the inspection chain,
persisting the verdict and answering with it.

The endpoint is never part of the production API: ``service.api.app.create_app`` does not know it.
"""

from __future__ import annotations

from fastapi import FastAPI, Request, status
from fastapi.responses import JSONResponse

from service.api.app import create_app
from service.api.deps import Ingest, SettingsDep
from service.api.uploads import parse_upload

NOOP_PATH = "/bench/noop"


def create_app_with_noop() -> FastAPI:
    """``create_app()`` with ``POST /bench/noop`` added (hidden from the OpenAPI schema)."""
    app = create_app()

    @app.post(NOOP_PATH, status_code=status.HTTP_201_CREATED, include_in_schema=False)
    async def noop_upload(request: Request, principal: Ingest, settings: SettingsDep) -> JSONResponse:
        body = await request.body()  # bounded by the app's BodyLimitMiddleware, as for the upload
        upload = parse_upload(body, request.headers.get("content-type", ""), None, settings.max_upload_bytes)
        return JSONResponse(
            {"noop": True, "organisation_id": principal.organisation_id, "n_samples": len(upload.x)},
            status_code=status.HTTP_201_CREATED,
        )

    return app
