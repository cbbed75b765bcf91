"""``GET /metrics``: Prometheus metrics, open or behind a bearer token of their own.

The metrics are fleet-wide counts with no organisation, and nothing an organisation chose (such
as a fault mode's name), in any label, so they take no API key;
``NARXWATCH_METRICS_TOKEN`` guards them where the endpoint is reachable beyond an internal network.
"""

from __future__ import annotations

import hmac
from typing import Annotated

from fastapi import APIRouter, Depends, HTTPException, Request, Response, status
from fastapi.responses import PlainTextResponse
from fastapi.security import HTTPAuthorizationCredentials, HTTPBearer
from prometheus_client import CONTENT_TYPE_LATEST
from pydantic import SecretStr

from service.api.deps import SessionDep, SettingsDep
from service.observability.metrics import DatabaseCollector, exposition

router = APIRouter(tags=["observability"])
token_bearer = HTTPBearer(
    auto_error=False,
    scheme_name="MetricsToken",
    description="The metrics token, when NARXWATCH_METRICS_TOKEN sets one: `Authorization: Bearer <token>`",
)


@router.get(
    "/metrics",
    response_class=PlainTextResponse,
    responses={401: {"description": "A metrics token is set and the request does not carry it"}},
)
def metrics(
    request: Request,
    settings: SettingsDep,
    session: SessionDep,
    credentials: Annotated[HTTPAuthorizationCredentials | None, Depends(token_bearer)],
) -> Response:
    """Records received, verdicts by status, the job queue, request latency."""
    if not admitted(settings.metrics_token, credentials):
        raise HTTPException(
            status.HTTP_401_UNAUTHORIZED,
            "metrics need the header 'Authorization: Bearer <NARXWATCH_METRICS_TOKEN>'",
            headers={"WWW-Authenticate": "Bearer"},
        )
    body = exposition(DatabaseCollector(session, request.app.state.jobs.queue_stats))
    return Response(body, media_type=CONTENT_TYPE_LATEST)


def admitted(token: SecretStr | None, credentials: HTTPAuthorizationCredentials | None) -> bool:
    """Anyone without a token; with one, its bearer only. Compared as bytes (a token may hold any
    character) in constant time: a wrong guess takes as long as a near miss."""
    if token is None:
        return True
    if credentials is None:
        return False
    return hmac.compare_digest(credentials.credentials.encode(), token.get_secret_value().encode())
