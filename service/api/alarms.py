"""Alarms and the alarm rules of each structure: viewers read, admins acknowledge, resolve and set rules."""

from __future__ import annotations

import datetime as dt
from typing import Annotated

from fastapi import APIRouter, Query

from service.api.deps import Admin, SessionDep, SettingsDep, Viewer
from service.api.params import IdPath, utc
from service.domain import alarms
from service.domain.records import acquisition_limit
from service.schemas import (
    MAX_ID,
    MODE_NAME_LENGTH,
    MODE_NAME_PATTERN,
    AlarmAction,
    AlarmDetail,
    AlarmOut,
    AlarmPage,
    AlarmRules,
    AlarmRulesOut,
    AlarmState,
    RuleKind,
)

router = APIRouter(tags=["alarms"])

PAGE = 100


@router.get("/alarms")
def list_alarms(
    principal: Viewer,
    session: SessionDep,
    structure_id: Annotated[int | None, Query(ge=1, le=MAX_ID)] = None,
    state: AlarmState | None = None,
    rule_kind: RuleKind | None = None,
    fault_mode: Annotated[str | None, Query(max_length=MODE_NAME_LENGTH, pattern=MODE_NAME_PATTERN)] = None,
    start: Annotated[dt.datetime | None, Query(description="Opened at or after (ISO 8601 with zone)")] = None,
    end: Annotated[dt.datetime | None, Query(description="Opened before (ISO 8601 with zone)")] = None,
    cursor: Annotated[int | None, Query(ge=1, le=MAX_ID)] = None,
    limit: Annotated[int, Query(ge=1, le=1000)] = PAGE,
) -> AlarmPage:
    """The organisation's alarms, newest first, with filters and cursor pagination."""
    page = alarms.list_alarms(
        session,
        principal,
        structure_id=structure_id,
        state=state,
        rule_kind=rule_kind,
        fault_mode=fault_mode,
        start=utc(start, "start"),
        end=utc(end, "end"),
        cursor=cursor,
        limit=limit,
    )
    return AlarmPage.model_validate(page, from_attributes=True)


@router.get("/alarms/{alarm_id}")
def get_alarm(alarm_id: IdPath, principal: Viewer, session: SessionDep) -> AlarmDetail:
    """An alarm with every transition of its state, oldest first."""
    return AlarmDetail.model_validate(alarms.get_alarm(session, principal, alarm_id), from_attributes=True)


@router.post("/alarms/{alarm_id}/acknowledge")
def acknowledge_alarm(
    alarm_id: IdPath, principal: Admin, session: SessionDep, body: AlarmAction | None = None
) -> AlarmOut:
    """Someone is on it: an open alarm becomes acknowledged, with who, when and the note (optional)."""
    alarm = alarms.acknowledge(session, principal, alarm_id, body.note if body else "")
    return AlarmOut.model_validate(alarm, from_attributes=True)


@router.post("/alarms/{alarm_id}/resolve")
def resolve_alarm(
    alarm_id: IdPath, principal: Admin, session: SessionDep, body: AlarmAction | None = None
) -> AlarmOut:
    """Resolve an open or acknowledged alarm by hand (a note is optional); the rule then looks only
    at records acquired later."""
    alarm = alarms.resolve(session, principal, alarm_id, body.note if body else "")
    return AlarmOut.model_validate(alarm, from_attributes=True)


@router.get("/structures/{structure_id}/alarm-rules")
def get_alarm_rules(
    structure_id: IdPath, principal: Viewer, session: SessionDep, settings: SettingsDep
) -> AlarmRulesOut:
    """The structure's alarm rules (the defaults until an admin sets them) and the CUSUM's design."""
    rules = alarms.get_rules(session, principal, structure_id, acquisition_limit(settings))
    return AlarmRulesOut.model_validate(rules, from_attributes=True)


@router.put("/structures/{structure_id}/alarm-rules")
def set_alarm_rules(
    structure_id: IdPath, body: AlarmRules, principal: Admin, session: SessionDep, settings: SettingsDep
) -> AlarmRulesOut:
    """Replace the structure's alarm rules (kinds left out stop firing) and judge its history by them."""
    rules = alarms.set_rules(session, principal, structure_id, body, acquisition_limit(settings))
    return AlarmRulesOut.model_validate(rules, from_attributes=True)
