"""Who is logged in to the dashboard, from the session cookie; visitors without one are sent to log in."""

from __future__ import annotations

import hashlib
import hmac
from typing import Annotated
from urllib.parse import quote, urlsplit

from fastapi import Depends, Form, HTTPException, Request, status

from service.api.deps import SessionDep
from service.domain.logins import Login, find_login

COOKIE = "narxwatch_session"
HOME = "/dashboard"
LOGIN = "/dashboard/login"


class NotLoggedInError(Exception):
    """Raised for a page asked for without a valid login; answered with a redirect to the login page."""

    def __init__(self, wanted: str) -> None:
        super().__init__(wanted)
        self.wanted = wanted

    @property
    def location(self) -> str:
        return f"{LOGIN}?next={quote(self.wanted, safe='')}"


def current_login(request: Request, session: SessionDep) -> Login:
    token = request.cookies.get(COOKIE)
    login = find_login(session, token) if token else None
    if login is None:
        query = f"?{request.url.query}" if request.url.query else ""
        raise NotLoggedInError(request.url.path + query)
    return login


LoginDep = Annotated[Login, Depends(current_login)]


def same_origin(request: Request) -> None:
    """Refuse a form post sent from another site (the cookie is SameSite=Lax; this is the second lock)."""
    origin = request.headers.get("origin")
    if origin is not None and origin != f"{request.url.scheme}://{request.url.netloc}":
        raise HTTPException(status.HTTP_403_FORBIDDEN, "this form can only be sent from the dashboard itself")


def csrf_token(request: Request) -> str:
    """The token the page's forms carry (:func:`form_token` of the request's login)."""
    return form_token(request.cookies.get(COOKIE, ""))


def form_token(session_token: str) -> str:
    """A login's form token: a keyed hash of its session token, so a page of another site cannot
    know it, and nothing needs storing. A third lock besides SameSite and the Origin check, which
    some clients leave out."""
    return hmac.new(session_token.encode(), b"narxwatch dashboard form", hashlib.sha256).hexdigest()


def checked_form(request: Request, csrf: Annotated[str, Form(max_length=100)] = "") -> None:
    """Refuse a form post from another site or without this login's token."""
    same_origin(request)
    if not hmac.compare_digest(csrf, csrf_token(request)):
        raise HTTPException(
            status.HTTP_403_FORBIDDEN,
            "this form has expired or was not sent from the dashboard: reload the page",
        )


def safe_next(target: str | None) -> str:
    """Where to go after logging in: a dashboard page of this site, never another site."""
    if not target:
        return HOME
    parts = urlsplit(target)
    if parts.scheme or parts.netloc or not (parts.path == HOME or parts.path.startswith(HOME + "/")):
        return HOME
    return target
