"""The dashboard's pages: server-rendered, charts drawn by plotly.js from figures built server-side."""

from __future__ import annotations

import datetime as dt
import re
from collections.abc import Callable
from pathlib import Path
from typing import Annotated, Any, get_args

import plotly
from fastapi import APIRouter, Depends, Form, HTTPException, Query, Request, status
from fastapi.responses import FileResponse, HTMLResponse, RedirectResponse, Response
from fastapi.templating import Jinja2Templates
from sqlalchemy.orm import Session

from models.errors import InputError
from recordfiles.quantities import SignalDeclaration, signal_label
from service.api.deps import SessionDep, SettingsDep
from service.api.params import IdPath, utc
from service.dashboard import figures, views
from service.dashboard.auth import (
    COOKIE,
    HOME,
    LOGIN,
    LoginDep,
    checked_form,
    csrf_token,
    safe_next,
    same_origin,
)
from service.domain import alarms
from service.domain.fleet import checked_standing
from service.domain.history import Status
from service.domain.logins import Login, close_login, open_login
from service.domain.records import acquisition_limit
from service.schemas import (
    MODE_NAME_LENGTH,
    MODE_NAME_PATTERN,
    NAME_PATTERN,
    NOTE_PATTERN,
    STRUCTURE_NAME_LENGTH,
)
from service.security import Principal, Role

HERE = Path(__file__).parent
PLOTLY_JS = Path(plotly.__file__).parent / "package_data" / "plotly.min.js"

templates = Jinja2Templates(directory=HERE / "templates")
templates.env.globals["plotly_version"] = plotly.__version__
router = APIRouter(prefix=HOME, include_in_schema=False)


def _when(moment: dt.datetime | None) -> str:
    return "—" if moment is None else moment.astimezone(dt.UTC).strftime("%Y-%m-%d %H:%M:%S UTC")


def _number(value: float | None, digits: int = 3) -> str:
    return "—" if value is None else f"{value:.{digits}g}"


def _in_unit(text: str, response: SignalDeclaration | None) -> str:
    """A figure of y or e named by ``text``, with the unit the structure declares its response in."""
    return signal_label(text, response, quantity=False)


templates.env.filters["when"] = _when
templates.env.filters["number"] = _number
templates.env.filters["in_unit"] = _in_unit
templates.env.filters["signal"] = signal_label


def render(
    request: Request, name: str, context: dict[str, Any], code: int = status.HTTP_200_OK
) -> HTMLResponse:
    headers = page_headers(uses_webgl(context.get("charts", {})))
    context = {"csrf": csrf_token(request)} | context
    return templates.TemplateResponse(request, name, context, status_code=code, headers=headers)


def page_headers(webgl: bool) -> dict[str, str]:
    """Every page's defences. Scripts come from this site only (plotly.js, dashboard.js; the
    figures travel as a JSON data block, which runs nothing), so injected markup cannot run code;
    no site may frame a page (clickjacking) and no cache may keep one (they show an
    organisation's data). Only pages with WebGL charts allow ``eval``: regl, plotly.js's WebGL
    layer, compiles its draw calls with ``new Function``. plotly.js sets inline styles, hence
    ``style-src 'unsafe-inline'`` (styles run no code)."""
    script_src = "'self' 'unsafe-eval'" if webgl else "'self'"
    policy = (
        f"default-src 'self'; script-src {script_src}; style-src 'self' 'unsafe-inline'; "
        "img-src 'self' data: blob:; object-src 'none'; base-uri 'none'; form-action 'self'; "
        "frame-ancestors 'none'"
    )
    return {
        "Content-Security-Policy": policy,
        "X-Frame-Options": "DENY",
        "Cache-Control": "no-store",
        "Referrer-Policy": "same-origin",
        "X-Content-Type-Options": "nosniff",
    }


def uses_webgl(charts: dict[str, figures.Figure]) -> bool:
    traces = (trace for figure in charts.values() for trace in figure["data"])
    return any(trace.get("type") == figures.WEBGL_TRACE for trace in traces)


@router.get("/static/plotly.min.js")
def plotly_js() -> FileResponse:
    """plotly.js as the installed ``plotly`` package ships it: nothing is fetched from elsewhere."""
    return FileResponse(
        PLOTLY_JS, media_type="text/javascript", headers={"Cache-Control": "public, max-age=86400"}
    )


@router.get("/login")
def login_form(
    request: Request, next_page: Annotated[str | None, Query(alias="next", max_length=2000)] = None
) -> HTMLResponse:
    return render(request, "login.html", {"next": safe_next(next_page), "error": None})


@router.post("/login", dependencies=[Depends(same_origin)])
def log_in(
    request: Request,
    session: SessionDep,
    settings: SettingsDep,
    api_key: Annotated[str, Form(max_length=200)],
    next_page: Annotated[str, Form(alias="next", max_length=2000)] = HOME,
) -> Response:
    lifetime = dt.timedelta(hours=settings.dashboard_session_hours)
    token = open_login(session, api_key, lifetime)
    if token is None:
        error = "That API key is not valid: it is unknown, malformed, revoked or expired."
        return render(request, "login.html", {"next": safe_next(next_page), "error": error}, 401)
    response = RedirectResponse(safe_next(next_page), status.HTTP_303_SEE_OTHER)
    response.set_cookie(
        COOKIE,
        token,
        max_age=int(lifetime.total_seconds()),
        path=HOME,
        secure=settings.session_cookie_secure,
        httponly=True,
        samesite="lax",
    )
    return response


