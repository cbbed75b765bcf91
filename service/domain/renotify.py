"""Open alarms nobody acknowledged are announced again ("alarm.renotified").

An alarm still open ``renotify_after_seconds`` after it opened, or after it was last announced
again, is announced again, then again after as long. The job workers' notification sweep runs
this before it sweeps the deliveries; each alarm is claimed by a compare-and-set on
``renotified_at``, so however many sweepers look at once it is announced once per period.
"""

from __future__ import annotations

import datetime as dt

from sqlalchemy import func, select, update
from sqlalchemy.orm import Session

from service.domain import notifications
from service.domain.alarms import LOADED, alarm_payload
from service.tables import Alarm, Structure, utcnow

BATCH = 200  # alarms announced again per sweep at most; the next sweep takes the rest


def sweep(session: Session, after: dt.timedelta, now: dt.datetime | None = None) -> int:
    """Announce again every alarm open and unannounced for ``after``; the number announced.
    Each in a transaction of its own (the announcement's deliveries with it); commits."""
    if after <= dt.timedelta(0):
        return 0
    now = now or utcnow()
    last = func.coalesce(Alarm.renotified_at, Alarm.opened_at)
    due = select(Alarm.id, Alarm.renotified_at).where(Alarm.state == "open", last <= now - after)
    found = session.execute(due.order_by(Alarm.id).limit(BATCH)).all()
    session.rollback()
    announced = 0
    for alarm_id, previous in found:
        unchanged = Alarm.renotified_at.is_(None) if previous is None else Alarm.renotified_at == previous
        claimed = (
            update(Alarm.__table__)
            .where(Alarm.id == alarm_id, Alarm.state == "open", unchanged)
            .values(renotified_at=now)
        )
        if session.execute(claimed).rowcount == 1:
            alarm = session.get(Alarm, alarm_id, options=list(LOADED), populate_existing=True)
            assert alarm is not None
            organisation_id = session.scalar(
                select(Structure.organisation_id).where(Structure.id == alarm.structure_id)
            )
            payload = alarm_payload(alarm)
            notifications.notify(session, organisation_id, "alarm.renotified", payload)
            announced += 1
        session.commit()
    return announced
