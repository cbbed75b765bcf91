"""Request-scoped dependencies: settings, the database session, the authenticated caller."""

from __future__ import annotations

import logging
from collections.abc import Callable, Iterator
from typing import Annotated

from fastapi import Depends, HTTPException, Request, status
from fastapi.security import HTTPAuthorizationCredentials, HTTPBearer
from sqlalchemy.orm import Session

from service.config import Settings
from service.security import KeyRefusedError, Principal, Role, authenticate

log = logging.getLogger("narxwatch.auth")
bearer = HTTPBearer(auto_error=False, description="An API key: `Authorization: Bearer nw_…`")


async def get_settings(request: Request) -> Settings:
    # async: a plain attribute read needs no trip through the thread pool.
    return request.app.state.settings


def get_session(request: Request) -> Iterator[Session]:
    """One session per request; handlers commit, anything uncommitted is rolled back."""
    with request.app.state.sessions() as session:
        yield session


SettingsDep = Annotated[Settings, Depends(get_settings)]
SessionDep = Annotated[Session, Depends(get_session)]


def require(role: Role) -> Callable[..., Principal]:
    """A dependency admitting keys of ``role`` or a more powerful one."""

    def dependency(
        session: SessionDep,
        credentials: Annotated[HTTPAuthorizationCredentials | None, Depends(bearer)],
    ) -> Principal:
        if credentials is None:
            raise HTTPException(
                status.HTTP_401_UNAUTHORIZED,
                "missing API key: send the header 'Authorization: Bearer <key>'",
                headers={"WWW-Authenticate": "Bearer"},
            )
        try:
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
