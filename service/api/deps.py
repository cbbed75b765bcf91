"""Request-scoped dependencies: settings, the database session, the authenticated caller."""

from __future__ import annotations

import logging
from collections.abc import Callable, Iterator
from typing import Annotated

from fastapi import Depends, HTTPException, Request, status
from fastapi.security import HTTPAuthorizationCredentials, HTTPBearer
from sqlalchemy.orm import Session

from service.config import Settings
from service.db import transaction
from service.security import KeyRefusedError, Principal, Role, authenticate

log = logging.getLogger("narxwatch.auth")
bearer = HTTPBearer(auto_error=False, description="An API key: `Authorization: Bearer nw_…`")


async def get_settings(request: Request) -> Settings:
    # async: a plain attribute read needs no trip through the thread pool.
    return request.app.state.settings


def get_session(request: Request) -> Iterator[Session]:
    """The request's unit of work: committed once when the endpoint returns, rolled back (on
    close) if it raises. Routers and domain code only flush.

    Declared with ``scope="function"`` (``SessionDep``): FastAPI then runs the code after
    ``yield`` before it sends the response, so a commit that fails is answered as an error, never
    as the success the endpoint had prepared. The default scope would commit after the response.

    The record uploads take none: they open, write and commit theirs in the thread that parses
    and inspects them (``service.api.records``, UPLOAD_SESSIONS).
    """
    with request.app.state.sessions() as session:
        yield session
        session.commit()


SettingsDep = Annotated[Settings, Depends(get_settings)]
SessionDep = Annotated[Session, Depends(get_session, scope="function")]


def require(role: Role) -> Callable[..., Principal]:
    """A dependency admitting keys of ``role`` or a more powerful one."""

    def dependency(
        request: Request, credentials: Annotated[HTTPAuthorizationCredentials | None, Depends(bearer)]
    ) -> Principal:
        """The key is checked in a short session of its own, not the request's: a request that
        then awaits its body (an upload) holds no pooled connection while the body arrives."""
        if credentials is None:
            raise HTTPException(
                status.HTTP_401_UNAUTHORIZED,
                "missing API key: send the header 'Authorization: Bearer <key>'",
                headers={"WWW-Authenticate": "Bearer"},
            )
        try:
            with transaction(request.app.state.sessions) as session:
                principal = authenticate(session, credentials.credentials)
        except KeyRefusedError as refused:
            # A trace of refusals (a guessing client shows up), never the key nor any part of it.
            log.warning("refused an API key: %s", refused)
            raise HTTPException(
                status.HTTP_401_UNAUTHORIZED, str(refused), headers={"WWW-Authenticate": "Bearer"}
            ) from None
        if principal.role < role:
            raise HTTPException(
                status.HTTP_403_FORBIDDEN,
                f"this needs a key of role '{role.name}' or higher; yours is '{principal.role.name}'",
            )
        return principal

    return dependency


Viewer = Annotated[Principal, Depends(require(Role.viewer))]
Ingest = Annotated[Principal, Depends(require(Role.ingest))]
Admin = Annotated[Principal, Depends(require(Role.admin))]
