"""jobs know their organisation; distributed jobs' errors; records that could not be inspected

Revision ID: 0007
Revises: 0005
Create Date: 2026-11-23 16:40:00.000000

Embedded jobs queued before this revision keep a null organisation: they run as before, and
``GET /jobs`` lists them to no one.
"""

from __future__ import annotations

import sqlalchemy as sa
from alembic import op

revision = "0007"
down_revision = "0006"
branch_labels = None
depends_on = None


def upgrade() -> None:
    with op.batch_alter_table("jobs", schema=None) as batch_op:
        batch_op.add_column(sa.Column("organisation_id", sa.Integer(), nullable=True))
        batch_op.create_foreign_key(
            "jobs_organisation_id_fkey", "organisations", ["organisation_id"], ["id"], ondelete="CASCADE"
        )
        batch_op.create_index("ix_jobs_organisation_id", ["organisation_id"], unique=False)
    op.create_table(
        "job_errors",
        sa.Column("job_id", sa.BigInteger(), autoincrement=False, nullable=False),
        sa.Column("error", sa.Text(), nullable=False),
        sa.Column("at", sa.DateTime(timezone=True), nullable=False),
        sa.PrimaryKeyConstraint("job_id"),
    )
    op.create_table(
        "inspection_failures",
        sa.Column("id", sa.Integer(), nullable=False),
        sa.Column("record_id", sa.Integer(), nullable=False),
        sa.Column("model_set", sa.String(length=200), nullable=False),
        sa.Column("reason", sa.Text(), nullable=False),
        sa.Column("created_at", sa.DateTime(timezone=True), nullable=False),
        sa.ForeignKeyConstraint(["record_id"], ["records.id"], ondelete="CASCADE"),
        sa.PrimaryKeyConstraint("id"),
        sa.UniqueConstraint("record_id", "model_set"),
    )
    with op.batch_alter_table("inspection_failures", schema=None) as batch_op:
        batch_op.create_index("ix_inspection_failures_record_id", ["record_id"], unique=False)


def downgrade() -> None:
    with op.batch_alter_table("inspection_failures", schema=None) as batch_op:
        batch_op.drop_index("ix_inspection_failures_record_id")
    op.drop_table("inspection_failures")
    op.drop_table("job_errors")
    with op.batch_alter_table("jobs", schema=None) as batch_op:
        batch_op.drop_index("ix_jobs_organisation_id")
        batch_op.drop_constraint("jobs_organisation_id_fkey", type_="foreignkey")
        batch_op.drop_column("organisation_id")