@router.post("/logout", dependencies=[Depends(same_origin)])
def log_out(request: Request, session: SessionDep) -> Response:
    token = request.cookies.get(COOKIE)
    if token:
        close_login(session, token)
    response = RedirectResponse(LOGIN, status.HTTP_303_SEE_OTHER)
    response.delete_cookie(COOKIE, path=HOME)
    return response


@router.get("")
def fleet(
    request: Request,
    login: LoginDep,
    session: SessionDep,
    status_filter: Annotated[str | None, Query(alias="status", max_length=20)] = None,
    name: Annotated[str | None, Query(max_length=STRUCTURE_NAME_LENGTH, pattern=NAME_PATTERN)] = None,
    cursor: Annotated[str | None, Query(max_length=200)] = None,
) -> HTMLResponse:
    filters = views.FleetFilter(
        standing=checked_standing(status_filter), name=name or None, cursor=cursor or None
    )
    context = views.fleet_page(session, login.principal, filters)
    return render(request, "fleet.html", {"login": login} | context)


@router.get("/structures/{structure_id}")
def structure(
    request: Request,
    structure_id: IdPath,
    login: LoginDep,
    session: SessionDep,
    settings: SettingsDep,
    status_filter: Annotated[str | None, Query(alias="status", max_length=20)] = None,
    fault_mode: Annotated[str | None, Query(max_length=200)] = None,
    start: Annotated[str | None, Query(max_length=40)] = None,
    end: Annotated[str | None, Query(max_length=40)] = None,
    cursor: Annotated[str | None, Query(max_length=200)] = None,
) -> HTMLResponse:
    filters = views.HistoryFilter(
        status=_status(status_filter),
        fault_mode=_fault_mode(fault_mode),
        start=_moment(start, "from"),
        end=_moment(end, "to"),
        cursor=cursor or None,
    )
    limit = acquisition_limit(settings)
    context = views.structure_page(session, login.principal, structure_id, filters, limit)
    return render(request, "structure.html", {"login": login} | context)


@router.get("/records/{record_id}")
def record(
    request: Request,
    record_id: IdPath,
    login: LoginDep,
    session: SessionDep,
    mode: Annotated[str | None, Query(max_length=200)] = None,
) -> HTMLResponse:
    context = views.record_page(session, login.principal, record_id, _fault_mode(mode))
    return render(request, "record.html", {"login": login} | context)


@router.get("/refinements/{refinement_id}")
def refinement(request: Request, refinement_id: IdPath, login: LoginDep, session: SessionDep) -> HTMLResponse:
    context = views.refinement_page(session, login.principal, refinement_id)
    return render(request, "refinement.html", {"login": login} | context)


def _alarm_action(
    action: str, act: Callable[[Session, Principal, int, str], object]
) -> Callable[..., Response]:
    """The form route that acts on an alarm (``act``, a domain function of :mod:`service.domain.alarms`)
    with the note given and returns to the page it was sent from: acknowledging and resolving take the
    same form and differ only in what they do."""

    def act_on_alarm(
        alarm_id: IdPath,
        login: LoginDep,
        session: SessionDep,
        note: Annotated[str, Form(max_length=2000, pattern=NOTE_PATTERN)] = "",
        next_page: Annotated[str, Form(alias="next", max_length=2000)] = HOME,
    ) -> RedirectResponse:
        act(session, _acting(login, action), alarm_id, note)
        return RedirectResponse(safe_next(next_page), status.HTTP_303_SEE_OTHER)

    return act_on_alarm


for _action, _act in (("acknowledge", alarms.acknowledge), ("resolve", alarms.resolve)):
    router.post(
        f"/alarms/{{alarm_id}}/{_action}", dependencies=[Depends(checked_form)], name=f"{_action}_alarm"
    )(_alarm_action(_action, _act))


def _acting(login: Login, action: str) -> Principal:
    """The login's principal if it may act on alarms (admins, as in the API)."""
    if login.principal.role < Role.admin:
        raise HTTPException(
            status.HTTP_403_FORBIDDEN,
            f"to {action} an alarm, log in with an admin key; yours is '{login.principal.role.name}'",
        )
    return login.principal


def _status(value: str | None) -> Status | None:
    if not value:
        return None
    if value not in get_args(Status):
        raise InputError(f"status must be one of {', '.join(get_args(Status))}, not {value!r}")
    return value  # type: ignore[return-value]


def _fault_mode(value: str | None) -> str | None:
    if not value:
        return None
    if len(value) > MODE_NAME_LENGTH or not re.fullmatch(MODE_NAME_PATTERN, value):
        raise InputError(
            f"a fault mode name has at most {MODE_NAME_LENGTH} letters, digits, '_', '.' and '-' only"
        )
    return value


def _moment(value: str | None, name: str) -> dt.datetime | None:
    """A time from the filter form: ISO 8601, read as UTC when it has no zone (the form says UTC)."""
    if not value:
        return None
    try:
        moment = dt.datetime.fromisoformat(value)
    except ValueError:
        raise InputError(f"'{name}' is not a date and time; write it like 2026-11-21T10:00") from None
    return utc(moment.replace(tzinfo=dt.UTC) if moment.tzinfo is None else moment, name)
