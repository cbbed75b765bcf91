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
from typing import Any, get_args

from pydantic_core import to_jsonable_python
from sqlalchemy import func, select, update
from sqlalchemy.orm import Session

from service import sealing, senders
from service.config import Settings
from service.domain.errors import ConflictError, NotFoundError
from service.schemas import EmailSubscriptionCreate, Event, WebhookCreate
from service.security import Principal
from service.tables import Delivery, EmailSubscription, Webhook, utcnow

EVENTS: tuple[str, ...] = get_args(Event)
# Targets an organisation may have of each kind: every event costs a delivery per target.
MAX_TARGETS = 20
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
    attempt = delivery.attempts + 1
    send = _sender(session, delivery, settings)
    if send is None:  # its webhook or subscription was deleted since it was read (and the delivery with it)
        session.rollback()
        return
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


def _sender(session: Session, delivery: Delivery, settings: Settings) -> Callable[[], senders.Outcome] | None:
    """The attempt at ``delivery``, with everything it needs read now (no transaction stays open
    while it runs); None if its target is gone."""
    message = senders.Message(delivery.key, delivery.event, delivery.created_at, delivery.payload)
    if delivery.webhook_id is not None:
        webhook = session.get(Webhook, delivery.webhook_id)
        if webhook is None:
            return None
        try:
            secret = sealing.unseal(webhook.secret, settings)
        except sealing.UnsealError as exc:
            refused = senders.Outcome(False, None, str(exc))
            return lambda: refused
        url, delivery_id = webhook.url, delivery.id
        return lambda: senders.post_webhook(url, secret, delivery_id, message, settings)
    subscription = session.get(EmailSubscription, delivery.email_subscription_id)
    if subscription is None:
        return None
    addresses = list(subscription.addresses)
    return lambda: senders.send_email(addresses, message, settings)


# --- webhooks and e-mail subscriptions ------------------------------------------------------------


def create_webhook(
    session: Session, principal: Principal, body: WebhookCreate, settings: Settings
) -> Webhook:
    """A webhook of the caller's organisation; its URL must be one a delivery may go to (http or
    https, a host of public addresses unless settings allow others: ``senders.check_webhook_url``)."""
    senders.check_webhook_url(body.url, settings)
    _check_room(session, Webhook, principal.organisation_id, "webhooks")
    webhook = Webhook(
        organisation_id=principal.organisation_id,
        url=body.url,
        secret=sealing.seal(body.secret, settings),
        events=body.events,
    )
    session.add(webhook)
    session.flush()
    return webhook


def reseal_secrets(session: Session, settings: Settings) -> int:
    """Seal every webhook's secret again under the first of the server's keys (a rotation's
    last step); the number resealed. A secret no key opens is a ConflictError naming its webhook."""
    webhooks = session.scalars(select(Webhook).order_by(Webhook.id)).all()
    for webhook in webhooks:
        try:
            webhook.secret = sealing.reseal(webhook.secret, settings)
        except sealing.UnsealError as exc:
            raise ConflictError(f"webhook {webhook.id}: {exc}") from exc
    return len(webhooks)


def create_email_subscription(
    session: Session, principal: Principal, body: EmailSubscriptionCreate, settings: Settings
) -> EmailSubscription:
    if settings.smtp_host is None:
        raise ConflictError("this server sends no e-mail: its operator has set no NARXWATCH_SMTP_HOST")
    _check_room(session, EmailSubscription, principal.organisation_id, "e-mail subscriptions")
    subscription = EmailSubscription(
        organisation_id=principal.organisation_id, addresses=body.addresses, events=body.events
    )
    session.add(subscription)
    session.flush()
    return subscription


def _check_room(
    session: Session, kind: type[Webhook | EmailSubscription], organisation_id: int, name: str
) -> None:
    count = session.scalar(
        select(func.count()).select_from(kind).where(kind.organisation_id == organisation_id)
    )
    if (count or 0) >= MAX_TARGETS:
        raise ConflictError(f"an organisation has at most {MAX_TARGETS} {name}: delete one first")


def list_webhooks(session: Session, principal: Principal) -> list[Webhook]:
    query = select(Webhook).where(Webhook.organisation_id == principal.organisation_id).order_by(Webhook.id)
    return list(session.scalars(query))


def list_email_subscriptions(session: Session, principal: Principal) -> list[EmailSubscription]:
    query = select(EmailSubscription).where(EmailSubscription.organisation_id == principal.organisation_id)
    return list(session.scalars(query.order_by(EmailSubscription.id)))


def get_webhook(session: Session, principal: Principal, webhook_id: int) -> Webhook:
    """One of the caller's organisation's webhooks; another's is as unknown as a missing one."""
    webhook = session.get(Webhook, webhook_id)
    if webhook is None or webhook.organisation_id != principal.organisation_id:
        raise NotFoundError("webhook", webhook_id)
    return webhook


def get_email_subscription(session: Session, principal: Principal, subscription_id: int) -> EmailSubscription:
    subscription = session.get(EmailSubscription, subscription_id)
    if subscription is None or subscription.organisation_id != principal.organisation_id:
        raise NotFoundError("e-mail subscription", subscription_id)
    return subscription


def delete_target(session: Session, target: Webhook | EmailSubscription) -> None:
    """Delete a webhook or subscription, and with it its deliveries, pending ones included."""
    session.delete(target)
    session.flush()


def deliveries(
    session: Session, target: Webhook | EmailSubscription, limit: int, before: int | None
) -> list[Delivery]:
    """A target's deliveries, newest first, older than ``before``."""
    column = Delivery.webhook_id if isinstance(target, Webhook) else Delivery.email_subscription_id
    query = select(Delivery).where(column == target.id)
    if before is not None:
        query = query.where(Delivery.id < before)
    return list(session.scalars(query.order_by(Delivery.id.desc()).limit(limit)))
