"""the records a refinement was fitted and judged on

Revision ID: 0008
Revises: 0007
Create Date: 2026-11-23 20:30:00.000000

A refinement may be fitted on several records and judged on others, whole. Each refinement
stored before this revision was fitted on its one ``record_id`` (and judged on a part of it).
"""

from __future__ import annotations

import sqlalchemy as sa
from alembic import op

revision = "0008"
down_revision = "0007"
branch_labels = None
depends_on = None


def upgrade() -> None:
    op.create_table(
        "refinement_records",
        sa.Column("refinement_id", sa.Integer(), nullable=False),
        sa.Column("record_id", sa.Integer(), nullable=False),
        sa.Column("role", sa.String(length=16), nullable=False),
        sa.Column("position", sa.Integer(), nullable=False),
        sa.ForeignKeyConstraint(["record_id"], ["records.id"], ondelete="CASCADE"),
        sa.ForeignKeyConstraint(["refinement_id"], ["refinements.id"], ondelete="CASCADE"),
        sa.PrimaryKeyConstraint("refinement_id", "record_id"),
    )
    with op.batch_alter_table("refinement_records", schema=None) as batch_op:
        batch_op.create_index("ix_refinement_records_record_id", ["record_id"], unique=False)
    op.execute(
        "INSERT INTO refinement_records (refinement_id, record_id, role, position) "
        "SELECT id, record_id, 'estimation', 0 FROM refinements"
    )


def downgrade() -> None:
    with op.batch_alter_table("refinement_records", schema=None) as batch_op:
        batch_op.drop_index("ix_refinement_records_record_id")
    op.drop_table("refinement_records")
