"""An organisation's webhooks and e-mail subscriptions, for its admins, with their delivery logs."""

from __future__ import annotations

from typing import Annotated

from fastapi import APIRouter, Query, Response, status
from sqlalchemy.orm import Session

from service.api.deps import Admin, SessionDep, SettingsDep
from service.api.params import IdPath
from service.domain import notifications
from service.schemas import (
    MAX_ID,
    DeliveryOut,
    DeliveryPage,
    EmailSubscriptionCreate,
    EmailSubscriptionOut,
    WebhookCreate,
    WebhookOut,
)
from service.tables import Delivery, EmailSubscription, Webhook

router = APIRouter(tags=["notifications"])

PAGE = 100
Cursor = Annotated[int | None, Query(ge=1, le=MAX_ID)]
Limit = Annotated[int, Query(ge=1, le=1000)]


@router.post("/webhooks", status_code=status.HTTP_201_CREATED)
def create_webhook(
    body: WebhookCreate, principal: Admin, session: SessionDep, settings: SettingsDep
) -> WebhookOut:
    """Tell ``url`` of ``events``: a JSON POST signed with ``secret`` (header
    ``Narxwatch-Signature: t=<unix time>,v1=<hex HMAC-SHA256 of "t.body">``), with an
    ``Idempotency-Key`` the same on every attempt; retried with backoff until a 2xx answer. The
    URL must be http(s) and resolve to public addresses. The secret is never shown again."""
    return _webhook_out(notifications.create_webhook(session, principal, body, settings))


@router.get("/webhooks")
def list_webhooks(principal: Admin, session: SessionDep) -> list[WebhookOut]:
    return [_webhook_out(webhook) for webhook in notifications.list_webhooks(session, principal)]


@router.delete("/webhooks/{webhook_id}", status_code=status.HTTP_204_NO_CONTENT)
def delete_webhook(webhook_id: IdPath, principal: Admin, session: SessionDep) -> Response:
    """Delete a webhook; its pending deliveries are dropped with it."""
    return _deleted(session, notifications.get_webhook(session, principal, webhook_id))


@router.get("/webhooks/{webhook_id}/deliveries")
def webhook_deliveries(
    webhook_id: IdPath, principal: Admin, session: SessionDep, cursor: Cursor = None, limit: Limit = PAGE
) -> DeliveryPage:
    """The webhook's deliveries, newest first: attempts, last status code and error."""
    return _deliveries(session, notifications.get_webhook(session, principal, webhook_id), cursor, limit)


@router.post("/email-subscriptions", status_code=status.HTTP_201_CREATED)
def create_email_subscription(
    body: EmailSubscriptionCreate, principal: Admin, session: SessionDep, settings: SettingsDep
) -> EmailSubscriptionOut:
    """Tell ``addresses`` of ``events`` by e-mail through the server's SMTP relay (409 when the
    server has none), retried with backoff like webhooks."""
    subscription = notifications.create_email_subscription(session, principal, body, settings)
    return EmailSubscriptionOut.model_validate(subscription, from_attributes=True)


@router.get("/email-subscriptions")
def list_email_subscriptions(principal: Admin, session: SessionDep) -> list[EmailSubscriptionOut]:
    return [
        EmailSubscriptionOut.model_validate(subscription, from_attributes=True)
        for subscription in notifications.list_email_subscriptions(session, principal)
    ]


@router.delete("/email-subscriptions/{subscription_id}", status_code=status.HTTP_204_NO_CONTENT)
def delete_email_subscription(subscription_id: IdPath, principal: Admin, session: SessionDep) -> Response:
    return _deleted(session, notifications.get_email_subscription(session, principal, subscription_id))


@router.get("/email-subscriptions/{subscription_id}/deliveries")
def email_deliveries(
    subscription_id: IdPath, principal: Admin, session: SessionDep, cursor: Cursor = None, limit: Limit = PAGE
) -> DeliveryPage:
    subscription = notifications.get_email_subscription(session, principal, subscription_id)
    return _deliveries(session, subscription, cursor, limit)


def _webhook_out(webhook: Webhook) -> WebhookOut:
    return WebhookOut.model_validate(webhook, from_attributes=True)


def _deleted(session: Session, target: Webhook | EmailSubscription) -> Response:
    """Delete a notification's target with its pending deliveries: 204."""
    notifications.delete_target(session, target)
    return Response(status_code=status.HTTP_204_NO_CONTENT)


def _deliveries(
    session: Session, target: Webhook | EmailSubscription, cursor: int | None, limit: int
) -> DeliveryPage:
    """A page of the target's deliveries, newest first, older than ``cursor``."""
    found = notifications.deliveries(session, target, limit + 1, cursor)
    page = found[:limit]
    return DeliveryPage(
        items=[_delivery_out(delivery) for delivery in page],
        next_cursor=page[-1].id if len(found) > limit else None,
    )


def _delivery_out(delivery: Delivery) -> DeliveryOut:
    out = DeliveryOut.model_validate(delivery, from_attributes=True)
    return out if delivery.status == "pending" else out.model_copy(update={"next_attempt_at": None})
