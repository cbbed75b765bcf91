"""Notifications: the events of an organisation told to its webhooks and e-mail subscriptions.

``notify`` is called in the transaction of the change it announces and only adds rows, one
``Delivery`` per webhook or subscription that wants the event: committed with the change, or not
at all. The deliveries are an outbox: a sweep (every backend's worker runs it, next to the
schedules' sweep) claims those due with a compare-and-set and defers one ``deliver`` job each,
so no job is queued for a change that was rolled back, and every committed one gets its jobs.

A job makes one attempt, counted before it is made, and records how it went: delivered, or due
again after an exponential backoff (``delivery_first_retry_seconds`` doubled per attempt), or,
after ``delivery_max_attempts``, failed. A job whose worker died runs again (the backends
redeliver it) and attempts again with the same ``Idempotency-Key``: at least once, and a
receiver that keeps the keys it has seen acts once.
"""

from __future__ import annotations

import datetime as dt
import logging
import uuid
from collections.abc import Callable
from typing import Any

from pydantic_core import to_jsonable_python
from sqlalchemy import select, update
from sqlalchemy.orm import Session

from service import senders
from service.config import Settings
from service.tables import Delivery, EmailSubscription, Webhook, utcnow

EVENTS = ("alarm.opened", "alarm.acknowledged", "alarm.resolved", "alarm.renotified")
DELIVER = "deliver"
# A claimed delivery whose job has not recorded an attempt within this time (the job lost, not
# merely redelivered: the backends do that sooner) is claimed again by a later sweep.
CLAIM_LEASE = dt.timedelta(minutes=15)
SWEEP_BATCH = 200  # deliveries claimed per sweep at most; the next sweep takes the rest

# defer(session, task_name, organisation_id, **task_args), in the session's transaction; the job's id
Defer = Callable[..., int]

log = logging.getLogger("narxwatch.notifications")


def notify(session: Session, organisation_id: int, event: str, payload: dict[str, Any]) -> None:
    """Announce ``event`` with ``payload`` (JSON-ready; datetimes are written as ISO 8601) to
    every webhook and e-mail subscription of the organisation that wants it, in the caller's
    transaction: nothing is sent before it commits, and nothing at all if it rolls back."""
    if event not in EVENTS:
        raise ValueError(f"unknown event {event!r}; the events are {', '.join(EVENTS)}")
    document = to_jsonable_python(payload)
    webhooks = session.scalars(select(Webhook).where(Webhook.organisation_id == organisation_id))
    subscriptions = session.scalars(
        select(EmailSubscription).where(EmailSubscription.organisation_id == organisation_id)
    )
    targets = [{"webhook_id": w.id} for w in webhooks if event in w.events]
    targets += [{"email_subscription_id": s.id} for s in subscriptions if event in s.events]
    for target in targets:
        session.add(
            Delivery(
                organisation_id=organisation_id,
                key=str(uuid.uuid4()),
                event=event,
                payload=document,
                next_attempt_at=utcnow(),
                **target,
            )
        )
    session.flush()


def sweep(session: Session, defer: Defer, now: dt.datetime | None = None) -> int:
    """Defer a ``deliver`` job for each delivery due at ``now``; the number deferred.

    Reads first (a sweep that finds nothing takes no write lock), then claims each delivery in a
    transaction of its own: its due time moves on by ``CLAIM_LEASE`` if it is still the one read
    (another sweeper may have claimed it since), and its job carries the new value, its claim.
    """
    now = now or utcnow()
    due = select(Delivery.id, Delivery.organisation_id, Delivery.next_attempt_at).where(
        Delivery.status == "pending", Delivery.next_attempt_at <= now
    )
    found = session.execute(due.order_by(Delivery.next_attempt_at).limit(SWEEP_BATCH)).all()
    session.rollback()
    deferred = 0
    for delivery_id, organisation_id, due_at in found:
        claim = now + CLAIM_LEASE
        moved = (
            update(Delivery.__table__)
            .where(
                Delivery.id == delivery_id, Delivery.status == "pending", Delivery.next_attempt_at == due_at
            )
            .values(next_attempt_at=claim)
        )
        if session.execute(moved).rowcount == 1:
            defer(session, DELIVER, organisation_id, delivery_id=delivery_id, claim=claim.isoformat())
            deferred += 1
        session.commit()
    return deferred


def deliver(session: Session, settings: Settings, delivery_id: int, claim: str) -> None:
    """One attempt at a delivery the sweep claimed (``claim``: the due time it set); commits.

    A job whose claim is no longer the delivery's (delivered meanwhile, or claimed again after
    its lease) does nothing. The attempt is counted before it is made, so that the log shows an
    attempt its worker died in; no transaction is open while the network is used.
    """
    claimed = dt.datetime.fromisoformat(claim)
    delivery = session.get(Delivery, delivery_id)
    if delivery is None or delivery.status != "pending" or delivery.next_attempt_at != claimed:
        log.info("delivery %s: claim %s no longer holds; nothing to do", delivery_id, claim)
        session.rollback()
        return
    holds = (Delivery.id == delivery_id, Delivery.status == "pending", Delivery.next_attempt_at == claimed)
    message = senders.Message(delivery.key, delivery.event, delivery.created_at, delivery.payload)
    attempt = delivery.attempts + 1
    if delivery.webhook_id is not None:
        webhook = session.get(Webhook, delivery.webhook_id)
        assert webhook is not None  # deleting a webhook deletes its deliveries
        url, secret = webhook.url, webhook.secret

        def send() -> senders.Outcome:
            return senders.post_webhook(url, secret, delivery_id, message, settings)
    else:
        subscription = session.get(EmailSubscription, delivery.email_subscription_id)
        assert subscription is not None
        addresses = list(subscription.addresses)

        def send() -> senders.Outcome:
            return senders.send_email(addresses, message, settings)

    session.execute(update(Delivery.__table__).where(*holds).values(attempts=attempt))
    session.commit()
    outcome = send()
    now = utcnow()
    values: dict[str, Any] = {"last_status_code": outcome.status_code, "last_error": outcome.error}
    if outcome.delivered:
        values |= {"status": "delivered", "delivered_at": now}
    elif attempt >= settings.delivery_max_attempts:
        values |= {"status": "failed"}
        log.error("delivery %s failed for good after %s attempt(s): %s", delivery_id, attempt, outcome.error)
    else:
        delay = dt.timedelta(seconds=settings.delivery_first_retry_seconds * 2 ** (attempt - 1))
        values |= {"next_attempt_at": now + delay}
        log.warning(
            "delivery %s failed (attempt %s), tried again in %s: %s",
            delivery_id,
            attempt,
            delay,
            outcome.error,
        )
    session.execute(update(Delivery.__table__).where(*holds).values(**values))
    session.commit()
