"""where each structure's alarm rules stand, kept on write

Revision ID: 0023
Revises: 0022
Create Date: 2026-11-30 09:00:00.000000

The alarm rules ran after every verdict over the structure's newest verdicts read again from its
history; ``alarm_states`` keeps, in one row per structure, what each rule needs to go on from the
newest verdict it counted (``service.domain.alarms``), written in each verdict's transaction. The
table starts empty: a structure's row is built from its history the first time its rules run
after this revision, from the verdicts the rules read before, so its alarms go on from there.
"""

from __future__ import annotations

import sqlalchemy as sa
from alembic import op

revision = "0023"
down_revision = "0022"
branch_labels = None
depends_on = None


def upgrade() -> None:
    op.create_table(
        "alarm_states",
        sa.Column("structure_id", sa.Integer(), autoincrement=False, nullable=False),
        sa.Column("state", sa.Text(), nullable=False),
        sa.ForeignKeyConstraint(["structure_id"], ["structures.id"], ondelete="CASCADE"),
        sa.PrimaryKeyConstraint("structure_id"),
    )


def downgrade() -> None:
    op.drop_table("alarm_states")
