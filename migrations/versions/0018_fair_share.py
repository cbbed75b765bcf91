"""jobs of the embedded backend: a priority for each organisation's fair share of the workers

Revision ID: 0018
Revises: 0017
Create Date: 2026-11-26 15:00:00.000000

A job is queued with priority −n, n being its organisation's jobs waiting then, and claimed by
the highest priority first, then the oldest (``service.jobs``: fair share); ``ix_jobs_waiting``
counts an organisation's waiting jobs without reading the others'. Jobs queued before keep
priority 0, and are taken first, in the order they were queued.
"""

from __future__ import annotations

import sqlalchemy as sa
from alembic import op

revision = "0018"
down_revision = "0017"
branch_labels = None
depends_on = None


def upgrade() -> None:
    with op.batch_alter_table("jobs") as batch:
        batch.add_column(sa.Column("priority", sa.Integer(), server_default="0", nullable=False))
    op.create_index("ix_jobs_waiting", "jobs", ["organisation_id", "status"])


def downgrade() -> None:
    op.drop_index("ix_jobs_waiting", table_name="jobs")
    with op.batch_alter_table("jobs") as batch:
        batch.drop_column("priority")
