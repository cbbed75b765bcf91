"""The dashboard: fleet, structure, record and refinement pages under /dashboard."""

from __future__ import annotations

from fastapi import FastAPI, Request
from fastapi.responses import HTMLResponse, RedirectResponse
from fastapi.staticfiles import StaticFiles

from service.dashboard.auth import COOKIE, HOME, NotLoggedInError
from service.dashboard.pages import HERE, render, router


def install(app: FastAPI) -> None:
    app.include_router(router)  # before the static mount: plotly.js is a route under /static
    app.mount(f"{HOME}/static", StaticFiles(directory=HERE / "static"), name="dashboard-static")

    @app.exception_handler(NotLoggedInError)
    async def to_login(_: Request, exc: NotLoggedInError) -> RedirectResponse:
        response = RedirectResponse(exc.location, status_code=303)
        response.delete_cookie(COOKIE, path=HOME)  # stale or forged: the browser need not send it again
        return response


def is_dashboard(request: Request) -> bool:
    return request.url.path == HOME or request.url.path.startswith(HOME + "/")


def error_page(request: Request, code: int, message: str) -> HTMLResponse:
    """An error as a page a person reads, with the way back; the status code stays the API's."""
    return render(request, "error.html", {"login": None, "code": code, "message": message}, code)
