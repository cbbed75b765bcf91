"""records of several response channels, and their verdicts

Revision ID: 0015
Revises: 0014
Create Date: 2026-11-26 01:30:00.000000

A record of several sensors stores y as an (N, K) array and its channels' names in
``records.channels`` (null for a record of one response, as every record stored before). A vector
inspection has no whiteness test that detects, so its verdicts have no
``q_critical_detection``. Downgrading is refused while records of several channels are stored
(the schema before this revision cannot hold them, nor their verdicts): deleting them here would
leave their alarms, refinements and counts behind.
"""

from __future__ import annotations

import sqlalchemy as sa
from alembic import op
from sqlalchemy.dialects.postgresql import JSONB

revision = "0015"
down_revision = "0014"
branch_labels = None
depends_on = None


def upgrade() -> None:
    op.add_column(
        "records", sa.Column("channels", sa.JSON().with_variant(JSONB(), "postgresql"), nullable=True)
    )
    with op.batch_alter_table("verdicts", schema=None) as batch_op:
        batch_op.alter_column("q_critical_detection", existing_type=sa.Float(), nullable=True)


def downgrade() -> None:
    # Neither SQL NULL nor JSON's null (records of one response stored before 0017) compares as
    # different from 'null'.
    several = op.get_bind().execute(sa.text("SELECT COUNT(*) FROM records WHERE channels <> 'null'")).scalar()
    if several:
        raise RuntimeError(
            f"{several} record(s) of several channels are stored, which the schema before revision 0015 "
            "cannot hold: delete them (and their structures' vector models) before downgrading"
        )
    with op.batch_alter_table("verdicts", schema=None) as batch_op:
        batch_op.alter_column("q_critical_detection", existing_type=sa.Float(), nullable=False)
    with op.batch_alter_table("records") as batch:
        batch.drop_column("channels")
