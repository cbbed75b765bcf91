"""An organisation's retention policy, for its admins: how long signals and verdicts are kept."""

from __future__ import annotations

from fastapi import APIRouter

from service.api.deps import Admin, SessionDep
from service.domain import retention
from service.schemas import Retention, RetentionOut

router = APIRouter(prefix="/retention", tags=["retention"])


@router.get("")
def get_retention(principal: Admin, session: SessionDep) -> RetentionOut:
    """How long your organisation keeps its records' signals and its verdicts."""
    return RetentionOut.model_validate(
        retention.policy(session, principal.organisation_id), from_attributes=True
    )


@router.put("")
def set_retention(body: Retention, principal: Admin, session: SessionDep) -> RetentionOut:
    """Set both periods, in days of acquisition time (null: forever; signals no longer than
    verdicts). The next pruning applies them: signals are dropped (the record stays, saying
    so), then verdicts and the records left with neither are deleted."""
    return RetentionOut.model_validate(retention.set_policy(session, principal, body), from_attributes=True)
