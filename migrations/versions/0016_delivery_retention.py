"""deliveries under the retention: an index on the settled ones by organisation and age

Revision ID: 0016
Revises: 0015
Create Date: 2026-11-26 14:30:00.000000

The retention deletes an organisation's settled deliveries (delivered or failed) written before
its verdict horizon (``service.domain.retention``); ``ix_deliveries_settled``, partial on the
settled ones, lets each batch read only those, never the pending outbox nor other
organisations' log. Nothing is deleted by this revision.
"""

from __future__ import annotations

import sqlalchemy as sa
from alembic import op

revision = "0016"
down_revision = "0015"
branch_labels = None
depends_on = None

SETTLED = sa.text("status <> 'pending'")


def upgrade() -> None:
    op.create_index(
        "ix_deliveries_settled",
        "deliveries",
        ["organisation_id", "created_at"],
        sqlite_where=SETTLED,
        postgresql_where=SETTLED,
    )


def downgrade() -> None:
    op.drop_index("ix_deliveries_settled", table_name="deliveries")
